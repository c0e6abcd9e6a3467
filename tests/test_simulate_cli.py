"""`mosiv eval` and `mosiv simulate` on a tiny finished run (example scene, ballistic simulator).

The ballistic toy simulator moves every particle on x0 + v0 t + (g + a) t^2 / 2 (a: the wind
term's acceleration, when modelled), so a novel initial velocity or an added wind has an exact
expected rollout to compare the written rollout.npz against.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

from mosiv_framework.cli.main import main
from mosiv_framework.interfaces import Simulator
from mosiv_framework.pipeline import run_pipeline
from mosiv_framework.recipes import validate_recipe
from mosiv_framework.registry import Component, Registry, hookimpl, manager
from mosiv_framework.types import Trajectory


class Ballistic(Simulator):
    """Free fall under gravity plus the ``wind`` term's steady acceleration, if modelled."""

    supported_terms = frozenset({"wind"})

    def __init__(self, **options):
        pass

    def rollout(self, particles, params, *, world, frames):
        t = torch.arange(frames + 1, dtype=torch.float32) / world.fps
        g = torch.tensor(world.gravity, dtype=torch.float32)
        if "wind" in params.terms:
            g = g + params.terms["wind"]["acceleration"].float()
        v0 = torch.stack([params.initial_velocity[int(k)] for k in particles.object_ids.tolist()])
        x = particles.positions[None] + t[:, None, None] * v0[None]
        return Trajectory(x + 0.5 * t[:, None, None] ** 2 * g, particles.object_ids, world.fps)


class BallisticPlugin:
    @hookimpl
    def mosiv_simulators(self, register):
        register(Component("simulator", "ballistic", factory=Ballistic))


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory):
    """A finished run folder made once for this module's tests."""
    tmp = tmp_path_factory.mktemp("run")
    reg = Registry().load_entry_points(disabled=["warp-mpm", "taichi-mpm", "gauss"])
    reg.add_plugin(BallisticPlugin(), name="ballistic-test")
    saved = manager._REGISTRY
    manager._REGISTRY = reg
    raw = {
        "scene": {
            "path": str(tmp / "scene"),
            "generate": "if-missing",
            "source": {"name": "example", "n_frames": 6, "n_cameras": 2, "size": 24},
        },
        "reconstructor": {"name": "oracle", "max_points": 200},
        "lifter": {"name": "gt-points", "max_particles_per_object": 200},
        "simulator": {"name": "ballistic"},
        "losses": {"chamfer": {"weight": 1.0, "max_points": 200}},
        "identify": {"velocity_iterations": 3, "param_iterations": 0, "velocity_lr": 0.01},
        "evaluate": {"emd_samples": 64, "video_size": 48},
        "output": {"dir": str(tmp / "run")},
    }
    resolved, problems = validate_recipe(raw, reg)
    assert problems == []
    run_pipeline(OmegaConf.create(resolved), run_dir=tmp / "run")
    yield tmp / "run"
    manager._REGISTRY = saved


@pytest.fixture
def registry_of_run(finished_run, monkeypatch):
    reg = Registry().load_entry_points(disabled=["warp-mpm", "taichi-mpm", "gauss"])
    reg.add_plugin(BallisticPlugin(), name="ballistic-test")
    monkeypatch.setattr(manager, "_REGISTRY", reg)
    return finished_run


def test_run_writes_videos_and_rollout(registry_of_run):
    run = registry_of_run
    assert (run / "videos" / "prediction_vs_reference.gif").stat().st_size > 0
    with np.load(run / "rollout.npz") as npz:
        assert {"obj_1", "obj_2", "fps"} <= set(npz.files)
        assert npz["obj_1"].shape[0] == 6


def test_eval_rewrites_metrics(registry_of_run):
    run = registry_of_run
    before = json.loads((run / "metrics.json").read_text())
    (run / "metrics.json").unlink()
    (run / "trajectories.png").unlink()
    assert main(["eval", str(run)]) == 0
    after = json.loads((run / "metrics.json").read_text())
    assert (run / "trajectories.png").is_file()
    # the same model scored again: the same numbers
    assert after["future"]["cd_mm2"] == pytest.approx(before["future"]["cd_mm2"], rel=1e-6)


