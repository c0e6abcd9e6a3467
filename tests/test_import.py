"""``mosiv data import``: a capture built here from a rendered scene (videos through a known
lens, COLMAP text cameras in cm with y up, cameras that started late) comes back as the scene.
"""

from __future__ import annotations

import shutil
import sys
from pathlib import Path

import numpy as np
import pycolmap
import pytest
import torch

from mosiv_framework.capture import CaptureError, ImportSettings, import_recording
from mosiv_framework.capture.colmap import MODEL_FILES, read_colmap, write_colmap
from mosiv_framework.capture.lens import (
    Distortion,
    distort_frames,
    distort_points,
    remap,
    undistort_frames,
    undistort_points,
)
from mosiv_framework.capture.nerfstudio import read_nerfstudio
from mosiv_framework.errors import OutputError
from mosiv_framework.scene import read_scene, validate_scene

pytest.importorskip("imageio_ffmpeg")

# the rendered scene, its capture and the shared helpers (--import-mode=importlib leaves this
# folder off sys.path)
HERE = Path(__file__).resolve().parent
if str(HERE) not in sys.path:
    sys.path.insert(0, str(HERE))
from capture_fakes import (  # noqa: E402
    LATE,
    LENS,
    N_FRAMES,
    RADIUS,
    RIG,
    SIZE,
    SPEED,
    expect_error,
    intrinsics,
    psnr,
    render_spheres,
    settings,
    sphere_paths,
    write_capture,
    write_model,
)


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Path:
    return render_spheres(tmp_path_factory.mktemp("scene") / "s", "slide", sphere_paths())


@pytest.fixture(scope="module")
def capture(scene, tmp_path_factory) -> Path:
    return write_capture(scene, tmp_path_factory.mktemp("capture") / "c")


