"""``mosiv data capture``: a scene written as a capture rig delivers it.

The example scene (ray-traced spheres) is written in centimetres with y up, through a barrel
lens, with one camera starting late; the videos must decode to the right frame counts and sizes,
the COLMAP text model must parse with pycolmap and give back the scene's cameras, and the lens
model's inverse must undo its forward map.
"""

from __future__ import annotations

import json
import warnings

import numpy as np
import pycolmap
import pytest

from mosiv_framework.capture import Distortion, RigFrame
from mosiv_framework.capture.lens import (
    Intrinsics,
    distort_frames,
    distort_pixels,
    distort_points,
    undistort_pixels,
    undistort_points,
)
from mosiv_framework.cli.main import main
from mosiv_framework.errors import ConfigError
from mosiv_framework.scene import read_scene, write_example_scene

imageio_ffmpeg = pytest.importorskip("imageio_ffmpeg")

N_FRAMES = 5
SIZE = 33  # odd on purpose: yuv420p needs even sizes, so the writer pads one row and column
LENS = Distortion(k1=-0.25, k2=0.06)


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory):
    return write_example_scene(
        tmp_path_factory.mktemp("scene") / "scene", n_frames=N_FRAMES, n_cameras=3, size=SIZE
    )


@pytest.fixture(scope="module")
def capture(scene_dir, tmp_path_factory):
    out = tmp_path_factory.mktemp("capture") / "cap"
    argv = ["data", "capture", str(scene_dir), str(out), "--units", "cm", "--up", "y"]
    argv += [f"--distortion={LENS.k1},{LENS.k2}", "--offsets", "cam_01=2", "--crf", "10"]
    assert main(argv) == 0
    return out


def _decode(path):
    reader = imageio_ffmpeg.read_frames(str(path))
    meta = next(reader)
    frames = [
        np.frombuffer(f, np.uint8).reshape(meta["size"][1], meta["size"][0], 3) for f in reader
    ]
    return meta, frames


def test_layout_has_no_masks_or_ground_truth(capture, scene_dir):
    files = sorted(str(p.relative_to(capture)) for p in capture.rglob("*") if p.is_file())
    assert files == [
        "capture.json",
        "sparse/0/cameras.txt",
        "sparse/0/frames.txt",
        "sparse/0/images.txt",
        "sparse/0/points3D.txt",
        "sparse/0/rigs.txt",
        "videos/cam_00.mp4",
        "videos/cam_01.mp4",
        "videos/cam_02.mp4",
    ]
    meta = json.loads((capture / "capture.json").read_text())
    assert meta["fps"] == read_scene(scene_dir).fps
    starts = {c["id"]: (c["start_frame"], c["n_frames"]) for c in meta["cameras"]}
    assert starts == {"cam_00": (0, 5), "cam_01": (2, 3), "cam_02": (0, 5)}
    assert (meta["units"], meta["up"], meta["distortion"]["k1"]) == ("cm", "y", LENS.k1)


def test_videos_decode_to_the_frames_through_the_lens(capture, scene_dir):
    scene = read_scene(scene_dir)
    meta = json.loads((capture / "capture.json").read_text())
    for entry in meta["cameras"]:
        video_meta, frames = _decode(capture / entry["video"])
        assert video_meta["codec"] == "h264" and video_meta["size"] == (SIZE + 1, SIZE + 1)
        assert len(frames) == N_FRAMES - entry["start_frame"]
        cam = scene.camera(entry["id"])
        for i, frame in enumerate(frames):
            t = entry["start_frame"] + i
            expected = distort_frames(scene.rgb(cam.id, t)[None], cam, LENS)[0]
            # H.264 at crf 10 with 4:2:0 chroma: mean error of a few grey levels
            err = np.abs(frame[:SIZE, :SIZE].astype(float) - expected).mean()
            undistorted = np.abs(frame[:SIZE, :SIZE].astype(float) - scene.rgb(cam.id, t)).mean()
            assert err < 4.0 and err < undistorted, (entry["id"], t, err, undistorted)


