"""The run folder is MOSIV's own: `mosiv run` refuses a folder of the user's and one inside the
scene, starts afresh only when told to (removing nothing but run files), reruns what a replaced
scene affects, validates the scene before writing anything, and records the caps its settings
put on the parameters.

A rigid ballistic simulator keeps every run to seconds; the stages, folder and markers are the
real ones.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from omegaconf import OmegaConf

from mosiv_framework import errors
from mosiv_framework.cli.main import main
from mosiv_framework.interfaces import Simulator
from mosiv_framework.pipeline import run_pipeline
from mosiv_framework.pipeline.formats import RUN
from mosiv_framework.pipeline.run import stage_keys
from mosiv_framework.pipeline.rundir import earlier_scene_digest
from mosiv_framework.recipes import validate_recipe
from mosiv_framework.registry import Component, Registry, hookimpl, manager
from mosiv_framework.scene.example import write_example_scene
from mosiv_framework.types import Trajectory


class Ballistic(Simulator):
    """x(t) = x0 + v0 t + g t^2 / 2 per particle, differentiable in v0."""

    calls = 0

    def __init__(self, **options):
        pass

    def rollout(self, particles, params, *, world, frames):
        Ballistic.calls += 1
        t = torch.arange(frames + 1, dtype=torch.float32)[:, None, None] / world.fps
        g = torch.tensor(world.gravity, dtype=torch.float32)
        v0 = torch.stack([params.initial_velocity[int(k)] for k in particles.object_ids.tolist()])
        x = particles.positions[None] + t * v0[None] + 0.5 * t**2 * g[None, None]
        return Trajectory(x, particles.object_ids, world.fps)


@dataclass
class GridOptions:
    """The options the stiffness caps follow from (the ballistic motion ignores them)."""

    grid: int = 16
    substeps: int = 160


class BallisticPlugin:
    @hookimpl
    def mosiv_simulators(self, register):
        register(Component("simulator", "ballistic", factory=Ballistic, options=GridOptions))


@pytest.fixture(autouse=True)
def registry(monkeypatch):
    reg = Registry().load_entry_points(disabled=["warp-mpm", "taichi-mpm", "gauss"])
    reg.add_plugin(BallisticPlugin(), name="ballistic-test")
    monkeypatch.setattr(manager, "_REGISTRY", reg)
    return reg


@pytest.fixture(autouse=True)
def restore_logging(monkeypatch):
    """main() configures the root logger and $MOSIV_LOG_LEVEL; put both back afterwards."""
    root = logging.getLogger()
    saved = (list(root.handlers), root.level, logging.getLogger("mosiv_framework").level)
    monkeypatch.delenv("MOSIV_LOG_LEVEL", raising=False)
    yield
    root.handlers[:] = saved[0]
    root.setLevel(saved[1])
    logging.getLogger("mosiv_framework").setLevel(saved[2])


def raw_recipe(scene: Path, out: Path, **simulator) -> dict:
    """The example scene (generated into ``scene`` if missing), oracle points, the ballistic
    simulator; grid 16 with 160 substeps caps no stiffness below its law's bound there."""
    return {
        "scene": {
            "path": str(scene),
            "generate": "if-missing",
            "source": {"name": "example", "n_frames": 8, "n_cameras": 2, "size": 24},
        },
        "reconstructor": {"name": "oracle", "max_points": 200},
        "lifter": {"name": "gt-points", "max_particles_per_object": 200},
        "simulator": {"name": "ballistic", "grid": 16, "substeps": 160, **simulator},
        "losses": {"chamfer": {"weight": 1.0, "max_points": 200}},
        "identify": {
            "velocity_iterations": 8,
            "param_iterations": 0,
            "velocity_lr": 0.1,
            "horizon_start": 2,
        },
        "evaluate": {"emd_samples": 64, "render_videos": False},
        "output": {"dir": str(out)},
    }


def write_recipe(folder: Path, scene: Path, out: Path, **simulator) -> Path:
    path = folder / "tiny.yaml"
    path.write_text(yaml.safe_dump(raw_recipe(scene, out, **simulator)))
    return path


def loaded(registry, scene: Path, out: Path, **simulator):
    resolved, problems = validate_recipe(raw_recipe(scene, out, **simulator), registry)
    assert problems == []
    return OmegaConf.create(resolved)


