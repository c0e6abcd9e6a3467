"""benchmarks/genesis_stiffness_profile.py: one body's E scaled, the rest true, scored.

On a scene that mosiv-synth made with warp-mpm (its own laws, multi-field contact, grid 24, 30
substeps), the same model reproduces gt/points.npz exactly at the true E, so the factor 1 fits
best, with a Chamfer of 0, and every other factor leaves an error on the scaled body. The
report gathers the rows, writes the section and the plot.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from mosiv_framework.pipeline.run import generate_scene
from mosiv_framework.recipes import load_recipe
from mosiv_framework.testing.pytest_plugin import require_simulator
from mosiv_framework.testing.scripts import load_script

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "benchmarks" / "genesis_stiffness_profile.py"
RECIPE = ROOT / "recipes" / "diagnose_small.yaml"
MODEL = ["--laws", "own", "--contact", "multi_field", "--grid", "24", "--substeps", "30"]


@pytest.fixture(scope="module")
def bench():
    return load_script(SCRIPT)


@pytest.fixture(scope="module")
def measured(bench, tmp_path_factory):
    require_simulator("warp-mpm")
    root = tmp_path_factory.mktemp("stiffness")
    overrides = [
        f"scene.path={root / 'suite' / 'E-P'}",
        "scene.source.materials=elastic,plasticine",
        "scene.source.n_frames=6",
        "scene.source.observed_frames=4",
        "scene.source.collision_frame=3",
        "scene.generate=if-missing",
    ]
    generate_scene(load_recipe(RECIPE, overrides).scene)
    argv = ["--scenes", str(root / "suite"), "--out", str(root / "out"), "--recipe", str(RECIPE)]
    argv += [*MODEL, "--device", "cpu", "--factors", "0.25", "1", "4", "--emd-samples", "64"]
    assert bench.main(argv) == 0
    rows = json.loads((root / "out" / "stiffness_profile.json").read_text())["rows"]
    return root, argv, rows


def test_the_true_stiffness_fits_best_where_the_model_is_the_generators(bench, measured):
    _, _, rows = measured
    assert {(r["body"], r["material"]) for r in rows} == {(1, "elastic"), (2, "plasticine")}
    assert {r["factor"] for r in rows} == {0.25, 1.0, 4.0}
    for (model, scene, body), curve in bench.by_body(rows).items():
        assert model == "own/multi_field/g24/s30" and scene == "E-P"
        assert curve[1.0]["observed_cd"] < 1e-6 and curve[1.0]["future_cd"] < 1e-6, body
        for factor in (0.25, 4.0):
            row = curve[factor]
            assert "diverged" not in row
            assert row["observed_cd"] + row["future_cd"] > 1e-3, (body, factor, row)
        assert bench.body_summary(curve)["best_factor"] == 1.0


def test_a_rerun_measures_nothing_again_and_the_report_writes_section_and_plot(bench, measured):
    root, argv, rows = measured
    assert bench.main(argv) == 0
    again = json.loads((root / "out" / "stiffness_profile.json").read_text())["rows"]
    assert again == rows
    results = root / "docs" / "RESULTS.md"
    results.parent.mkdir()
    results.write_text("# Results\n\n## Model error on Genesis scenes\n\nkept\n\n"
                       "## Choosing the stress on Genesis scenes\n\nkept too\n")  # fmt: skip
    report = ["--out", str(root / "out"), "--report", "--write-results", str(results)]
    assert bench.main(report) == 0
    text = results.read_text()
    assert text.index("## Model error") < text.index("## Stiffness profile on Genesis scenes")
    assert text.index("## Stiffness profile") < text.index("## Choosing the stress")
    assert "| own/multi_field/g24/s30 | 2 | 2 | x1, x1 | 0 |" in text
    assert (root / "docs" / "img" / bench.PLOT).stat().st_size > 10_000
    assert str(root) not in text


def test_summary_of_a_flat_and_a_diverged_curve(bench):
    def row(factor, observed, future=100.0):
        return {"factor": factor, "observed_cd": observed, "future_cd": future}

    flat = {0.5: row(0.5, 11.0, 300.0), 1.0: row(1.0, 10.0), 2.0: row(2.0, 9.0, 50.0)}
    s = bench.body_summary(flat)
    assert s["best_factor"] == 2.0  # the observed frames prefer a wrong E, by a little
    assert s["observed_change"] == pytest.approx(0.1) and s["future_change"] == pytest.approx(2.0)
    broken = {0.5: {"factor": 0.5, "diverged": "object 1, frame 3, substep 7"}, 1.0: row(1.0, 10)}
    s = bench.body_summary(broken)
    assert s["best_factor"] == 1.0 and s["observed_change"] is None