def test_colmap_model_parses_and_gives_back_the_scene_cameras(capture, scene_dir):
    scene = read_scene(scene_dir)
    rec = pycolmap.Reconstruction(str(capture / "sparse" / "0"))
    assert len(rec.cameras) == 3 and len(rec.images) == 3 and len(rec.points3D) == 0
    rig = RigFrame("cm", "y")
    for image in rec.images.values():
        cam = scene.camera(image.name.removesuffix(".mp4"))
        colmap_cam = rec.cameras[image.camera_id]
        assert colmap_cam.model.name == "OPENCV"
        assert (colmap_cam.width, colmap_cam.height) == (SIZE + 1, SIZE + 1)
        np.testing.assert_allclose(
            colmap_cam.params, [cam.fx, cam.fy, cam.cx, cam.cy, LENS.k1, LENS.k2, 0, 0]
        )
        rig_w2c = np.eye(4)
        rig_w2c[:3] = image.cam_from_world().matrix()
        back = rig.scene_world_to_camera(rig_w2c)
        np.testing.assert_allclose(back, cam.world_to_camera.numpy(), atol=1e-9)
        # in the rig's world the camera centre is in cm with y up: the scene's z is its y
        centre = -rig_w2c[:3, :3].T @ rig_w2c[:3, 3]
        scene_centre = cam.camera_center.numpy()
        np.testing.assert_allclose(centre, 100 * scene_centre[[0, 2, 1]] * [1, 1, -1], atol=1e-7)


def test_radial_model_and_refusals(scene_dir, tmp_path, capsys):
    out = tmp_path / "radial"
    argv = ["data", "capture", str(scene_dir), str(out), "--camera-model", "RADIAL"]
    assert main([*argv, "--distortion", "0.1,0.0"]) == 0
    rec = pycolmap.Reconstruction(str(out / "sparse" / "0"))
    assert {c.model.name for c in rec.cameras.values()} == {"RADIAL"}
    assert main([*argv, "--distortion", "0.1,0.0"]) == 6  # not empty now: refused
    assert "non-empty folder" in capsys.readouterr().err
    other = tmp_path / "tangential"
    assert main(["data", "capture", str(scene_dir), str(other), "--camera-model", "RADIAL",
                 "--distortion", "0.1,0,0.01,0"]) == 2  # fmt: skip
    assert "RADIAL" in capsys.readouterr().err and not other.exists()
    assert main(["data", "capture", str(scene_dir), str(other), "--offsets", "cam_09=1"]) == 2
    assert "cam_09" in capsys.readouterr().err
    assert main(["data", "capture", str(scene_dir), str(other), "--distortion", "0.1"]) == 2


def test_with_reference_copies_gt_beside_the_capture(scene_dir, tmp_path):
    out = tmp_path / "bench"
    assert main(["data", "capture", str(scene_dir), str(out), "--with-reference"]) == 0
    assert sorted(p.name for p in (out / "reference_gt").iterdir()) == ["params.json", "points.npz"]
    assert not (out / "gt").exists()


LENSES = [
    LENS,
    Distortion(0.2, -0.05, 0.01, -0.02),
    Distortion(-0.1, 0.02, 1e-3, 2e-3, -5e-3),
    Distortion(-0.2, 0.05, 1e-3, -2e-3, 0.01, 0.1, -0.02, 0.003),  # rational (FULL_OPENCV)
    Distortion(k1=0.04, k2=-0.01, k3=2e-3, k4=-3e-4, model="fisheye"),
    Distortion(model="fisheye"),  # equidistant: not a pinhole
]


@pytest.mark.parametrize("lens", [*LENSES, Distortion()])
def test_distortion_inverse_round_trips_below_a_thousandth_of_a_pixel(lens):
    k = Intrinsics(320, 240, fx=300.0, fy=290.0, cx=160.5, cy=119.0)
    vv, uu = np.meshgrid(np.linspace(0, 240, 49), np.linspace(0, 320, 65), indexing="ij")
    uv = np.stack([uu, vv], -1)
    back = undistort_pixels(distort_pixels(uv, lens, k), lens, k)
    assert np.abs(back - uv).max() < 1e-3
    # and the other way round: undistort, then distort
    again = distort_pixels(undistort_pixels(uv, lens, k), lens, k)
    assert np.abs(again - uv).max() < 1e-3