@pytest.fixture(scope="module")
def imported(capture, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("imp") / "scene"
    return import_recording(settings(capture, out, late_cameras="trim"))


# ------------------------------------------------------------------------------ lens model
def test_undistort_points_inverts_distort_points():
    rng = np.random.default_rng(0)
    xy = rng.uniform(-0.5, 0.5, size=(200, 2))
    back = undistort_points(distort_points(xy, LENS), LENS)
    assert np.max(np.abs(back - xy)) < 1e-9


def test_undistort_frames_undoes_distort_frames(scene):
    s = read_scene(scene)
    cam = s.cameras[0]
    frames = np.stack([s.rgb(cam.id, t) for t in range(3)])
    lensed = distort_frames(frames, intrinsics(cam), LENS)
    moved, restored = (
        psnr(lensed, frames),
        psnr(undistort_frames(lensed, intrinsics(cam), LENS), frames),
    )
    # the lens moved pixels (the lensed frames differ), undistortion moves them back; two
    # bilinear resamplings blur, so the gain is measured: 2.6 dB on this scene
    assert restored > 30 and restored > moved + 1.5, (moved, restored)


def test_undistort_in_place_writes_the_same_frames_into_the_clip(scene):
    """``in_place`` (the import holds a long clip once) gives the frames a new array gets."""
    s = read_scene(scene)
    cam = s.cameras[0]
    frames = np.stack([s.rgb(cam.id, t) for t in range(20)])  # more than one block of 16
    lensed = distort_frames(frames, intrinsics(cam), LENS)
    expected = undistort_frames(lensed, intrinsics(cam), LENS)
    got = undistort_frames(lensed, intrinsics(cam), LENS, in_place=True)
    assert got is lensed and np.array_equal(got, expected)
    lensed.flags.writeable = False
    with pytest.raises(ValueError, match="writable uint8 .* read-only"):
        undistort_frames(lensed, intrinsics(cam), LENS, in_place=True)
    uv = np.zeros(lensed.shape[1:3] + (2,))
    overlapping = np.concatenate([lensed, lensed[:1]])
    with pytest.raises(ValueError, match="overlaps the frames"):
        remap(overlapping[1:], uv, out=overlapping[:-1])


def test_import_brought_down_to_a_resolution_scales_the_cameras(capture, imported, tmp_path):
    """``resolution`` 48 on the 96-pixel capture: frames half the size as they are read,
    every camera's focal lengths and principal point halved, the same frames otherwise."""
    import json

    from mosiv_framework.capture.video import shrink

    out = tmp_path / "half"
    import_recording(settings(capture, out, late_cameras="trim", resolution=SIZE // 2))
    full, half = read_scene(imported), read_scene(out)
    assert validate_scene(out) == [] and half.n_frames == full.n_frames
    for cam in full.cameras:
        mine = half.camera(cam.id)
        assert (mine.width, mine.height) == (SIZE // 2, SIZE // 2)
        assert (mine.fx, mine.fy, mine.cx, mine.cy) == pytest.approx(
            (cam.fx / 2, cam.fy / 2, cam.cx / 2, cam.cy / 2), abs=1e-9
        )
        assert torch.allclose(mine.world_to_camera, cam.world_to_camera, atol=1e-9)
        ref = np.stack([shrink(full.rgb(cam.id, t), (SIZE // 2,) * 2) for t in range(4)])
        assert psnr(np.stack([half.rgb(cam.id, t) for t in range(4)]), ref) > 27, cam.id
    assert json.loads((out / "import.json").read_text())["settings"]["resolution"] == SIZE // 2


# ----------------------------------------------------------------------------- the import
def test_import_recovers_cameras_frames_offsets(scene, imported):
    import json

    original, got = read_scene(scene), read_scene(imported)
    assert validate_scene(imported) == []
    assert got.camera_ids == original.camera_ids
    for cam in original.cameras:
        mine = got.camera(cam.id)
        assert (mine.fx, mine.fy, mine.cx, mine.cy) == pytest.approx(
            (cam.fx, cam.fy, cam.cx, cam.cy), abs=1e-9
        )
        assert torch.allclose(mine.world_to_camera, cam.world_to_camera, atol=1e-9)
    record = json.loads((imported / "import.json").read_text())
    # estimated drops: the earliest cameras lose what the late ones lack
    late_most = max(LATE.values())
    assert record["offsets"] == {c: late_most - LATE.get(c, 0) for c in original.camera_ids}
    assert record["offsets_estimated"] is True
    assert got.n_frames == N_FRAMES - late_most
    for cam in original.camera_ids:
        ref = np.stack([original.rgb(cam, t + late_most) for t in range(got.n_frames)])
        mine = np.stack([got.rgb(cam, t) for t in range(got.n_frames)])
        assert psnr(mine, ref) > 28, cam
    assert got.ground_height == 0.0
    paths = sphere_paths()[late_most:]
    assert np.all(paths.min(axis=(0, 1)) - RADIUS >= np.array(got.domain_lower) - 1e-9)
    assert np.all(paths.max(axis=(0, 1)) + RADIUS <= np.array(got.domain_upper))
    assert (imported / "preview" / "contact_sheet.png").is_file()


def test_masks_match_rendered_masks(scene, imported):
    original, got = read_scene(scene), read_scene(imported)
    shift = N_FRAMES - got.n_frames
    for cam in original.camera_ids:
        ref = np.stack([original.mask(cam, t + shift) for t in range(got.n_frames)])
        mine = np.stack([got.mask(cam, t) for t in range(got.n_frames)])
        iou = ((ref > 0) & (mine > 0)).sum() / ((ref > 0) | (mine > 0)).sum()
        assert iou > 0.7, (cam, iou)


def test_fitted_ground_and_inferred_up(scene, capture, tmp_path):
    """No --up, no --ground: up from the cameras, the ground under the first frames' hull."""
    out = import_recording(settings(capture, tmp_path / "s", up=None, ground=None))
    original, got = read_scene(scene), read_scene(out)
    for cam in original.cameras:
        mine = got.camera(cam.id)
        assert torch.allclose(mine.rotation, cam.rotation, atol=1e-6)
        shift = (mine.camera_center - cam.camera_center).numpy()
        # the spheres rest on the ground: the fitted ground lies within 3 cm of the true one
        assert np.abs(shift[:2]).max() < 1e-6 and abs(shift[2]) < 0.03


# ---------------------------------------------------------------------- other camera files
def test_nerfstudio_cameras_match(scene, tmp_path):
    import json

    original = read_scene(scene)
    frames = []
    for cam in original.cameras:
        c2w_gl = cam.camera_to_world.numpy() @ np.diag([1.0, -1.0, -1.0, 1.0])
        frames.append(
            {"file_path": f"images/{cam.id}.png", "transform_matrix": c2w_gl.tolist(),
             "fl_x": cam.fx, "fl_y": cam.fy}
        )  # fmt: skip
    path = tmp_path / "transforms.json"
    top = {"w": SIZE, "h": SIZE, "cx": SIZE / 2, "cy": SIZE / 2, "k1": LENS.k1, "frames": frames}
    path.write_text(json.dumps(top))
    cams = {c.id: c for c in read_nerfstudio(path, set(original.camera_ids))}
    for cam in original.cameras:
        assert np.allclose(cams[cam.id].world_to_camera, cam.world_to_camera.numpy(), atol=1e-9)
        assert cams[cam.id].intrinsics.fx == cam.fx and cams[cam.id].distortion.k1 == LENS.k1


def test_binary_colmap_model_reads_as_text(capture, tmp_path):
    rec = pycolmap.Reconstruction(str(capture / "sparse" / "0"))
    rec.write_binary(str(tmp_path))
    known = {f"cam_{i:02d}" for i in range(4)}
    text = {c.id: c for c in read_colmap(capture / "sparse" / "0", known)}
    binary = {c.id: c for c in read_colmap(tmp_path, known)}
    assert set(binary) == known
    for cid, cam in text.items():
        assert np.allclose(binary[cid].world_to_camera, cam.world_to_camera, atol=1e-9)
        assert binary[cid].intrinsics == cam.intrinsics and binary[cid].distortion == cam.distortion


# ------------------------------------------------------ COLMAP models written and read back
def varied_cameras(scene: Path, same_focal: bool) -> list:
    """The scene's cameras with focal lengths and principal points that differ per camera (and
    fx != fy unless ``same_focal``), so a mix-up between cameras or parameters shows."""
    from dataclasses import replace

    return [
        replace(
            cam,
            fx=cam.fx * (1 + 0.01 * i),
            fy=cam.fx * (1 + 0.01 * i) if same_focal else cam.fy * (1 - 0.02 * i),
            cx=cam.cx + 0.5 + 0.25 * i,
            cy=cam.cy - 0.75 * i,
        )
        for i, cam in enumerate(read_scene(scene).cameras)
    ]


@pytest.mark.parametrize("binary", [False, True], ids=["text", "binary"])
@pytest.mark.parametrize("model", ["OPENCV", "RADIAL", "FULL_OPENCV", "OPENCV_FISHEYE"])
def test_writer_and_reader_round_trip(scene, tmp_path, model, binary):
    lens = {
        "OPENCV": LENS,
        "RADIAL": Distortion(k1=LENS.k1, k2=LENS.k2),
        "FULL_OPENCV": Distortion(-0.2, 0.05, 1e-3, -2e-3, 0.01, 0.1, -0.02, 0.003),
        "OPENCV_FISHEYE": Distortion(k1=0.04, k2=-0.01, k3=2e-3, k4=-3e-4, model="fisheye"),
    }[model]
    cameras = varied_cameras(scene, same_focal=model == "RADIAL")
    names = [f"{cam.id}/frame_0001.png" for cam in cameras]  # the parent folder names the camera
    sizes = [(cam.width + 2 * i, cam.height + i) for i, cam in enumerate(cameras)]
    write_colmap(tmp_path, cameras, names=names, sizes=sizes, distortion=lens, model=model,
                 rig=RIG, binary=binary)  # fmt: skip
    ext = ".bin" if binary else ".txt"
    assert {f"{name}{ext}" for name in MODEL_FILES} <= {p.name for p in tmp_path.iterdir()}
    got = {c.id: c for c in read_colmap(tmp_path, {cam.id for cam in cameras})}
    assert sorted(got) == [cam.id for cam in cameras]
    for cam, size in zip(cameras, sizes):
        back = got[cam.id]
        assert back.model == model and f"images{ext}" in back.origin
        k = back.intrinsics
        assert (k.width, k.height) == size
        np.testing.assert_allclose(
            [k.fx, k.fy, k.cx, k.cy], [cam.fx, cam.fy, cam.cx, cam.cy], rtol=0, atol=1e-9
        )
        d, want = back.distortion.as_dict(), lens.as_dict()
        assert d.pop("model") == want.pop("model")
        np.testing.assert_allclose([d[n] for n in want], list(want.values()), rtol=0, atol=1e-9)
        # poses in the rig's world (cm, y up), and back in the scene's (m, z up)
        w2c = cam.world_to_camera.numpy()
        np.testing.assert_allclose(back.world_to_camera, RIG.world_to_camera(w2c), atol=1e-9)
        back_in_scene = RIG.scene_world_to_camera(back.world_to_camera)
        np.testing.assert_allclose(back_in_scene, w2c, rtol=0, atol=1e-9)


def test_model_without_rigs_and_frames_reads_the_same(scene, tmp_path):
    """Models of COLMAP before 3.12 have no rigs and frames files; the images hold the poses."""
    cameras, known = read_scene(scene).cameras, set(read_scene(scene).camera_ids)
    write_model(tmp_path / "new", cameras)
    old = Path(shutil.copytree(tmp_path / "new", tmp_path / "old"))
    (old / "rigs.txt").unlink()
    (old / "frames.txt").unlink()
    new_cams = {c.id: c for c in read_colmap(tmp_path / "new", known)}
    for cam in read_colmap(old, known):
        np.testing.assert_array_equal(cam.world_to_camera, new_cams[cam.id].world_to_camera)
        assert cam.intrinsics == new_cams[cam.id].intrinsics


# ------------------------------------------------------------------------------- bad input
def copy_capture(capture: Path, tmp_path: Path) -> Path:
    return Path(shutil.copytree(capture, tmp_path / "c"))


def test_unreadable_video_names_the_file(capture, tmp_path):
    c = copy_capture(capture, tmp_path)
    (c / "videos" / "cam_02.mp4").write_bytes(b"not a video at all")
    expect_error(settings(c, tmp_path / "s"), OutputError, "cam_02.mp4", "cannot be read")


def test_camera_without_frames(scene, tmp_path):
    c = write_capture(scene, tmp_path / "c", drop_video="cam_03")
    expect_error(settings(c, tmp_path / "s"), CaptureError, "images.txt", "cam_03", "no frames")


def test_unknown_colmap_camera_model(capture, tmp_path):
    c = copy_capture(capture, tmp_path)
    path = c / "sparse" / "0" / "cameras.txt"
    lines = path.read_text().splitlines()
    first = next(i for i, line in enumerate(lines) if not line.startswith("#"))
    lines[first] = lines[first].replace("OPENCV", "FOV").rsplit(" ", 3)[0]
    path.write_text("\n".join(lines) + "\n")
    expect_error(
        settings(c, tmp_path / "s"),
        CaptureError, "cameras.txt", "'FOV'", "SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV",
    )  # fmt: skip


def first_camera_line(path: Path) -> tuple[list[str], int]:
    lines = path.read_text().splitlines()
    return lines, next(i for i, line in enumerate(lines) if not line.startswith("#"))


def test_colmap_model_name_that_colmap_does_not_know(scene, tmp_path):
    write_model(tmp_path, read_scene(scene).cameras)
    lines, first = first_camera_line(tmp_path / "cameras.txt")
    lines[first] = lines[first].replace("OPENCV", "OPENCV_PLUS")
    (tmp_path / "cameras.txt").write_text("\n".join(lines) + "\n")
    with pytest.raises(CaptureError) as info:
        read_colmap(tmp_path, set(read_scene(scene).camera_ids))
    message = str(info.value)
    for word in ("cameras.txt", f"line {first + 1}", "'OPENCV_PLUS'", "is unknown",
                 "SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV"):  # fmt: skip
        assert word in message, (word, message)


def test_binary_colmap_model_id_that_colmap_does_not_know(scene, tmp_path):
    cameras = read_scene(scene).cameras
    write_colmap(tmp_path, cameras, names=[f"{c.id}.mp4" for c in cameras], binary=True)
    data = bytearray((tmp_path / "cameras.bin").read_bytes())
    # cameras.bin: camera count (uint64), then per camera its id (uint32) and model id (int32)
    data[12:16] = (999).to_bytes(4, "little")
    (tmp_path / "cameras.bin").write_bytes(bytes(data))
    with pytest.raises(CaptureError) as info:
        read_colmap(tmp_path, {c.id for c in cameras})
    message = str(info.value)
    assert str(tmp_path) in message and ".bin model" in message, message
    assert "camera model" in message.lower(), message
    assert "supported models: SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL" in message, message


@pytest.mark.parametrize("name", ["cameras.bin", "images.bin"])
@pytest.mark.parametrize("keep", [0.5, -5, 3])  # half, all but 5 bytes, less than the count
def test_truncated_binary_colmap_file_is_named(scene, tmp_path, name, keep):
    # pycolmap reads such files as garbage or fails with an allocation error
    cameras = read_scene(scene).cameras
    write_colmap(tmp_path, cameras, names=[f"{c.id}.mp4" for c in cameras], binary=True)
    data = (tmp_path / name).read_bytes()
    cut = int(len(data) * keep) if isinstance(keep, float) else keep % len(data)
    (tmp_path / name).write_bytes(data[:cut])
    with pytest.raises(CaptureError) as info:
        read_colmap(tmp_path, {c.id for c in cameras})
    message = str(info.value)
    assert str(tmp_path / name) in message and "truncated" in message, message
    assert f"has {cut}" in message or f"{cut} bytes" in message, message


def test_missing_colmap_file_is_named(capture, tmp_path):
    c = copy_capture(capture, tmp_path)
    (c / "sparse" / "0" / "images.txt").unlink()
    expect_error(settings(c, tmp_path / "s"), CaptureError, "images.txt missing", "points3D")


@pytest.mark.parametrize("binary", [False, True], ids=["text", "binary"])
def test_colmap_folder_without_a_model(scene, tmp_path, binary):
    cameras, known = read_scene(scene).cameras, set(read_scene(scene).camera_ids)
    names = [f"{c.id}.mp4" for c in cameras]
    write_colmap(tmp_path / "m", cameras, names=names, binary=binary)
    ext = ".bin" if binary else ".txt"
    (tmp_path / "m" / f"points3D{ext}").unlink()
    with pytest.raises(CaptureError, match=f"points3D\\{ext} missing"):
        read_colmap(tmp_path / "m", known)
    with pytest.raises(CaptureError, match="does not exist or is not a folder"):
        read_colmap(tmp_path / "nowhere", known)


def test_colmap_camera_with_zero_focal_length(scene, tmp_path):
    write_model(tmp_path, read_scene(scene).cameras)
    lines, first = first_camera_line(tmp_path / "cameras.txt")
    tok = lines[first].split()  # CAMERA_ID MODEL WIDTH HEIGHT fx fy ...
    lines[first] = " ".join([*tok[:4], "0", *tok[5:]])
    (tmp_path / "cameras.txt").write_text("\n".join(lines) + "\n")
    with pytest.raises(CaptureError, match=r"cameras\.txt: camera 1: .*must be positive.*fx=0\.0"):
        read_colmap(tmp_path, set(read_scene(scene).camera_ids))


def test_pose_with_the_scene_behind_the_camera(scene, tmp_path):
    from dataclasses import replace

    cameras = read_scene(scene).cameras
    turn = torch.diag(torch.tensor([-1.0, 1.0, -1.0, 1.0], dtype=torch.float64))
    # half a turn about the camera's y axis: it looks away from the scene
    cameras[2] = replace(cameras[2], world_to_camera=turn @ cameras[2].world_to_camera)
    c = copy_capture(write_capture(scene, tmp_path / "orig"), tmp_path)
    write_model(c / "sparse" / "0", cameras)
    expect_error(settings(c, tmp_path / "s"), CaptureError, "images.txt", "'cam_02'", "behind")


def test_refuses_a_non_empty_out(capture, tmp_path):
    out = tmp_path / "s"
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    with pytest.raises(OutputError, match="non-empty"):
        import_recording(settings(capture, out))
    assert (out / "keep.txt").read_text() == "mine"


def test_cli_reports_bad_input_with_one_line(capture, tmp_path, capsys):
    from mosiv_framework.cli.main import main

    code = main(
        ["data", "import", str(tmp_path / "s"), "--recording", str(capture), "--units", "cm",
         "--up", "y", "--ground", "y=0", "--materials", "elastic,sand", "--offsets", "none",
         "--late-cameras", "trim"]
    )  # fmt: skip
    err = capsys.readouterr().err
    assert code == 2
    assert err.startswith("mosiv data: error: cameras have different frame counts")
    assert "Traceback" not in err


# ---------------------------------------------------------- round trip with the capture writer
FISHEYE = Distortion(k1=0.03, k2=-0.005, model="fisheye")


@pytest.mark.parametrize(
    ("lens", "camera_model"),
    [(LENS, "OPENCV"), (FISHEYE, "OPENCV_FISHEYE")],
    ids=["opencv", "fisheye"],
)
def test_round_trip_with_the_capture_writer(scene, tmp_path, lens, camera_model):
    import json

    from mosiv_framework.capture import find_inputs
    from mosiv_framework.capture import write_capture as write_rig_capture

    rig = write_rig_capture(
        scene, tmp_path / "rig", rig=RIG, distortion=lens, camera_model=camera_model,
        offsets="cam_02=3",
    )  # fmt: skip

    found = find_inputs(rig)
    out = import_recording(
        ImportSettings(out=tmp_path / "s", materials="elastic,sand", units="cm", up="y",
                       ground="y=0", **found)
    )  # fmt: skip
    original, got = read_scene(scene), read_scene(out)
    assert validate_scene(out) == []
    for cam in original.cameras:
        assert torch.allclose(got.camera(cam.id).world_to_camera, cam.world_to_camera, atol=1e-9)
    record = json.loads((out / "import.json").read_text())
    assert record["distortion"]["cam_00"] == lens.as_dict()
    assert record["offsets"] == {c: 0 if c == "cam_02" else 3 for c in original.camera_ids}
    # the default --late-cameras keep: every frame, cam_02 declared as starting 3 frames late
    assert got.n_frames == original.n_frames and got.camera_frames == {
        "cam_02": (3, original.n_frames - 1)
    }
    for cam in ("cam_00", "cam_02"):
        frames = got.recorded_frames(cam)
        ref = np.stack([original.rgb(cam, t) for t in frames])
        # 35-36 dB after H.264 and two resamplings; the fisheye's frames imported as if
        # through a pinhole read about 30 dB
        assert psnr(np.stack([got.rgb(cam, t) for t in frames]), ref) > 33, cam


# --------------------------------------------------------------- clean plates of the empty scene
SLIDE = 8  # frames the spheres of the settling scene slide before they rest


def settling_paths() -> np.ndarray:
    """[T, 2, 3] centres: two spheres sliding for SLIDE frames, then at rest to the end."""
    t = np.minimum(np.arange(N_FRAMES), SLIDE)[:, None]
    a = np.array([-0.2, -0.35, RADIUS]) + t * np.array([0.0, SPEED, 0.0])
    b = np.array([0.2, 0.33, RADIUS]) + t * np.array([0.0, -SPEED, 0.0])
    return np.stack([a, b], axis=1)


@pytest.fixture(scope="module")
def settling(tmp_path_factory) -> Path:
    """The two spheres slide for the first frames, then rest where they stopped for most of the
    clip: each pixel's median over time shows a resting sphere, not the table."""
    return render_spheres(tmp_path_factory.mktemp("settling") / "s", "settle", settling_paths())


def worst_mask_iou(original, got) -> float:
    """The lowest per-frame IoU of the objects' union over every camera and frame."""
    worst = 1.0
    for cam in original.camera_ids:
        for t in range(got.n_frames):
            ref, mine = original.mask(cam, t) > 0, got.mask(cam, t) > 0
            worst = min(worst, (ref & mine).sum() / max((ref | mine).sum(), 1))
    return float(worst)


def test_a_clean_plate_keeps_resting_objects_out_of_the_background(settling, tmp_path):
    """A rig's clean plate (``mosiv data capture --background-plate``, found in background/ by
    the import) is the segmenter's background; without it the temporal median paints the
    resting spheres into the background, the segmenter loses them while they rest, and the
    import says so and how to give a background."""
    from mosiv_framework.capture import find_inputs
    from mosiv_framework.capture import write_capture as write_rig_capture
    from mosiv_framework.capture.write import empty_plate

    rig = write_rig_capture(settling, tmp_path / "rig", rig=RIG, distortion=LENS, with_plates=True)
    original = read_scene(settling)
    for cam in original.cameras:
        plate, never_free = empty_plate(original, cam.id)
        free = np.stack([original.mask(cam.id, t) == 0 for t in range(N_FRAMES)])
        assert never_free <= 5  # where a sphere at rest overlaps where it started
        assert plate.shape == (SIZE, SIZE, 3)
        # where a sphere rests the plate is the table the first frames show, not the sphere
        resting = ~free[-1] & free[0]
        assert resting.sum() > 20
        np.testing.assert_array_equal(plate[resting], original.rgb(cam.id, 0)[resting])
    found = find_inputs(rig)
    assert found["background"] == rig / "background"
    common = dict(materials="elastic,sand", units="cm", up="y", ground="y=0", offsets="none")
    with_plate = import_recording(ImportSettings(out=tmp_path / "p", **common, **found))
    # MEASURED 0.85 with the rim of mixed pixels trimmed (edge_fraction 0.5)
    assert worst_mask_iou(original, read_scene(with_plate)) > 0.8
    found.pop("background")
    # the median shows the resting spheres: they vanish into the background once they rest,
    # which the import names instead of writing a scene without them
    expect_error(
        ImportSettings(out=tmp_path / "m", **common, **found), CaptureError,
        "lost objects", f"object 1 in frame(s) {SLIDE}, ", "--background DIR", "background_frames",
    )  # fmt: skip


def test_a_plate_of_the_wrong_size_is_named(settling, tmp_path):
    import imageio.v3 as iio

    from mosiv_framework.capture import find_inputs
    from mosiv_framework.capture import write_capture as write_rig_capture

    rig = write_rig_capture(settling, tmp_path / "rig", rig=RIG, with_plates=True)
    iio.imwrite(rig / "background" / "cam_02.png", np.zeros((SIZE, SIZE + 4, 3), np.uint8))
    s = ImportSettings(out=tmp_path / "s", materials="elastic,sand", units="cm", up="y",
                       ground="y=0", offsets="none", **find_inputs(rig))  # fmt: skip
    expect_error(s, CaptureError, "cam_02.png", f"{SIZE + 4}x{SIZE}", f"{SIZE}x{SIZE}")
    (rig / "background" / "cam_02.png").unlink()
    expect_error(s, CaptureError, "cam_02", "background")


def test_the_import_says_what_its_domain_means_for_the_simulator_cell():
    from mosiv_framework.cli.importing import resolution_note

    note = resolution_note(1.0798)
    assert "largest side 1.08 m" in note
    assert "simulator.grid=64 simulates it at 1.69 cm cells" in note
    assert "simulator.cell_size=0.0125 (as recipes/video_paper.yaml) at grid 86" in note
    assert "at grid 64" in resolution_note(0.8)
    # the note names the shipped recipe's cell: it must be that recipe's
    import inspect

    import yaml

    recipe = yaml.safe_load(
        (Path(__file__).parents[1] / "recipes" / "video_paper.yaml").read_text()
    )
    default = inspect.signature(resolution_note).parameters["cell_size"].default
    assert recipe["simulator"]["cell_size"] == default