def test_simulate_new_velocity_follows_the_analytic_arc(registry_of_run, tmp_path):
    run = registry_of_run
    out = tmp_path / "novel"
    code = main(
        [
            "simulate",
            str(run),
            "--velocity",
            "obj1=0,0,1",
            "--frames",
            "4",
            "--out",
            str(out),
            "--size",
            "32",
        ]
    )
    assert code == 0
    particles = torch.load(run / "particles.pt", weights_only=False)
    x0 = particles.positions[particles.object_ids == 1].numpy()
    with np.load(out / "rollout.npz") as npz:
        obj1, fps = npz["obj_1"], float(npz["fps"])
    assert obj1.shape == (5, x0.shape[0], 3)
    t = 4 / fps
    expected = x0 + np.array([0.0, 0.0, 1.0]) * t + 0.5 * np.array([0.0, 0.0, -9.8]) * t**2
    np.testing.assert_allclose(obj1[4], expected, atol=1e-5)
    assert (out / "video.gif").stat().st_size > 0
    params = json.loads((out / "params.json").read_text())
    assert params["objects"]["1"]["initial_velocity"] == [0.0, 0.0, 1.0]


def test_simulate_swap_and_set_edit_the_parameters(registry_of_run, tmp_path):
    run = registry_of_run
    identified = json.loads((run / "identified.json").read_text())["objects"]
    out = tmp_path / "swapped"
    assert (
        main(
            [
                "simulate",
                str(run),
                "--swap",
                "1,2",
                "--set",
                "obj1.rho=700",
                "--frames",
                "2",
                "--out",
                str(out),
                "--size",
                "32",
            ]
        )
        == 0
    )
    params = json.loads((out / "params.json").read_text())["objects"]
    assert params["1"]["family"] == identified["2"]["family"]
    assert params["2"]["params"] == identified["1"]["params"]
    assert params["1"]["params"]["rho"] == 700.0
    # velocities stay with the bodies
    assert params["1"]["initial_velocity"] == identified["1"]["initial_velocity"]


def test_simulate_rejects_bad_edits_by_name(registry_of_run, capsys):
    run = str(registry_of_run)
    assert main(["simulate", run, "--set", "obj1.stiffness=3"]) == 2
    assert "whose parameters are" in capsys.readouterr().err
    assert main(["simulate", run, "--swap", "1,9"]) == 2
    assert "no object 9" in capsys.readouterr().err
    assert main(["simulate", run, "--set", "obj1.rho=1e9"]) == 2
    assert "outside its valid range" in capsys.readouterr().err
    assert main(["eval", str(registry_of_run) + "-missing"]) == 2
    assert "does not exist" in capsys.readouterr().err


def test_simulate_set_adds_a_physics_term(registry_of_run, tmp_path):
    run = registry_of_run
    out = tmp_path / "windy"
    args = ["simulate", str(run), "--set", "term.wind.acceleration=0,1.5,0", "--frames", "4"]
    assert main([*args, "--out", str(out), "--size", "32"]) == 0
    particles = torch.load(run / "particles.pt", weights_only=False)
    x0 = particles.positions[particles.object_ids == 1].numpy()
    v0 = np.array(
        json.loads((run / "identified.json").read_text())["objects"]["1"]["initial_velocity"]
    )
    with np.load(out / "rollout.npz") as npz:
        obj1, fps = npz["obj_1"], float(npz["fps"])
    t = 4 / fps
    expected = x0 + v0 * t + 0.5 * np.array([0.0, 1.5, -9.8]) * t**2
    np.testing.assert_allclose(obj1[4], expected, atol=1e-5)
    terms = json.loads((out / "params.json").read_text())["terms"]
    assert terms == {"wind": {"acceleration": [0.0, 1.5, 0.0]}}


def test_simulate_rejects_bad_term_edits_by_name(registry_of_run, capsys):
    run = str(registry_of_run)
    assert main(["simulate", run, "--set", "term.breeze.acceleration=1,0,0"]) == 2
    assert "no physics term 'breeze'" in capsys.readouterr().err
    assert main(["simulate", run, "--set", "term.wind.speed=1"]) == 2
    assert "the parameters of wind are ['acceleration']" in capsys.readouterr().err
    assert main(["simulate", run, "--set", "term.wind.acceleration=1,0"]) == 2
    assert "expected 3 comma-separated numbers" in capsys.readouterr().err
    assert main(["simulate", run, "--set", "term.wind.acceleration=0,0,99"]) == 2
    assert "outside its valid range" in capsys.readouterr().err
    # a term the run's simulator does not implement is refused before any rollout
    assert main(["simulate", run, "--set", "term.linear_drag.coefficient=2"]) == 2
    assert "not implemented by the run's simulator 'ballistic'" in capsys.readouterr().err
