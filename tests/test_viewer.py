"""``mosiv view``: loading a finished run into ViewerData, the panel text, the viser server
(page served, scene nodes, frame scrubbing, toggles) and the command's errors and Ctrl-C.

The run is the example scene (two spheres on exact ballistic arcs) through the whole pipeline
with a rigid ballistic simulator: seconds on CPU, and every file a finished run holds.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import signal
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

from mosiv_framework.cli.main import build_parser, main
from mosiv_framework.errors import EXIT_INTERRUPTED, EXIT_USAGE
from mosiv_framework.interfaces import Simulator
from mosiv_framework.scene import read_scene
from mosiv_framework.types import Trajectory
from mosiv_framework.viewer import load_run, panel, start_viewer
from mosiv_framework.viewer.data import ViewerData


class Ballistic(Simulator):
    """x(t) = x0 + v0 t + g t^2 / 2 per particle: the example scene's exact motion."""

    def __init__(self, **options):
        pass

    def rollout(self, particles, params, *, world, frames):
        t = torch.arange(frames + 1, dtype=torch.float32) / world.fps
        g = torch.tensor(world.gravity, dtype=torch.float32)
        v0 = torch.stack([params.initial_velocity[int(k)] for k in particles.object_ids.tolist()])
        x = particles.positions[None] + t[:, None, None] * v0[None]
        return Trajectory(
            x + 0.5 * t[:, None, None] ** 2 * g[None, None], particles.object_ids, world.fps
        )


@pytest.fixture(scope="module")
def run(tmp_path_factory) -> Path:
    """A finished run folder of the example scene (8 frames, 5 observed, 2 cameras)."""
    from mosiv_framework.pipeline import run_pipeline
    from mosiv_framework.recipes import validate_recipe
    from mosiv_framework.registry import Component, Registry, hookimpl, manager

    class Plugin:
        @hookimpl
        def mosiv_simulators(self, register):
            register(Component("simulator", "ballistic", factory=Ballistic))

    root = tmp_path_factory.mktemp("viewer")
    reg = Registry().load_entry_points(disabled=["warp-mpm", "taichi-mpm", "gauss"])
    reg.add_plugin(Plugin(), name="ballistic-test")
    raw = {
        "scene": {
            "path": str(root / "scene"),
            "generate": "if-missing",
            "source": {"name": "example", "n_frames": 8, "n_cameras": 2, "size": 24},
        },
        "reconstructor": {"name": "oracle", "max_points": 200},
        "lifter": {"name": "gt-points", "max_particles_per_object": 200},
        "simulator": {"name": "ballistic"},
        "losses": {"chamfer": {"weight": 1.0, "max_points": 200}},
        "identify": {"velocity_iterations": 20, "param_iterations": 0, "velocity_lr": 0.1},
        "evaluate": {"emd_samples": 64, "render_videos": False},
        "output": {"dir": str(root / "run")},
    }
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(manager, "_REGISTRY", reg)
        resolved, problems = validate_recipe(raw, reg)
        assert problems == []
        run_pipeline(OmegaConf.create(resolved), run_dir=root / "run")
    return root / "run"


@pytest.fixture(scope="module")
def data(run) -> ViewerData:
    return load_run(run)


