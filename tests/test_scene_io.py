"""Reading and writing mosiv-scene/1 folders, with the example scene as the fixture."""

import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from mosiv_framework.errors import SceneFormatError
from mosiv_framework.scene import (
    SceneObject,
    SceneWriter,
    atomic_write_bytes,
    read_scene,
    run_check,
    write_example_scene,
    write_scene,
)
from mosiv_framework.types import World


@pytest.fixture(scope="module")
def example(tmp_path_factory) -> Path:
    return write_example_scene(tmp_path_factory.mktemp("example") / "scene", seed=3)


def leftovers(root: Path) -> list[str]:
    return [p.name for p in root.rglob("*") if p.name.startswith(".") or p.suffix == ".tmp"]


def test_read_scene_fields(example):
    scene = read_scene(example)
    assert scene.name == "example-two-spheres-0003"
    assert (scene.fps, scene.n_frames, scene.observed_frames) == (24.0, 4, 2)
    assert [(o.id, o.material) for o in scene.objects] == [(1, "elastic"), (2, "plasticine")]
    assert scene.materials == {1: "elastic", 2: "plasticine"}
    assert scene.camera_ids == ["cam_00", "cam_01", "cam_02", "cam_03"]
    assert all((c.width, c.height) == (32, 32) and c.is_rigid for c in scene.cameras)
    assert scene.world == World((-0.5, -0.5, 0.0), (0.5, 0.5, 1.0), (0.0, 0.0, -9.8), 0.0, 24.0)
    with pytest.raises(KeyError, match="cam_00"):
        scene.camera("nope")
    with pytest.raises(IndexError, match="frame 4"):
        scene.rgb("cam_00", 4)


def test_images_and_masks(example):
    scene = read_scene(example)
    rgb, mask = scene.rgb("cam_01", 2), scene.mask("cam_01", 2)
    assert rgb.shape == (32, 32, 3) and rgb.dtype == np.uint8
    assert mask.shape == (32, 32) and mask.dtype == np.uint8
    assert set(np.unique(mask).tolist()) <= {0, 1, 2}
    frames = scene.load_rgb_tensor()
    assert frames.shape == (4, 4, 32, 32, 3) and frames.dtype == torch.float32
    torch.testing.assert_close(frames[2, 1], torch.from_numpy(rgb).float() / 255.0)
    masks = scene.load_masks(frames=[2], cameras=["cam_01"])
    assert masks.shape == (1, 1, 2, 32, 32)
    for k in (1, 2):
        assert torch.equal(masks[0, 0, k - 1], torch.from_numpy(mask == k).float())
    ids = scene.load_mask_ids(frames=[2], cameras=["cam_01"])
    assert ids.dtype == torch.int64 and np.array_equal(ids[0, 0].numpy(), mask)
    # both objects are visible somewhere in frame 0
    assert set(np.unique(scene.load_mask_ids(frames=[0]).numpy()).tolist()) == {0, 1, 2}


def test_masks_agree_with_camera_projection(example):
    """The renderer's ray cast and Camera.project share one convention: each sphere's centre
    projects onto a pixel its own mask covers, and the mask area matches the projected disc."""
    scene = read_scene(example)
    points = scene.gt_points()
    for cam in scene.cameras:
        for t in (0, 3):
            mask = scene.mask(cam.id, t)
            for k, pts in points.items():
                centre = pts[t].double().mean(0, keepdim=True)
                uv, depth = cam.project(centre)
                col, row = (int(x) for x in uv[0].floor())
                assert mask[row, col] == k, (cam.id, t, k)


def test_ground_truth(example):
    scene = read_scene(example)
    assert scene.has_gt
    points = scene.gt_points()
    assert sorted(points) == [1, 2]
    assert all(p.shape == (4, 256, 3) and p.dtype == torch.float32 for p in points.values())
    dt = scene.world.frame_dt
    params = scene.gt_params()
    for entry in params["objects"]:
        centroid = points[entry["id"]].double().mean(1)  # rigid motion: centroid = path + const
        # ballistic flight: second differences equal g dt^2
        accel = (centroid[2:] - 2 * centroid[1:-1] + centroid[:-2]) / dt**2
        torch.testing.assert_close(
            accel, torch.tensor([[0.0, 0.0, -9.8]] * 2, dtype=torch.float64), atol=2e-3, rtol=0
        )
        # x(dt) - x(0) = v0 dt + g dt^2 / 2
        v0 = (centroid[1] - centroid[0] - 0.5 * torch.tensor([0, 0, -9.8]) * dt**2) / dt
        torch.testing.assert_close(
            v0, torch.tensor(entry["initial_velocity"], dtype=torch.float64), atol=1e-4, rtol=0
        )
    assert [o["material"] for o in params["objects"]] == ["elastic", "plasticine"]
    assert scene.gt_effects() == []