def hashes(folder: Path) -> dict[str, str]:
    """Every file under ``folder`` with the hash of its bytes and its modification time."""
    return {
        str(p.relative_to(folder)): f"{hashlib.sha256(p.read_bytes()).hexdigest()}@"
        f"{p.stat().st_mtime_ns}"
        for p in sorted(folder.rglob("*"))
        if p.is_file()
    }


def fails(capsys, argv: list[str], code: int) -> str:
    """Run ``mosiv ARGV``; check its exit status and one error line; return that line."""
    capsys.readouterr()
    assert main(argv) == code
    err = capsys.readouterr().err
    assert "Traceback" not in err
    lines = [line for line in err.splitlines() if line.startswith("mosiv ")]
    assert len(lines) == 1, err
    return lines[0]


def scores(metrics: dict) -> tuple:
    """What a run measured (not its wall time)."""
    velocity_errors = [
        e["initial_velocity"]["rel_error"] for _, e in sorted(metrics["param_error"].items())
    ]
    return (metrics["observed"]["cd_mm2"], metrics["future"]["cd_mm2"], *velocity_errors)


@pytest.fixture(scope="module")
def example(tmp_path_factory) -> Path:
    return write_example_scene(tmp_path_factory.mktemp("ex") / "scene", n_frames=8, n_cameras=2)


@pytest.fixture
def scene(tmp_path, example) -> Path:
    return shutil.copytree(example, tmp_path / "scene")


# ----------------------------------------------------------------------- folders refused
def test_a_folder_of_the_users_is_refused_and_left_as_it_was(capsys, tmp_path):
    mine = tmp_path / "mine"
    (mine / "plots").mkdir(parents=True)
    for name in ("recipe.yaml", "metrics.json", "notes.txt", "plots/a.png"):
        (mine / name).write_text(f"the user's {name}")
    before = hashes(mine)
    recipe = write_recipe(tmp_path, tmp_path / "scene", mine)
    line = fails(capsys, ["run", str(recipe)], errors.EXIT_OUTPUT)
    assert f"output.dir={str(mine)!r}" in line and "not a run folder" in line
    for name in ("'metrics.json'", "'notes.txt'", "'plots'", "'recipe.yaml'"):
        assert name in line, line
    assert hashes(mine) == before
    assert not (tmp_path / "scene").exists()  # refused before the scene was generated


@pytest.mark.parametrize("where", ["the scene", "inside the scene", "through a link"])
def test_an_output_folder_in_the_scene_is_refused(where, capsys, tmp_path, scene):
    (tmp_path / "link").symlink_to(scene)
    out = {
        "the scene": scene,
        "inside the scene": scene / "run",
        "through a link": tmp_path / "link" / "run",
    }[where]
    before = hashes(scene)
    recipe = write_recipe(tmp_path, scene, out)
    line = fails(capsys, ["run", str(recipe)], errors.EXIT_OUTPUT)
    assert f"output.dir={str(out)!r}" in line and "inside" in line
    assert hashes(scene) == before


# ------------------------------------------------------------------------ starting afresh
def test_resume_false_needs_force_and_force_keeps_foreign_files(capsys, tmp_path, scene):
    run = tmp_path / "run"
    recipe = write_recipe(tmp_path, scene, run)
    assert main(["run", str(recipe)]) == 0
    record = json.loads((run / "run.json").read_text())
    assert record["format"] == RUN
    assert record["stages_done"] == ["reconstruct", "lift", "identify", "evaluate"]
    assert {"recipe.yaml", "metrics.json", "stages", "identify"} <= set(record["files"])
    first = json.loads((run / "metrics.json").read_text())
    (run / "notes.txt").write_text("the user's notes")

    before = hashes(run)
    line = fails(capsys, ["run", str(recipe), "output.resume=false"], errors.EXIT_OUTPUT)
    assert "output.resume=false" in line and "--force" in line
    assert hashes(run) == before

    Ballistic.calls = 0
    assert main(["run", "--force", str(recipe), "output.resume=false"]) == 0
    assert Ballistic.calls > 0  # every stage ran again
    assert (run / "notes.txt").read_text() == "the user's notes"
    again = json.loads((run / "metrics.json").read_text())
    assert again["time_s"] != first["time_s"]  # written anew, not kept
    assert scores(again) == pytest.approx(scores(first))
    assert json.loads((run / "run.json").read_text())["created"] >= record["created"]