def test_forward_model_matches_opencv_formula_by_hand():
    """One point worked by hand: x = 0.3, y = -0.2, r^2 = 0.13."""
    lens = Distortion(0.1, 0.01, 0.002, -0.003, 0.004)
    x, y, r2 = 0.3, -0.2, 0.13
    radial = 1 + 0.1 * r2 + 0.01 * r2**2 + 0.004 * r2**3
    xd = x * radial + 2 * 0.002 * x * y + -0.003 * (r2 + 2 * x * x)
    yd = y * radial + 0.002 * (r2 + 2 * y * y) + 2 * -0.003 * x * y
    np.testing.assert_allclose(distort_points(np.array([x, y]), lens), [xd, yd], rtol=1e-15)
    np.testing.assert_allclose(undistort_points(np.array([xd, yd]), lens), [x, y], atol=1e-12)


def test_rational_and_fisheye_models_match_their_formulas_by_hand():
    """The rational radial factor at r^2 = 0.13; the fisheye's angle: a point 45 degrees off
    the axis (r = 1, theta = pi / 4) lands at r_d = theta (1 + k1 theta^2 + ... + k4 theta^8),
    and on the axis the lens bends nothing."""
    lens = Distortion(0.1, 0.01, 0.0, 0.0, 0.004, 0.05, -0.002, 0.001)
    r2 = 0.13
    radial = (1 + 0.1 * r2 + 0.01 * r2**2 + 0.004 * r2**3) / (
        1 + 0.05 * r2 - 0.002 * r2**2 + 0.001 * r2**3
    )
    np.testing.assert_allclose(
        distort_points(np.array([0.3, -0.2]), lens), [0.3 * radial, -0.2 * radial], rtol=1e-15
    )
    fisheye = Distortion(k1=0.05, k2=-0.01, k3=0.002, k4=-0.0003, model="fisheye")
    t = np.pi / 4
    r_d = t * (1 + 0.05 * t**2 - 0.01 * t**4 + 0.002 * t**6 - 0.0003 * t**8)
    np.testing.assert_allclose(
        distort_points(np.array([0.6, 0.8]), fisheye), [0.6 * r_d, 0.8 * r_d]
    )
    np.testing.assert_allclose(distort_points(np.zeros(2), fisheye), [0.0, 0.0], atol=0)
    assert not Distortion(model="fisheye").is_zero and Distortion().is_zero


@pytest.mark.parametrize("lens", LENSES[2:], ids=["opencv", "rational", "fisheye", "equidistant"])
def test_lens_jacobian_matches_finite_differences(lens):
    """The Jacobian Newton's inverse uses, against central differences of the forward map,
    near the axis too (where the fisheye's theta_d / r is 0 / 0 and its series takes over)."""
    from mosiv_framework.capture.lens import _jacobian

    rng = np.random.default_rng(3)
    xy = np.concatenate([rng.uniform(-0.8, 0.8, (200, 2)), [[1e-5, -2e-5], [3e-3, 1e-3]]])
    a, b, c, e = _jacobian(xy[:, 0], xy[:, 1], lens)
    h = 1e-6
    dx = (distort_points(xy + [h, 0], lens) - distort_points(xy - [h, 0], lens)) / (2 * h)
    dy = (distort_points(xy + [0, h], lens) - distort_points(xy - [0, h], lens)) / (2 * h)
    for got, want in ((a, dx[:, 0]), (b, dy[:, 0]), (c, dx[:, 1]), (e, dy[:, 1])):
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-8)


def test_fisheye_radial_factor_on_both_sides_of_the_axis_series():
    """Just below the threshold the series 1 + (k1 - 1/3) r^2 serves, just above the closed
    form theta_d / r: both agree with the Taylor expansion to its next order, r^4 (theta =
    r - r^3/3 + r^5/5, so theta_d / r = 1 + (k1 - 1/3) r^2 + (1/5 - k1 + k2) r^4 + ...)."""
    from mosiv_framework.capture.lens import FISHEYE_SERIES_R2, _radial

    lens = Distortion(k1=0.3, k2=-0.2, model="fisheye")
    second, fourth = lens.k1 - 1 / 3, 1 / 5 - lens.k1 + lens.k2
    for r2 in (0.5 * FISHEYE_SERIES_R2, 2.0 * FISHEYE_SERIES_R2, 1e-4):
        radial, dradial = _radial(np.array([r2]), lens)
        assert (radial[0] - 1.0) / r2 == pytest.approx(second + fourth * r2, rel=1e-6, abs=1e-7)
        assert dradial[0] == pytest.approx(second + 2 * fourth * r2, rel=1e-4)