# ---------------------------------------------------------------------------------- loading
def test_loader_reads_rollout_reference_and_scores(run, data):
    scene = read_scene(run.parent / "scene")
    with np.load(run / "rollout.npz") as npz:
        for k in scene.object_ids:
            np.testing.assert_array_equal(data.predicted[k], npz[f"obj_{k}"])
    truth = scene.gt_points()
    assert data.reference_source == "gt/points.npz"
    for k in scene.object_ids:
        np.testing.assert_array_equal(data.reference[k], truth[k].numpy())
    assert data.n_frames == scene.n_frames and data.observed_frames == scene.observed_frames
    assert [data.phase(t) for t in range(data.n_frames)] == ["observed"] * scene.observed_frames + [
        "future"
    ] * (scene.n_frames - scene.observed_frames)

    identified = json.loads((run / "identified.json").read_text())
    metrics = json.loads((run / "metrics.json").read_text())
    assert sorted(data.objects) == scene.object_ids
    for k, obj in data.objects.items():
        saved = identified["objects"][str(k)]
        assert obj.family == saved["family"] and obj.params == pytest.approx(saved["params"])
        assert obj.initial_velocity == pytest.approx(saved["initial_velocity"])
        errors = metrics["param_error"][str(k)]
        assert obj.truth["initial_velocity"].error == pytest.approx(
            errors["initial_velocity"]["rel_error"]
        )
        assert obj.cd_observed_mm2 == pytest.approx(
            metrics["observed"]["per_object"][str(k)]["cd_mm2"]
        )
        assert obj.cd_future_mm2 == pytest.approx(metrics["future"]["per_object"][str(k)]["cd_mm2"])
    assert data.residuals is None  # not diagnosed


def test_cameras_become_frustums_looking_where_the_camera_projects(data, run):
    scene = read_scene(run.parent / "scene")
    assert [c.id for c in data.cameras] == scene.camera_ids
    for view, cam in zip(data.cameras, scene.cameras):
        np.testing.assert_allclose(view.position, cam.camera_center.numpy(), atol=1e-9)
        np.testing.assert_allclose(view.rotation @ view.rotation.T, np.eye(3), atol=1e-9)
        assert view.aspect == pytest.approx(cam.width / cam.height)
        # the frustum's +z axis is the optical axis, and its top edge (OpenCV: -y) is the top
        # row of the image: both project where the camera says
        d = 0.7
        axis = view.position + view.rotation @ np.array([0.0, 0.0, d])
        top = view.position + view.rotation @ np.array([0.0, -math.tan(view.fov_y / 2) * d, d])
        uv, z = cam.project(torch.tensor(np.stack([axis, top])))
        assert z[0].item() == pytest.approx(d)
        assert uv[0].tolist() == pytest.approx([cam.cx, cam.cy], abs=1e-6)
        assert uv[1, 1].item() == pytest.approx(cam.cy - cam.height / 2, abs=1e-6)


def test_a_relative_scene_path_is_found_from_where_the_run_started(run, tmp_path, monkeypatch):
    # `mosiv run` in tmp_path with output.dir=runs/a and scene.path=scenes/s
    shutil.copytree(run.parent / "scene", tmp_path / "scenes" / "s")
    copy = shutil.copytree(run, tmp_path / "runs" / "a")
    recipe = (copy / "recipe.yaml").read_text()
    recipe = recipe.replace(str(run.parent / "scene"), "scenes/s").replace(str(run), "runs/a")
    (copy / "recipe.yaml").write_text(recipe)
    monkeypatch.chdir(tmp_path.parent)  # the viewer starts elsewhere
    assert load_run(copy).scene_name == read_scene(tmp_path / "scenes" / "s").name


# ------------------------------------------------------------------------------------ panel
def test_panel_shows_truth_errors_chamfer_and_the_phase(data):
    obj = data.objects[1]
    text = panel.object_markdown(obj)
    assert obj.name in text and obj.family in text and "| true | error |" in text
    error = obj.truth["initial_velocity"].error
    assert f"{100 * error:.3g} %" in text
    chamfer = panel.chamfer_markdown(data)
    for o in data.objects.values():
        assert f"{o.cd_observed_mm2:.4g}" in chamfer and f"{o.cd_future_mm2:.4g}" in chamfer
    last = data.observed_frames - 1
    assert "observed" in panel.frame_text(data, last)
    assert "future" in panel.frame_text(data, last + 1)
    assert panel.object_rgb(1) != panel.object_rgb(2)
    # the reference shade is paler: every channel nearer to white
    assert all(r >= p for r, p in zip(panel.object_rgb(1, reference=True), panel.object_rgb(1)))