def test_resume_false_on_a_new_folder_needs_no_force(tmp_path, scene):
    recipe = write_recipe(tmp_path, scene, tmp_path / "run")
    assert main(["run", str(recipe), "output.resume=false"]) == 0
    assert (tmp_path / "run" / "metrics.json").is_file()


def test_a_scene_generated_inside_the_run_folder_is_the_runs_own(tmp_path):
    run = tmp_path / "run"
    run.mkdir()
    (run / "suite.log").write_text("the diagnosis suite logs here before the run starts\n")
    recipe = write_recipe(tmp_path, run / "scene", run)
    assert main(["run", str(recipe)]) == 0
    scene_files = hashes(run / "scene")
    Ballistic.calls = 0
    assert main(["run", str(recipe)]) == 0
    assert Ballistic.calls == 0  # resumed
    assert main(["run", "--force", str(recipe), "output.resume=false"]) == 0
    assert Ballistic.calls > 0
    assert hashes(run / "scene") == scene_files  # the input is never removed
    assert (run / "suite.log").is_file()


# ------------------------------------------------------------------------- a stale scene
def test_a_scene_replaced_at_the_same_path_reruns_and_matches_a_fresh_run(
    tmp_path, registry, caplog
):
    scene = write_example_scene(tmp_path / "scene", n_frames=8, n_cameras=2, size=24, seed=0)
    run = tmp_path / "run"
    recipe = loaded(registry, scene, run)
    first = run_pipeline(recipe, run_dir=run)

    shutil.rmtree(scene)
    write_example_scene(scene, n_frames=8, n_cameras=2, size=24, seed=1)
    with caplog.at_level(logging.INFO, logger="mosiv_framework"):
        Ballistic.calls = 0
        replaced = run_pipeline(recipe, run_dir=run)
    assert "scene changed since the last run: rerunning from reconstruct" in caplog.text
    assert Ballistic.calls > 0
    fresh = run_pipeline(loaded(registry, scene, tmp_path / "fresh"), run_dir=tmp_path / "fresh")
    assert scores(replaced) != pytest.approx(scores(first))
    assert scores(replaced) == pytest.approx(scores(fresh))
    digest = json.loads((run / "run.json").read_text())["scene"]["digest"]
    assert digest == json.loads((tmp_path / "fresh" / "run.json").read_text())["scene"]["digest"]

    # the same scene again: every stage resumes
    Ballistic.calls = 0
    run_pipeline(recipe, run_dir=run)
    assert Ballistic.calls == 0


def copied_without_times(source: Path, target: Path) -> Path:
    """``source`` copied as ``cp -r`` does: the bytes, with every file's time new."""
    return shutil.copytree(source, target, copy_function=shutil.copyfile)


def test_a_run_copied_with_its_scene_to_another_place_resumes_every_stage(tmp_path, registry):
    # as a suite prepared on one machine, diagnosed on a GPU machine and copied back
    scene = write_example_scene(tmp_path / "a" / "scene", n_frames=8, n_cameras=2, size=24)
    first = run_pipeline(
        loaded(registry, scene, tmp_path / "a" / "run"), run_dir=tmp_path / "a" / "run"
    )
    moved_scene = copied_without_times(scene, tmp_path / "b" / "scene")
    moved_run = copied_without_times(tmp_path / "a" / "run", tmp_path / "b" / "run")
    assert (moved_scene / "scene.json").stat().st_mtime_ns != (
        scene / "scene.json"
    ).stat().st_mtime_ns

    Ballistic.calls = 0
    again = run_pipeline(loaded(registry, moved_scene, moved_run), run_dir=moved_run)
    assert Ballistic.calls == 0
    assert scores(again) == pytest.approx(scores(first))