def test_write_scene_round_trip(example, tmp_path):
    src = read_scene(example)
    rgb = {c: np.stack([src.rgb(c, t) for t in range(4)]) for c in src.camera_ids}
    masks = {c: np.stack([src.mask(c, t) for t in range(4)]) for c in src.camera_ids}
    effects = [{"kind": "wind", "params": {"acceleration": [1.5, 0.0, 0.0]}}]
    out = write_scene(
        tmp_path / "copy",
        name="copy",
        fps=src.fps,
        objects=src.objects,
        cameras=src.cameras,
        rgb=rgb,
        masks=masks,
        domain_lower=src.domain_lower,
        domain_upper=src.domain_upper,
        observed_frames=3,
        ground_height=None,
        gt_points=src.gt_points(),
        gt_params=src.gt_params(),
        gt_effects=effects,
    )
    back = read_scene(out)
    assert (back.name, back.n_frames, back.observed_frames, back.ground_height) == (
        "copy",
        4,
        3,
        None,
    )
    assert [c.to_dict() for c in back.cameras] == [c.to_dict() for c in src.cameras]
    assert np.array_equal(back.rgb("cam_03", 1), src.rgb("cam_03", 1))
    assert np.array_equal(back.mask("cam_02", 3), src.mask("cam_02", 3))
    assert torch.equal(back.gt_points()[2], src.gt_points()[2])
    assert back.gt_effects() == effects
    assert leftovers(out) == []


def test_atomic_write_leaves_old_file_or_new_file(tmp_path, monkeypatch):
    target = tmp_path / "a" / "scene.json"
    atomic_write_bytes(target, b"old")

    def interrupted(src, dst):
        raise KeyboardInterrupt  # the generator is stopped between writing and renaming

    monkeypatch.setattr(os, "replace", interrupted)
    with pytest.raises(KeyboardInterrupt):
        atomic_write_bytes(target, b"new content")
    assert target.read_bytes() == b"old"
    assert leftovers(tmp_path) == []
    monkeypatch.undo()
    atomic_write_bytes(target, b"new content")
    assert target.read_bytes() == b"new content"
    assert leftovers(tmp_path) == []


def test_writer_refuses_an_incomplete_scene(tmp_path):
    src = read_scene(write_example_scene(tmp_path / "src", n_frames=2, n_cameras=2, size=8))
    writer = SceneWriter(
        tmp_path / "partial",
        name="partial",
        fps=24.0,
        n_frames=2,
        observed_frames=1,
        objects=[SceneObject(1, "a", "elastic")],
        cameras=src.cameras,
        domain_lower=(0, 0, 0),
        domain_upper=(1, 1, 1),
    )
    for cam in src.cameras:
        writer.write_frame(cam.id, 0, rgb=src.rgb(cam.id, 0), mask=np.zeros((8, 8), np.uint8))
    with pytest.raises(ValueError, match="expected \\[8, 8, 3\\]"):
        writer.write_frame(
            "cam_00", 1, rgb=np.zeros((8, 8), np.uint8), mask=np.zeros((8, 8), np.uint8)
        )
    with pytest.raises(SceneFormatError) as err:
        writer.finish()
    assert "rgb/cam_00/0001.png: missing frame" in str(err.value)
    assert "masks/cam_01/0001.png: missing frame" in str(err.value)


def test_read_errors_name_the_file(example, tmp_path):
    broken = Path(shutil.copytree(example, tmp_path / "broken"))
    (broken / "rgb" / "cam_01" / "0002.png").unlink()
    scene_json = json.loads((broken / "scene.json").read_text())
    scene_json["objects"][0]["material"] = "jelly"
    (broken / "scene.json").write_text(json.dumps(scene_json))
    with pytest.raises(SceneFormatError) as err:
        read_scene(broken)
    problems = err.value.problems
    assert any("rgb/cam_01/0002.png" in p and "missing" in p for p in problems)
    assert any("scene.json" in p and "jelly" in p for p in problems)

    (broken / "cameras.json").unlink()
    with pytest.raises(SceneFormatError, match="cameras.json: missing"):
        read_scene(broken)

    # a PNG that breaks after loading is reported by name when it is read
    ok = Path(shutil.copytree(example, tmp_path / "ok"))
    scene = read_scene(ok)
    (ok / "masks" / "cam_00" / "0001.png").write_bytes(b"\x89PNG\r\n\x1a\n garbage")
    with pytest.raises(SceneFormatError, match="masks/cam_00/0001.png"):
        scene.mask("cam_00", 1)


