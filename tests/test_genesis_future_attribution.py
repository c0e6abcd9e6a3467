"""benchmarks/genesis_future_attribution.py: an identified row rolled out again with one group
of values replaced by the truth at a time.

On a scene that mosiv-synth made with warp-mpm (multi-field contact, own laws, grid 24, 30
substeps) the truth reproduces the recording exactly. A row identified right but for the
initial velocities (10 % too fast) must therefore score exactly 0 when the velocities are
replaced by the truth, and exactly what the identified values score when anything else is
replaced; the rows with the truth are 0 whatever else. A second row wrong in the law
parameters only is put right by the material variant alone. The table, the rerun and the
RESULTS section are tested on the same rows.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from mosiv_framework.pipeline.run import generate_scene
from mosiv_framework.recipes import load_recipe
from mosiv_framework.scene import read_scene
from mosiv_framework.testing.pytest_plugin import require_simulator
from mosiv_framework.testing.scripts import load_script

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "benchmarks" / "genesis_future_attribution.py"
RECIPE = ROOT / "recipes" / "diagnose_small.yaml"
SETS = ["--set", "simulator.grid=24", "--set", "simulator.substeps=30"]
SETS += ["--set", "simulator.device=cpu"]


@pytest.fixture(scope="module")
def bench():
    return load_script(SCRIPT)


def _identified(scene, *, v0_scale=1.0, e_scale=1.0, gauge=False) -> dict:
    """identified.json's values: the scene's truth, with the initial velocities and the
    stiffnesses scaled; ``gauge``: in identification's density gauge (the first object's
    density 1000, every density and stress scaled alike)."""
    gt = scene.gt_params()
    factor = 1000.0 / gt["objects"][0]["params"]["rho"] if gauge else 1.0
    objects = {}
    for record in gt["objects"]:
        params = {n: float(v) for n, v in record["params"].items()}
        for name in ("rho", "E", "yield_stress"):
            if name in params:
                params[name] *= factor
        params["E"] = params["E"] * e_scale
        objects[str(record["id"])] = {
            "family": record["material"],
            "params": params,
            "initial_velocity": [v * v0_scale for v in record["initial_velocity"]],
        }
    ground = (gt.get("generator_params") or {}).get("ground_friction", 0.1)
    return {"objects": objects, "ground_friction": ground}


@pytest.fixture(scope="module")
def measured(bench, tmp_path_factory):
    require_simulator("warp-mpm")
    root = tmp_path_factory.mktemp("attribution")
    suite = root / "suite"
    for name in ("fast", "stiff"):
        overrides = [
            f"scene.path={suite / name}",
            "scene.source.n_frames=8",
            "scene.source.observed_frames=5",
            "scene.source.collision_frame=3",
            "scene.generate=if-missing",
        ]
        generate_scene(load_recipe(RECIPE, overrides).scene)
    rows = root / "rows"
    rows.mkdir()
    contact = {"choice": "fixed", "mode": "multi_field"}
    fast = _identified(read_scene(suite / "fast"), v0_scale=1.1)
    stiff = _identified(read_scene(suite / "stiff"), e_scale=4.0, gauge=True)
    for name, identified in (("fast", fast), ("stiff", stiff)):
        row = {"scene": name, "contact": contact, "identified": identified}
        (rows / f"{name}.json").write_text(json.dumps(row))
    argv = ["--rows", str(rows), "--scenes", str(suite), "--out", str(root / "out")]
    argv += ["--recipe", str(RECIPE), *SETS]
    assert bench.main(argv) == 0
    table = json.loads((root / "out" / "attribution.json").read_text())["rows"]
    return root, argv, {(r["scene"], r["variant"]): r for r in table}


def test_only_the_wrong_group_put_right_reproduces_the_recording(measured):
    _, _, by = measured
    for scene, culprit in (("fast", "velocity"), ("stiff", "material")):
        wrong = by[(scene, "identified")]
        assert wrong["observed_cd"] > 1e-3 and wrong["future_cd"] > 1e-3, wrong
        for name in ("truth", culprit):
            right = by[(scene, name)]
            assert right["observed_cd"] < 1e-6 and right["future_cd"] < 1e-6, right
            assert max(right["last_offset_mm"].values()) < 1e-3, right
        others = {"ground", "velocity", "material"} - {culprit}
        for name in others:
            same = by[(scene, name)]
            assert same["future_cd"] == pytest.approx(wrong["future_cd"], rel=1e-5), name
        assert max(wrong["last_offset_mm"].values()) > 0.1, wrong


def test_a_rerun_measures_nothing_again_and_writes_the_section(measured, bench):
    root, argv, by = measured
    notes = root / "RESULTS.md"
    notes.write_text("# Results\n\n## From video\n\nkept\n")
    data = "two tiny own-synth scenes"
    assert bench.main([*argv, "--write-results", str(notes), "--data", data]) == 0
    rows = json.loads((root / "out" / "attribution.json").read_text())["rows"]
    assert {(r["scene"], r["variant"]): r for r in rows} == by
    text = notes.read_text()
    assert "## Future error on Genesis scenes" in text and "## From video" in text
    assert f"- Data: {data}." in text
    assert "| rows | 24 / 30 | fast | multi_field | " in text
    assert "| rows | 24 / 30 | velocity | 2 | 0 |" in text
    assert "| rows | 24 / 30 | truth | 2 | 0 | 0 | 2 |" in text


def test_a_row_without_identified_values_is_refused_by_name(bench, tmp_path):
    (tmp_path / "E-E.json").write_text(json.dumps({"scene": "E-E", "contact": None}))
    with pytest.raises(SystemExit, match="E-E.json: the row keeps no identified values"):
        bench.read_rows(tmp_path)


def test_an_unknown_variant_names_the_valid_ones(bench):
    with pytest.raises(ValueError, match="identified, ground, velocity, material, truth"):
        bench.variant_params(None, None, None, "gravity")


def test_the_identified_values_are_put_into_the_truths_gauge(bench):
    """Identification holds the first density at 1000; the truth's is 2000: every density and
    stress doubles (a liquid's viscosity and bulk modulus too), nothing else changes."""
    import torch

    from mosiv_framework.types import ObjectParams, SimulationParams

    def params(rho1, e, viscosity):
        elastic = {"E": torch.tensor(e), "nu": torch.tensor(0.3), "rho": torch.tensor(rho1)}
        liquid = {"viscosity": torch.tensor(viscosity), "bulk_modulus": torch.tensor(10 * rho1)}
        liquid |= {"rho": torch.tensor(rho1 / 2), "friction": torch.tensor(0.2)}
        objects = {1: ObjectParams("elastic", elastic), 2: ObjectParams("newtonian", liquid)}
        return SimulationParams(objects, {1: torch.zeros(3), 2: torch.zeros(3)}, torch.tensor(0.4))

    identified, truth = params(1000.0, 5e4, 2.0), params(2000.0, 1e5, 4.0)
    gauged = bench.in_truth_gauge(identified, truth)
    for k in (1, 2):
        for name, value in gauged.objects[k].values.items():
            assert float(value) == pytest.approx(float(truth.objects[k].values[name])), (k, name)
    assert float(gauged.ground_friction) == pytest.approx(0.4)


def test_a_rollout_that_does_not_reproduce_its_row_is_warned_about(bench, capsys):
    row = {"scene": "E-E", "future_cd_mm2": 100.0}
    bench._check_reproduced(row, {"future_cd": 101.0, "grid": 96, "substeps": 600})
    assert capsys.readouterr().err == ""
    bench._check_reproduced(row, {"future_cd": 150.0, "grid": 64, "substeps": 400})
    assert "E-E: the identified rollout's future Chamfer 150 mm^2 is 50.0 % off" in (
        capsys.readouterr().err
    )