def _diagnosed_copy(run: Path, dest: Path, *, fmt: str = "mosiv-diagnosis/1") -> Path:
    """A copy of ``run`` with a diagnosis.json in the layout diagnose/report.py writes."""
    copy = shutil.copytree(run, dest)
    diagnosis = {
        "format": fmt,
        "verdict": "missing physics",
        "accepted": {"name": "wind"},
        "frame_errors_mm2": {
            "identified": [[0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, None], [0.5] * 8],
            "wind": [[0.0] * 8, [0.0] * 8],
        },
        "location": {
            "objects": {
                "1": {
                    "centroid_residual_m": [[0, 0, 0], [0.003, 0.004, 0]] + [[0, 0, 0.001]] * 3,
                    "noise_floor_m": 0.0002,
                    "onset_frame": 1,
                },
                "2": {
                    "centroid_residual_m": [[0, 0, 0]] * 5,
                    "noise_floor_m": 0.0001,
                    "onset_frame": 0,
                },
            }
        },
    }
    (copy / "diagnosis.json").write_text(json.dumps(diagnosis))
    return copy


def test_diagnosis_residuals_are_read_per_object_and_frame(run, tmp_path):
    data = load_run(_diagnosed_copy(run, tmp_path / "diagnosed"))
    res = data.residuals
    assert res.verdict == "missing physics" and res.accepted == "wind"
    np.testing.assert_array_equal(res.chamfer_mm2[1][:7], np.arange(7.0))
    assert np.isnan(res.chamfer_mm2[1][7])  # a frame the prediction did not reach
    assert res.centroid_mm[1][1] == pytest.approx(5.0)  # |(3, 4, 0)| mm
    assert res.noise_floor_mm[1] == pytest.approx(0.2) and res.onset_frame[1] == 1
    assert panel.residual_at(data, 1, 3) == 3.0 and panel.residual_at(data, 1, 7) is None
    assert panel.residual_rgb(0.0, 6.0)[:2] == (0, 200)  # green
    assert panel.residual_rgb(6.0, 6.0)[:2] == (255, 0)  # red
    assert "missing physics" in panel.diagnosis_markdown(
        data
    ) and "wind" in panel.diagnosis_markdown(data)


def test_a_diagnosis_of_an_unknown_format_is_refused_naming_the_file(run, tmp_path, capsys):
    copy = _diagnosed_copy(run, tmp_path / "newer", fmt="mosiv-diagnosis/9")
    assert main(["view", str(copy), "--no-block", "--port", "0"]) != 0
    err = capsys.readouterr().err
    assert str(copy / "diagnosis.json") in err and "mosiv-diagnosis/9" in err


# ----------------------------------------------------------------------------------- server
def _get(url: str) -> tuple[int, str, str]:
    with urllib.request.urlopen(url, timeout=20) as response:
        return response.status, response.headers.get("content-type", ""), response.read().decode()


def test_server_serves_the_page_and_scrubs_frames(data):
    viewer = start_viewer(data, host="127.0.0.1", port=0)
    try:
        assert viewer.url.startswith("http://127.0.0.1:")
        status, kind, body = _get(viewer.url + "/")
        assert status == 200 and "text/html" in kind and "<html" in body.lower()
        expected = {f"/predicted/obj_{k}" for k in data.object_ids}
        expected |= {f"/reference/obj_{k}" for k in data.object_ids}
        expected |= {f"/cameras/{c.id}" for c in data.cameras} | {"/phase"}
        assert expected <= set(viewer.nodes)
        for name in expected:
            assert viewer.nodes[name].name == name  # viser's own scene node of that name

        t = data.observed_frames  # the first future frame
        viewer.gui["frame"].value = t  # as a person dragging the slider
        assert viewer.frame == t
        for k in data.object_ids:
            np.testing.assert_allclose(
                viewer.nodes[f"/predicted/obj_{k}"].points, data.predicted[k][t]
            )
            np.testing.assert_allclose(
                viewer.nodes[f"/reference/obj_{k}"].points, data.reference[k][t]
            )
        assert "future" in viewer.nodes["/phase"].text
        viewer.show_frame(0)
        assert "observed" in viewer.nodes["/phase"].text and viewer.gui["frame"].value == 0

        viewer.gui["show_reference"].value = False
        assert not any(viewer.nodes[f"/reference/obj_{k}"].visible for k in data.object_ids)
        assert all(viewer.nodes[f"/predicted/obj_{k}"].visible for k in data.object_ids)

        viewer.gui["play"].value = True
        deadline = time.time() + 10
        while viewer.frame == 0 and time.time() < deadline:
            time.sleep(0.05)
        assert viewer.frame != 0  # playing advances the frames
        viewer.gui["play"].value = False
    finally:
        viewer.stop()
    with pytest.raises(OSError):
        _get(viewer.url + "/")  # nothing listens any more


