"""``mosiv intervals RUN``: a finished run's intervals made again without identifying again.

On the tiny Genesis scene (oracle geometry, warp-mpm on the CPU, every point in the Chamfer
term so no random subset differs between the run and the recomputation): the same method
gives the run's own intervals back (the vector, bounds, stiffness ceilings, contact and
objective are rebuilt faithfully), the other method is appended to the history and becomes
the run's, and metrics.json's coverage marks follow it."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from mosiv_framework.cli.main import main as mosiv
from mosiv_framework.pipeline.formats import read_history
from mosiv_framework.pipeline.uncertainty import INTERVALS_PHASE
from mosiv_framework.testing.pytest_plugin import require_simulator

ROOT = Path(__file__).resolve().parents[1]
TINY = ROOT / "plugins" / "mosiv-genesis" / "tests" / "data" / "tiny_scene"

SETTINGS = [
    "simulator.device=cpu",
    "simulator.grid=16",
    "simulator.substeps=20",
    "identify.velocity_iterations=2",
    "identify.param_iterations=3",
    "identify.global_candidates=2",
    "identify.global_polish=2",
    "identify.contact=fixed",
    "identify.law_choice=fixed",
    "losses.chamfer.max_points=100000",  # every point: no subset differs between runs
    "evaluate.emd_samples=64",
    "evaluate.render_videos=false",
]


def _intervals(run: Path) -> list[dict]:
    return [
        h
        for h in read_history(run / "identify" / "history.json")
        if h.get("phase") == INTERVALS_PHASE
    ]


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory):
    require_simulator("warp-mpm")
    root = tmp_path_factory.mktemp("reinterval")
    scene = root / "scene"
    shutil.copytree(TINY, scene)
    run = root / "run"
    recipe = ROOT / "recipes" / "genesis_oracle.yaml"
    code = mosiv(["run", str(recipe), f"scene.path={scene}", f"output.dir={run}", *SETTINGS])
    assert code == 0
    return scene, run


def test_the_same_method_gives_the_run_its_own_intervals_back(finished_run, tmp_path):
    scene, run = finished_run
    copy = tmp_path / "run"
    shutil.copytree(run, copy)
    (original,) = _intervals(copy)
    # the scene moved: --scene says where it is now
    moved = tmp_path / "moved_scene"
    shutil.copytree(scene, moved)
    assert mosiv(["intervals", str(copy), "--scene", str(moved)]) == 0
    first, again = _intervals(copy)
    assert first == original and again["recomputed"] is True
    assert again["method"] == original["method"] == "sandwich"
    for owner, entries in original["intervals"].items():
        entries = {"": entries} if "kind" in entries else entries
        for name, got in entries.items():
            new = again["intervals"][owner] if name == "" else again["intervals"][owner][name]
            assert new["kind"] == got["kind"], (owner, name)
            for side in ("low", "high"):
                if got[side] is None:
                    assert new[side] is None
                else:
                    assert new[side] == pytest.approx(got[side], rel=1e-4), (owner, name, side)


def test_another_method_becomes_the_runs_and_remarks_coverage(finished_run, tmp_path):
    _, run = finished_run
    copy = tmp_path / "run"
    shutil.copytree(run, copy)
    assert mosiv(["intervals", str(copy), "--method", "laplace"]) == 0
    last = _intervals(copy)[-1]
    assert last["method"] == "laplace"
    identified = json.loads((copy / "identified.json").read_text())
    assert identified["intervals"] == last["intervals"]
    metrics = json.loads((copy / "metrics.json").read_text())
    assert metrics["params"]["intervals"] == last["intervals"]
    marked = [
        err["covered"]
        for errors in metrics["param_error"].values()
        for err in errors.values()
        if isinstance(err, dict) and "covered" in err
    ]
    assert marked and all(isinstance(m, bool) for m in marked)


def test_a_missing_run_folder_is_named(tmp_path, capsys):
    assert mosiv(["intervals", str(tmp_path / "nowhere")]) != 0
    err = capsys.readouterr().err
    assert "run folder" in err and "nowhere" in err
