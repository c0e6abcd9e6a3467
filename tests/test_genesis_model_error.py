"""benchmarks/genesis_model_error.py: the true parameters rolled out and scored against gt.

On a scene that mosiv-synth made with warp-mpm (multi-field contact, its own laws, grid 24, 30
substeps), rolling out the truth at those settings reproduces gt/points.npz exactly: the
benchmark's mapping of gt/params.json (parameters, initial velocities, the recorded ground
friction) and the recipe's oracle particles are the generator's. Every other stress or contact
leaves an error. The report, the rerun and the RESULTS section are tested on the same rows.
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
SCRIPT = ROOT / "benchmarks" / "genesis_model_error.py"
RECIPE = ROOT / "recipes" / "diagnose_small.yaml"
CONFIG = ["--grids", "24", "--substeps", "30", "--device", "cpu"]


@pytest.fixture(scope="module")
def bench():
    return load_script(SCRIPT)


@pytest.fixture(scope="module")
def measured(bench, tmp_path_factory):
    require_simulator("warp-mpm")
    root = tmp_path_factory.mktemp("model_error")
    overrides = [
        f"scene.path={root / 'suite' / 'E-E'}",
        "scene.source.n_frames=6",
        "scene.source.observed_frames=4",
        "scene.source.collision_frame=3",
        "scene.generate=if-missing",
    ]
    generate_scene(load_recipe(RECIPE, overrides).scene)
    argv = ["--scenes", str(root / "suite"), "--out", str(root / "out"), "--recipe", str(RECIPE)]
    argv += ["--laws", "own", "corotated", "--contacts", "multi_field", "single_field", *CONFIG]
    assert bench.main(argv) == 0
    rows = json.loads((root / "out" / "model_error.json").read_text())["rows"]
    return root, argv, rows


def test_the_generators_own_model_reproduces_its_scene_and_no_other_does(measured):
    _, _, rows = measured
    by_config = {r["config"]: r for r in rows}
    assert sorted(by_config) == [
        "corotated/multi_field/g24/s30",
        "corotated/single_field/g24/s30",
        "own/multi_field/g24/s30",
        "own/single_field/g24/s30",
    ]
    exact = by_config.pop("own/multi_field/g24/s30")
    assert exact["observed_cd"] < 1e-6 and exact["future_cd"] < 1e-6, exact
    for config, row in by_config.items():
        assert row["observed_cd"] + row["future_cd"] > 1e-2, (config, row)
    assert all(r["device"] == "CPU" and r["scene"] == "E-E" for r in rows)


def test_a_rerun_measures_nothing_again_and_the_report_writes_the_section(measured, bench):
    root, argv, rows = measured
    assert bench.main(argv) == 0
    again = json.loads((root / "out" / "model_error.json").read_text())["rows"]
    assert again == rows
    notes = root / "RESULTS.md"
    notes.write_text("# Results\n\n## From video\n\nkept\n")
    measuring = "python benchmarks/genesis_model_error.py --scenes S --out O"
    report = ["--out", str(root), "--report", "--measured-with", measuring]
    assert bench.main([*report, "--write-results", str(notes)]) == 0
    text = notes.read_text()
    assert text.index("## Model error on Genesis scenes") < text.index("## From video")
    assert f"`{measuring}` (one process per scene)" in text
    assert "--measured-with" not in text  # the report's own command is shown without it
    assert "| E-E | 0 / 0 |" in text
    assert "| own/multi_field/g24/s30 | 1 | 0 |" in text


def test_report_refuses_a_folder_without_rows_or_with_another_table(bench, tmp_path):
    with pytest.raises(SystemExit, match="no model_error.json"):
        bench.main(["--out", str(tmp_path), "--report"])
    (tmp_path / "model_error.json").write_text(json.dumps({"format": "other", "rows": []}))
    with pytest.raises(SystemExit, match="not a model-error table"):
        bench.main(["--out", str(tmp_path), "--report"])


def test_split_particles_are_a_configuration_of_their_own(measured, bench):
    """``--splits 1 2``: the generator's own particles reproduce its scene, the same bodies
    split into 2^3 particles each are another discretisation (the key says split2)."""
    root, argv, _ = measured
    out = root / "split"
    suite, recipe = argv[argv.index("--scenes") + 1], argv[argv.index("--recipe") + 1]
    split_argv = ["--scenes", suite, "--out", str(out), "--recipe", recipe, "--laws", "own"]
    split_argv += ["--contacts", "multi_field", *CONFIG, "--splits", "1", "2"]
    assert bench.main(split_argv) == 0
    rows = {r["config"]: r for r in json.loads((out / "model_error.json").read_text())["rows"]}
    assert sorted(rows) == ["own/multi_field/g24/s30", "own/multi_field/g24/s30/split2"]
    exact, split = rows["own/multi_field/g24/s30"], rows["own/multi_field/g24/s30/split2"]
    assert exact["observed_cd"] < 1e-6 and split["split"] == 2
    assert split["observed_cd"] + split["future_cd"] > 1e-2, split


def test_a_changed_ground_is_a_configuration_of_its_own(measured, bench):
    """``--ground-frictions`` and ``--ground-offsets-mm``: the truth's own ground (the recorded
    coefficient, no offset) reproduces the scene; the table raised by 300 mm, into the bodies'
    path, is another world (the key says dz300), and a coefficient named explicitly is keyed
    by its value (gf2)."""
    root, argv, _ = measured
    out = root / "ground"
    suite, recipe = argv[argv.index("--scenes") + 1], argv[argv.index("--recipe") + 1]
    ground_argv = ["--scenes", suite, "--out", str(out), "--recipe", recipe, "--laws", "own"]
    ground_argv += ["--contacts", "multi_field", *CONFIG, "--ground-offsets-mm", "0", "300"]
    assert bench.main(ground_argv) == 0
    assert bench.main([*ground_argv, "--ground-frictions", "2"]) == 0
    rows = {r["config"]: r for r in json.loads((out / "model_error.json").read_text())["rows"]}
    base = "own/multi_field/g24/s30"
    assert sorted(rows) == [base, f"{base}/dz300", f"{base}/gf2", f"{base}/gf2/dz300"]
    assert rows[base]["observed_cd"] < 1e-6 and rows[base]["future_cd"] < 1e-6
    raised = rows[f"{base}/dz300"]
    assert raised["ground_offset_mm"] == 300 and raised["observed_cd"] > 1e-2, raised
    assert rows[f"{base}/gf2/dz300"]["future_cd"] != pytest.approx(raised["future_cd"], rel=1e-3)