def test_a_wide_fisheye_inverts_up_to_its_fold_and_not_beyond():
    """An equidistant fisheye maps the angle theta to r_d = theta: points up to 85 degrees off
    the axis come back (r = tan theta), and a recorded radius past 90 degrees has no pinhole
    ray: NaN, without warnings."""
    lens = Distortion(model="fisheye")
    theta = np.radians([10.0, 45.0, 70.0, 85.0])
    back = undistort_points(np.stack([theta, np.zeros(4)], -1), lens)
    np.testing.assert_allclose(back[:, 0], np.tan(theta), rtol=1e-9)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        beyond = undistort_points(np.array([[np.radians(100.0), 0.0]]), lens)
    assert np.isnan(beyond).all()


def test_lens_text_and_invalid_lenses_are_named():
    assert Distortion.parse("fisheye:0.1,-0.02") == Distortion(k1=0.1, k2=-0.02, model="fisheye")
    assert Distortion.parse("-0.1,0.02") == Distortion(-0.1, 0.02)
    for text in ("fisheye:", "fisheye:1,2,3,4,5", "0.1"):
        with pytest.raises(ValueError, match="fisheye:k1"):
            Distortion.parse(text)
    with pytest.raises(ValueError, match="a fisheye lens has only k1, k2, k3, k4; got {'p1'"):
        Distortion(p1=0.01, model="fisheye")
    with pytest.raises(ValueError, match="lens model 'kannala'"):
        Distortion(model="kannala")


def test_fisheye_capture_writes_an_opencv_fisheye_model(tmp_path):
    """``--distortion fisheye:...`` picks COLMAP's OPENCV_FISHEYE unless told otherwise, and a
    model that cannot hold the lens is refused before anything is written."""
    from mosiv_framework.capture.write import write_capture

    scene_dir = write_example_scene(tmp_path / "scene", n_frames=3, size=32, n_cameras=2)
    out = tmp_path / "capture"
    assert main(["data", "capture", str(scene_dir), str(out), "--distortion=fisheye:0.05"]) == 0
    lines = [ln for ln in (out / "sparse/0/cameras.txt").read_text().splitlines() if ln[:1] != "#"]
    assert all(ln.split()[1] == "OPENCV_FISHEYE" for ln in lines) and len(lines) == 2
    meta = json.loads((out / "capture.json").read_text())
    assert meta["distortion"]["model"] == "fisheye" and meta["distortion"]["k1"] == 0.05
    refused = "--camera-model OPENCV with --distortion: .*cannot hold a fisheye lens; use OPENCV_F"
    with pytest.raises(ConfigError, match=refused):
        write_capture(
            scene_dir,
            tmp_path / "refused",
            distortion=Distortion(k1=0.05, model="fisheye"),
            camera_model="OPENCV",
        )
    assert not (tmp_path / "refused").exists()


def test_yuv444p_keeps_the_colour_that_yuv420p_halves(tmp_path):
    """A red-green pattern one pixel fine: 4:2:0 averages its colour over 2 x 2 pixels, 4:4:4
    keeps it, both losslessly quantised (crf 0)."""
    from mosiv_framework.capture.write import encode_h264, write_capture

    rows, cols = np.indices((16, 16))
    frame = np.zeros((16, 16, 3), dtype=np.uint8)
    red = (rows + cols) % 2 == 0
    frame[red, 0], frame[~red, 1] = 200, 200
    errors = {}
    for fmt in ("yuv420p", "yuv444p"):
        path = tmp_path / f"{fmt}.mp4"
        encode_h264([frame, frame], path, fps=24.0, crf=0, pixel_format=fmt)
        _, frames = _decode(path)
        errors[fmt] = np.abs(frames[0].astype(float) - frame).mean()
    assert errors["yuv444p"] < 3.0 < 20.0 < errors["yuv420p"], errors
    with pytest.raises(ConfigError, match="--pixel-format 'yuv422'"):
        write_capture(tmp_path / "none", tmp_path / "out", pixel_format="yuv422")