def test_bytes_changed_behind_an_unchanged_size_and_time_rerun_the_stages(
    tmp_path, registry, caplog
):
    scene = write_example_scene(tmp_path / "scene", n_frames=8, n_cameras=2, size=24)
    notes = scene / "notes.txt"  # a file of the scene's that the stages do not parse
    notes.write_text("take 1")
    run = tmp_path / "run"
    run_pipeline(loaded(registry, scene, run), run_dir=run)
    # edited in place: same size, its time put back
    stat = notes.stat()
    notes.write_text("take 2")
    os.utime(notes, ns=(stat.st_atime_ns, stat.st_mtime_ns))
    assert (notes.stat().st_size, notes.stat().st_mtime_ns) == (stat.st_size, stat.st_mtime_ns)

    with caplog.at_level(logging.INFO, logger="mosiv_framework"):
        run_pipeline(loaded(registry, scene, run), run_dir=run)
    assert "scene changed since the last run: rerunning from reconstruct" in caplog.text


def as_earlier_markers(run: Path, scene: Path, recipe) -> None:
    """Rewrite a run's stage markers as MOSIV wrote them before the scene entered by its
    content: keys holding the scene's path, the scene digested by file times."""
    plain = OmegaConf.to_container(recipe, resolve=True)
    keys, digest = stage_keys(plain, earlier=True), earlier_scene_digest(scene)
    for marker in (run / "stages").glob("*.json"):
        data = json.loads(marker.read_text())
        data.update(config=keys[marker.stem], inputs=digest)
        marker.write_text(json.dumps(data))


def test_markers_of_the_earlier_form_resume_and_are_rewritten(tmp_path, registry, caplog):
    scene = write_example_scene(tmp_path / "scene", n_frames=8, n_cameras=2, size=24)
    run = tmp_path / "run"
    recipe = loaded(registry, scene, run)
    first = run_pipeline(recipe, run_dir=run)
    as_earlier_markers(run, scene, recipe)

    Ballistic.calls = 0
    with caplog.at_level(logging.INFO, logger="mosiv_framework"):
        again = run_pipeline(recipe, run_dir=run)
    assert Ballistic.calls == 0
    assert scores(again) == pytest.approx(scores(first))
    carried = (
        "stage markers of an earlier MOSIV carried over: reconstruct, lift, identify, evaluate"
    )
    assert carried in caplog.text
    current = stage_keys(OmegaConf.to_container(recipe, resolve=True))
    for stage, key in current.items():
        assert json.loads((run / "stages" / f"{stage}.json").read_text())["config"] == key


def test_markers_of_the_earlier_form_on_a_copied_scene_rerun(tmp_path, registry):
    # the earlier digest held file times, so it cannot vouch for a copy: the stages rerun
    scene = write_example_scene(tmp_path / "scene", n_frames=8, n_cameras=2, size=24)
    run = tmp_path / "run"
    recipe = loaded(registry, scene, run)
    run_pipeline(recipe, run_dir=run)
    as_earlier_markers(run, scene, recipe)
    shutil.rmtree(scene)
    write_example_scene(scene, n_frames=8, n_cameras=2, size=24)

    Ballistic.calls = 0
    run_pipeline(recipe, run_dir=run)
    assert Ballistic.calls > 0


# ---------------------------------------------------------------------- failed runs
def test_invalid_ground_truth_fails_before_any_stage_and_leaves_no_folder(capsys, tmp_path, scene):
    points = dict(np.load(scene / "gt" / "points.npz"))
    points["obj_1"][3, 7] = np.nan
    np.savez(scene / "gt" / "points.npz", **points)
    run = tmp_path / "run"
    recipe = write_recipe(tmp_path, scene, run)
    line = fails(capsys, ["run", str(recipe)], errors.EXIT_SCENE)
    assert "points.npz" in line and "non-finite" in line
    assert not run.exists()

    # an empty folder of the user's stays empty
    run.mkdir()
    fails(capsys, ["run", str(recipe)], errors.EXIT_SCENE)
    assert list(run.iterdir()) == []


def test_a_run_refused_after_generating_its_scene_inside_the_output_removes_it(capsys, tmp_path):
    run = tmp_path / "run"
    # 10 substeps cap E below the value identification starts from: a recipe error
    recipe = write_recipe(tmp_path, run / "scene", run, substeps=10)
    line = fails(capsys, ["run", str(recipe)], errors.EXIT_USAGE)
    assert "simulator.substeps=10 caps E" in line
    assert not run.exists()