def test_residual_markers_follow_the_diagnosis(run, tmp_path):
    data = load_run(_diagnosed_copy(run, tmp_path / "diagnosed"))
    viewer = start_viewer(data, port=0)
    try:
        marker = viewer.nodes["/residual/obj_1"]
        viewer.show_frame(0)
        assert tuple(marker.color) == panel.residual_rgb(0.0, 6.0)
        viewer.show_frame(6)
        assert tuple(marker.color) == panel.residual_rgb(6.0, 6.0)
        assert "residual_plot" in viewer.gui
    finally:
        viewer.stop()


# -------------------------------------------------------------------------------------- cli
def test_view_no_block_prints_the_address_and_keeps_serving(run, capsys):
    args = build_parser().parse_args(["view", str(run), "--port", "0", "--no-block"])
    assert args.handler(args) == 0
    try:
        line = capsys.readouterr().out.strip()
        assert line == f"viewing {run} at {args.viewer.url}"
        assert _get(args.viewer.url + "/")[0] == 200
    finally:
        args.viewer.stop()


@pytest.mark.parametrize("case", ["missing", "not a run", "no rollout"])
def test_view_errors_name_the_folder_and_what_is_missing(case, run, tmp_path, capsys):
    if case == "missing":
        folder, words = tmp_path / "nope", ["does not exist"]
    elif case == "not a run":
        folder, words = tmp_path, ["recipe.yaml", "mosiv run"]
    else:
        folder = shutil.copytree(run, tmp_path / "unevaluated")
        (folder / "rollout.npz").unlink()
        words = ["rollout.npz", f"mosiv eval {folder}"]
    assert main(["view", str(folder), "--no-block", "--port", "0"]) == EXIT_USAGE
    err = capsys.readouterr().err.strip()
    assert err.startswith("mosiv view: error:") and len(err.splitlines()) == 1
    assert str(folder) in err and all(w in err for w in words), err


def _default_sigint() -> None:
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def test_view_serves_until_ctrl_c_then_ends_with_130(run):
    proc = subprocess.Popen(
        [sys.executable, "-m", "mosiv_framework.cli.main", "view", str(run), "--port", "0"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        # a shell starts background jobs with SIGINT ignored and children inherit it: give the
        # server the disposition a terminal's Ctrl-C meets
        preexec_fn=_default_sigint,
    )
    try:
        line = proc.stdout.readline()  # printed once the server listens
        assert "Ctrl-C" in line, (line, proc.stderr.read() if proc.poll() is not None else "")
        url = line.split(" at ")[1].split()[0]
        assert _get(url + "/")[0] == 200
        os.kill(proc.pid, signal.SIGINT)
        out, err = proc.communicate(timeout=30)
    finally:
        proc.kill()
    assert proc.returncode == EXIT_INTERRUPTED
    assert err.strip().splitlines() == [
        "mosiv view: interrupted; rerun the same command to start it again"
    ]
    assert out.strip() == ""  # viser's own banner and "stopped" line stay off stdout


def test_view_frame_outside_the_run_is_refused(run, capsys, data):
    args = ["view", str(run), "--no-block", "--port", "0", "--frame", str(data.n_frames)]
    assert main(args) == EXIT_USAGE
    err = capsys.readouterr().err
    assert f"--frame {data.n_frames}" in err and f"0 to {data.n_frames - 1}" in err