def test_example_refuses_a_non_empty_folder(example):
    with pytest.raises(FileExistsError, match="not empty"):
        write_example_scene(example)


def test_readers_turn_bad_files_into_scene_format_errors(example, tmp_path):
    """After read_scene, a gt file that breaks (or a scene changed under the reader) is a
    SceneFormatError naming the file, never a numpy, zipfile, OSError or JSON traceback."""
    root = Path(shutil.copytree(example, tmp_path / "scene"))
    scene = read_scene(root)
    points = root / "gt" / "points.npz"
    points.write_bytes(points.read_bytes()[:100])
    with pytest.raises(SceneFormatError, match="gt/points.npz: cannot be read as .npz"):
        scene.gt_points()
    (root / "gt" / "effects.json").write_text("{not json")
    with pytest.raises(SceneFormatError, match="gt/effects.json: is not valid JSON"):
        scene.gt_effects()
    (root / "gt" / "params.json").unlink()
    (root / "gt" / "params.json").mkdir()
    with pytest.raises(SceneFormatError, match="gt/params.json: is a folder"):
        scene.gt_params()


def test_read_scene_names_files_that_change_while_read(example, tmp_path, monkeypatch):
    root = Path(shutil.copytree(example, tmp_path / "scene"))
    from mosiv_framework.scene import io as scene_io

    def vanished(path):
        raise FileNotFoundError(2, "No such file or directory", str(root / "cameras.json"))

    monkeypatch.setattr(scene_io, "_build_scene", vanished)
    with pytest.raises(SceneFormatError, match="changed while being read") as err:
        read_scene(root)
    assert str(root / "cameras.json") in str(err.value)


# ------------------------------------------------------------- cameras that missed frames
def test_a_late_camera_is_read_with_its_recorded_frames(example, tmp_path):
    from mosiv_framework.testing.views import with_recorded_frames

    late = read_scene(with_recorded_frames(example, tmp_path / "late", {"cam_01": (2, 3)}))
    lines: list[str] = []
    assert run_check(late.root, out=lines.append) == 0
    assert lines[-1].endswith("; cam_01 recorded frames 2..3 only")
    assert late.recorded_frames("cam_01") == range(2, 4)
    assert late.records("cam_00", 0) and not late.records("cam_01", 1)
    assert [c.id for c in late.cameras_at(1)] == [c for c in late.camera_ids if c != "cam_01"]
    views = late.view_mask(frames=[0, 2], cameras=["cam_00", "cam_01"])
    assert views.tolist() == [[True, False], [True, True]]
    with pytest.raises(SceneFormatError, match="camera 'cam_01' recorded frames 2..3 only"):
        late.rgb("cam_01", 0)
    with pytest.raises(SceneFormatError, match="not frame 1"):
        late.load_mask_ids(frames=[1])
    rgb = late.load_rgb_tensor(frames=[1, 2], missing="zeros")
    ids = late.load_mask_ids(frames=[1, 2], missing="zeros")
    col = late.camera_ids.index("cam_01")
    assert rgb[0, col].abs().sum() == 0 and ids[0, col].abs().sum() == 0
    full = read_scene(example)
    assert torch.equal(rgb[1], full.load_rgb_tensor(frames=[2])[0])
    assert torch.equal(ids[:, 0], full.load_mask_ids(frames=[1, 2])[:, 0])


def test_the_writer_writes_a_camera_that_started_late(example, tmp_path):
    src = read_scene(example)
    writer = SceneWriter(
        tmp_path / "late",
        name="late",
        fps=src.fps,
        n_frames=src.n_frames,
        observed_frames=src.observed_frames,
        objects=src.objects,
        cameras=src.cameras,
        domain_lower=src.domain_lower,
        domain_upper=src.domain_upper,
        camera_frames={"cam_02": (1, src.n_frames - 1)},
    )
    with pytest.raises(IndexError, match="frame 0 of camera 'cam_02' outside 1.."):
        writer.write_frame("cam_02", 0, rgb=src.rgb("cam_02", 0), mask=src.mask("cam_02", 0))
    for cam in src.camera_ids:
        for t in src.recorded_frames(cam):
            if (cam, t) != ("cam_02", 0):
                writer.write_frame(cam, t, rgb=src.rgb(cam, t), mask=src.mask(cam, t))
    back = read_scene(writer.finish())
    assert back.camera_frames == {"cam_02": (1, src.n_frames - 1)}
    assert not back.records("cam_02", 0) and back.records("cam_02", 1)