def test_a_failing_first_stage_takes_back_recipe_and_run_json(tmp_path, scene, monkeypatch):
    from mosiv_framework.oracle import OracleReconstructor

    def broken(self, scene, *, run_dir=None):
        raise RuntimeError("reconstructor failed")

    monkeypatch.setattr(OracleReconstructor, "fit", broken)
    run = tmp_path / "run"
    recipe = write_recipe(tmp_path, scene, run)
    assert main(["run", str(recipe)]) == errors.EXIT_INTERNAL
    assert not run.exists()


# --------------------------------------------------------------------------- caps, layout
def test_a_cap_on_the_parameters_is_logged_and_stored_in_identified_json(
    tmp_path, registry, scene, caplog
):
    run = tmp_path / "run"
    with caplog.at_level(logging.WARNING, logger="mosiv_framework"):
        run_pipeline(loaded(registry, scene, run, substeps=20), run_dir=run)
    warnings = json.loads((run / "identified.json").read_text())["warnings"]
    assert len(warnings) == 1 and warnings[0].startswith("simulator.substeps=20 caps E")
    assert "the law allows up to" in warnings[0]
    assert warnings[0] in caplog.text

    # no cap below the laws' bounds: no warnings key
    quiet = tmp_path / "quiet"
    run_pipeline(loaded(registry, scene, quiet), run_dir=quiet)
    assert "warnings" not in json.loads((quiet / "identified.json").read_text())


def test_a_run_folder_made_before_run_json_still_resumes(tmp_path, registry, scene):
    run = tmp_path / "run"
    recipe = loaded(registry, scene, run)
    run_pipeline(recipe, run_dir=run)
    # the earlier layout: no run.json, stage markers without the scene digest
    (run / "run.json").unlink()
    for marker in (run / "stages").glob("*.json"):
        data = json.loads(marker.read_text())
        del data["inputs"]
        marker.write_text(json.dumps(data))
    Ballistic.calls = 0
    run_pipeline(recipe, run_dir=run)
    assert Ballistic.calls == 0
    record = json.loads((run / "run.json").read_text())
    assert record["format"] == RUN and record["stages_done"][-1] == "evaluate"


def test_a_folder_holding_only_a_runs_recipe_is_a_run_folder(tmp_path, registry, scene):
    from mosiv_framework.errors import OutputError
    from mosiv_framework.pipeline.formats import recipe_header

    stopped, mine = tmp_path / "stopped", tmp_path / "mine"
    recipe = loaded(registry, scene, stopped)
    for folder, header in ((stopped, recipe_header()), (mine, b"")):
        folder.mkdir()
        (folder / "recipe.yaml").write_bytes(header + OmegaConf.to_yaml(recipe).encode())
    run_pipeline(recipe, run_dir=stopped)  # a run stopped before its first stage finished
    assert (stopped / "run.json").is_file() and (stopped / "metrics.json").is_file()
    before = hashes(mine)
    with pytest.raises(OutputError, match="'recipe.yaml'"):
        run_pipeline(recipe, run_dir=mine)  # a recipe of the user's, not a run's
    assert hashes(mine) == before


def test_a_scene_generation_that_dies_part_way_leaves_no_half_scene(tmp_path, monkeypatch):
    """The scene is written beside its folder and moved in once complete: a source that dies
    after writing some files leaves scene.path missing (not a half scene that the next run
    would refuse as the user's files), and the next generation replaces the leftover."""
    from mosiv_framework.pipeline.run import generate_scene
    from mosiv_framework.scene import read_scene

    scene = tmp_path / "scene"
    section = OmegaConf.create(raw_recipe(scene, tmp_path / "run")["scene"])
    real_write = write_example_scene

    def dies_part_way(path, **kwargs):
        Path(path).mkdir(parents=True)
        (Path(path) / "rgb").mkdir()
        raise RuntimeError("engine crashed")

    monkeypatch.setattr("mosiv_framework.scene.example.write_example_scene", dies_part_way)
    with pytest.raises(RuntimeError, match="engine crashed"):
        generate_scene(section)
    assert not scene.exists()
    monkeypatch.setattr("mosiv_framework.scene.example.write_example_scene", real_write)
    assert generate_scene(section)
    assert read_scene(scene).n_frames == 8
    assert [p.name for p in tmp_path.iterdir()] == ["scene"]
    assert not generate_scene(section)  # a scene is there now: kept
