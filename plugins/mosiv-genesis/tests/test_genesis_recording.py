"""A scene Genesis recorded (tests/data/tiny_scene, made by ``python -m mosiv_genesis.tiny_scene``)
through the pipeline's reading path: the scene reader and checker, the oracle reconstructor,
the gt-points lifter and a short identification. Needs no engine, so it runs everywhere."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from mosiv_genesis import plan as P
from mosiv_genesis.source import CONTACT_MODE
from mosiv_genesis.tiny_scene import TINY_OPTIONS

from mosiv_framework.laws import get_law
from mosiv_framework.scene import read_scene, validate_scene
from mosiv_framework.testing.pytest_plugin import require_simulator

TINY = Path(__file__).parent / "data" / "tiny_scene"


def _gt() -> dict:
    return json.loads((TINY / "gt" / "params.json").read_text())


def test_the_committed_scene_is_small_and_valid():
    size = sum(f.stat().st_size for f in TINY.rglob("*") if f.is_file())
    assert size < 300 * 1024, f"tests/data/tiny_scene is {size / 1024:.0f} KB"
    assert validate_scene(TINY) == []
    scene = read_scene(TINY)
    assert (scene.n_frames, len(scene.cameras)) == (6, 2)
    assert [o.material for o in scene.objects] == TINY_OPTIONS["materials"].split(",")
    ids = scene.load_mask_ids(frames=[0])
    assert (ids == 1).any() and (ids == 2).any()


def test_gt_records_what_genesis_ran_with():
    """Grid, substeps, contact mode and ranges, so identification can know them; the recorded
    CFL number is the one of the recorded parameters and substeps, below the bound."""
    doc = _gt()
    g = doc["generator_params"]
    assert g["contact"] == CONTACT_MODE == "single_grid"
    assert g["grid_density"] == TINY_OPTIONS["grid_density"]
    assert g["grid_cell_m"] == pytest.approx(1.0 / g["grid_density"])
    assert g["substeps"] >= g["substeps_requested"] == TINY_OPTIONS["substeps"]
    params = [o["generator_params"] for o in doc["objects"]]
    dt = 1.0 / (24.0 * g["substeps"])
    cfl = P.cfl_number(params, grid_density=g["grid_density"], dt=dt)
    assert g["cfl"] == pytest.approx(cfl) and cfl < P.CFL_BOUND
    assert doc["ranges"] == "wide" and doc["range_table"] == P.range_table("wide")
    for obj in doc["objects"]:
        for name, value in obj["generator_params"].items():
            lo, hi = P.preset_ranges(obj["material"], "wide")[name]
            assert lo <= value <= hi


def test_free_flight_of_the_recording_is_ballistic():
    """Before the planned collision (frame 3) each centroid follows x0 + v0 t + g t^2 / 2
    with the recorded initial state (Genesis' MPM under gravity, no contact yet)."""
    scene, doc = read_scene(TINY), _gt()
    gt = scene.gt_points()
    g = np.array(scene.gravity)
    for obj in doc["objects"]:
        x0, v0 = np.array(obj["initial_centroid"]), np.array(obj["initial_velocity"])
        for t in range(3):
            s = t / scene.fps
            centroid = gt[obj["id"]][t].numpy().mean(0)
            assert np.allclose(centroid, x0 + v0 * s + 0.5 * g * s * s, atol=3e-3)


def test_a_short_identification_reads_the_recording(tmp_path):
    """Oracle points and gt-points particles of the Genesis recording, then a short fit with
    the warp-mpm simulator: the initial velocities come from the recorded free flight, and every
    identified parameter lies inside its law's bounds."""
    from omegaconf import OmegaConf

    from mosiv_framework.pipeline import run_pipeline
    from mosiv_framework.recipes import validate_recipe

    registry = require_simulator("warp-mpm")
    scene = tmp_path / "scene"
    shutil.copytree(TINY, scene)  # the run must not write next to the committed data
    raw = {
        "scene": {"path": str(scene)},
        "reconstructor": {"name": "oracle", "max_points": 400},
        "lifter": {"name": "gt-points", "max_particles_per_object": 400},
        "simulator": {"name": "warp-mpm", "grid": 16, "substeps": 40, "device": "cpu"},
        "losses": {"chamfer": {"weight": 1.0, "max_points": 300}},
        "identify": {
            "velocity_iterations": 3, "param_iterations": 2, "velocity_lr": 0.01,
            "param_lr": 0.02, "horizon_start": 2, "checkpoint_every": 5,
        },
        "evaluate": {"emd_samples": 128},
        "output": {"dir": str(tmp_path / "run")},
    }  # fmt: skip
    resolved, problems = validate_recipe(raw, registry)
    assert problems == []
    metrics = run_pipeline(OmegaConf.create(resolved), run_dir=tmp_path / "run")
    assert np.isfinite(metrics["future"]["cd_mm2"])
    for k, err in metrics["param_error"].items():
        assert err["initial_velocity"]["rel_error"] < 0.1, (k, err)
    identified = json.loads((tmp_path / "run" / "identified.json").read_text())
    assert set(identified["objects"]) == {"1", "2"}
    for obj in identified["objects"].values():
        law = get_law(obj["family"])
        for name, value in obj["params"].items():
            spec = law.param(name)
            assert spec.lower <= value <= spec.upper, (name, value)
