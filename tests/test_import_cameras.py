"""Camera files written by hand the ways capture tools write them: nerfstudio / instant-ngp
``transforms.json`` variants and COLMAP text models, read as ``mosiv data import`` reads them,
and the errors that name the file and the entry when they cannot be used."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from mosiv_framework.capture.colmap import read_colmap
from mosiv_framework.capture.common import CaptureError
from mosiv_framework.capture.nerfstudio import read_nerfstudio

KNOWN = {"cam01", "cam02"}
W, H = 64, 48


def gl_pose(angle_deg: float = 0.0, centre=(0.0, -2.0, 0.5)) -> np.ndarray:
    """A camera-to-world matrix (OpenGL axes) turned ``angle_deg`` about the world z axis."""
    a = math.radians(angle_deg)
    c2w = np.eye(4)
    c2w[:3, :3] = [[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]]
    c2w[:3, 3] = centre
    return c2w


def write_transforms(tmp_path, frames: list[dict], **top) -> object:
    path = tmp_path / "transforms.json"
    path.write_text(json.dumps({**top, "frames": frames}))
    return path


def frame(name: str, c2w: np.ndarray, **fields) -> dict:
    return {"file_path": name, "transform_matrix": c2w.tolist(), **fields}


# ------------------------------------------------------------------------------ nerfstudio
def test_field_of_view_three_by_four_pose_and_simple_radial_model(tmp_path):
    """instant-ngp's camera_angle_x without fl_x or a principal point, a 3x4 matrix and a
    SIMPLE_RADIAL camera read as the focal length the angle gives, the image centre and the
    same pose as the 4x4 matrix."""
    angle = 0.9
    full, short = gl_pose(10.0), gl_pose(10.0)[:3]
    frames = [frame("images/cam01.png", full), frame("images/cam02.png", short)]
    path = write_transforms(
        tmp_path, frames, camera_angle_x=angle, w=W, h=H, camera_model="SIMPLE_RADIAL", k1=0.02
    )
    cams = {c.id: c for c in read_nerfstudio(path, KNOWN)}
    k = cams["cam02"].intrinsics
    assert k.fx == pytest.approx(0.5 * W / math.tan(0.5 * angle), rel=1e-12) and k.fy == k.fx
    assert (k.cx, k.cy, k.width, k.height) == (W / 2, H / 2, W, H)
    assert cams["cam02"].distortion.k1 == 0.02
    assert np.allclose(cams["cam01"].world_to_camera, cams["cam02"].world_to_camera, atol=1e-12)


@pytest.mark.parametrize(
    ("fields", "message"),
    [
        ({"k4": 0.05}, "'k4' = 0.05"),
        ({"w": 64.5}, "'w' must be a positive whole number"),
        ({"camera_model": "EQUIRECTANGULAR"}, "camera_model 'EQUIRECTANGULAR' is not supported"),
        ({"fl_x": None}, "lacks 'fl_x' (or the field of view 'camera_angle_x')"),
        ({"camera_angle_x": 4.0, "fl_x": None}, "'camera_angle_x' must lie in (0, pi)"),
    ],
)
def test_lens_fields_mosiv_cannot_use_are_named(tmp_path, fields, message):
    top = {"w": W, "h": H, "fl_x": 50.0, "fl_y": 50.0, "cx": 32.0, "cy": 24.0, **fields}
    top = {k: v for k, v in top.items() if v is not None}
    path = write_transforms(tmp_path, [frame("images/cam01.png", gl_pose())], **top)
    with pytest.raises(CaptureError, match="frames\\[0\\]") as caught:
        read_nerfstudio(path, {"cam01"})
    assert message in str(caught.value)


def test_nerfstudio_fisheye_camera_reads_as_a_fisheye_lens(tmp_path):
    """ns-process-data's fisheye cameras: camera_model OPENCV_FISHEYE with k1-k4 on the angle;
    a frame of the same camera with another lens model is refused as other intrinsics."""
    lens = {"w": W, "h": H, "fl_x": 40.0, "fl_y": 41.0, "cx": 32.0, "cy": 24.0}
    fish = {"camera_model": "OPENCV_FISHEYE", "k1": 0.02, "k2": -0.004, "k3": 1e-3, "k4": -2e-4}
    path = write_transforms(tmp_path, [frame("images/cam01.png", gl_pose())], **lens, **fish)
    (cam,) = read_nerfstudio(path, {"cam01"})
    assert cam.model == "OPENCV_FISHEYE" and cam.distortion.model == "fisheye"
    assert cam.distortion.coefficients[:6] == (0.02, -0.004, 0.0, 0.0, 1e-3, -2e-4)
    # all coefficients zero in both: only the model tells an equidistant fisheye from a pinhole
    frames = [
        frame("cam01/f_1.png", gl_pose(), camera_model="OPENCV_FISHEYE"),
        frame("cam01/f_2.png", gl_pose(), camera_model="OPENCV"),
    ]
    path = write_transforms(tmp_path, frames, **lens)
    with pytest.raises(CaptureError, match="other intrinsics or distortion"):
        read_nerfstudio(path, {"cam01"})


def test_frames_of_one_camera_agree_up_to_noise_or_are_refused(tmp_path):
    """A static rig registered frame by frame: tiny differences keep the first frame; a camera
    that turns, moves or changes focal length between its frames is refused, naming both."""
    lens = {"w": W, "h": H, "fl_x": 50.0, "fl_y": 50.0, "cx": 32.0, "cy": 24.0}
    other = frame("images/cam02.png", gl_pose(90.0, centre=(2.0, 0.0, 0.5)))
    noisy = gl_pose(0.01)
    frames = [frame("cam01/f_0001.png", gl_pose()), frame("cam01/f_0002.png", noisy), other]
    cams = {c.id: c for c in read_nerfstudio(write_transforms(tmp_path, frames, **lens), KNOWN)}
    assert "frames[0]" in cams["cam01"].origin  # the first by file path
    for moved, what in (
        (frame("cam01/f_0002.png", gl_pose(5.0)), "turned 5 deg"),
        (frame("cam01/f_0002.png", gl_pose(0.0, centre=(0.0, -2.0, 0.7))), "moved 0.2"),
        (frame("cam01/f_0002.png", gl_pose(), fl_x=55.0), "other intrinsics"),
    ):
        path = write_transforms(tmp_path, [frames[0], moved, other], **lens)
        with pytest.raises(CaptureError, match="frames\\[1\\]") as caught:
            read_nerfstudio(path, KNOWN)
        assert what in str(caught.value) and "frames[0]" in str(caught.value)


def test_a_frame_that_is_not_an_object_is_named(tmp_path):
    path = write_transforms(tmp_path, [["images/cam01.png"]], w=W, h=H)
    with pytest.raises(CaptureError, match=r"frames\[0\] must be an object"):
        read_nerfstudio(path, {"cam01"})


# ---------------------------------------------------------------------------------- COLMAP
def write_colmap_text(folder, cameras: list[str], images: list[str]) -> object:
    """A text model: ``cameras`` lines, ``images`` as (image line, points line) pairs."""
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "cameras.txt").write_text("# Camera list\n" + "\n".join(cameras) + "\n")
    (folder / "images.txt").write_text("# Image list\n# two lines each\n" + "".join(images))
    (folder / "points3D.txt").write_text("# 3D point list\n")
    return folder


CAMERA = "1 PINHOLE 64 48 50 50 32 24"


def image(image_id: int, name: str, q=(1.0, 0.0, 0.0, 0.0), t=(0.0, 0.0, 2.0), cam=1) -> str:
    """An image line (QW QX QY QZ TX TY TZ) and an empty points line."""
    values = " ".join(f"{v:.9g}" for v in (*q, *t))
    return f"{image_id} {values} {cam} {name}\n\n"


def test_colmap_parameter_count_and_missing_camera_are_named_by_line(tmp_path):
    few = write_colmap_text(tmp_path / "few", ["1 PINHOLE 64 48 50 50 32"], [image(1, "cam01.png")])
    with pytest.raises(CaptureError, match=r"cameras.txt: line 2: PINHOLE takes 4 parameters"):
        read_colmap(few, {"cam01"})
    lost = write_colmap_text(tmp_path / "lost", [CAMERA], [image(1, "cam01.png", cam=7)])
    with pytest.raises(CaptureError, match=r"images.txt: line 3: image 1 \(cam01.png\) names "):
        read_colmap(lost, {"cam01"})


@pytest.mark.parametrize(
    ("line", "lens"),
    [
        ("1 FULL_OPENCV 64 48 50 51 32 24 -0.2 0.05 0.001 -0.002 0.01 0.1 -0.02 0.003",
         {"model": "opencv", "k1": -0.2, "k2": 0.05, "p1": 0.001, "p2": -0.002, "k3": 0.01,
          "k4": 0.1, "k5": -0.02, "k6": 0.003}),
        ("1 OPENCV_FISHEYE 64 48 50 51 32 24 0.04 -0.01 0.002 -0.0003",
         {"model": "fisheye", "k1": 0.04, "k2": -0.01, "k3": 0.002, "k4": -0.0003}),
        ("1 RADIAL_FISHEYE 64 48 50 32 24 0.04 -0.01",
         {"model": "fisheye", "k1": 0.04, "k2": -0.01}),
        ("1 SIMPLE_RADIAL_FISHEYE 64 48 50 32 24 0.04", {"model": "fisheye", "k1": 0.04}),
    ],
    ids=["full_opencv", "opencv_fisheye", "radial_fisheye", "simple_radial_fisheye"],
)  # fmt: skip
def test_colmap_rational_and_fisheye_models_read_in_colmaps_parameter_order(tmp_path, line, lens):
    (cam,) = read_colmap(write_colmap_text(tmp_path, [line], [image(1, "cam01.png")]), {"cam01"})
    want = {"k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0, "k3": 0.0, "k4": 0.0, "k5": 0.0}
    want |= {"k6": 0.0, **lens}
    got = cam.distortion.as_dict()
    assert got.pop("model") == want.pop("model")
    assert got == pytest.approx(want, abs=1e-12)
    assert cam.intrinsics.fx == 50.0 and cam.intrinsics.cx == 32.0


def test_colmap_quaternion_of_rounded_length_is_normalised_and_a_wrong_one_refused(tmp_path):
    rounded = (0.7071, 0.7071, 0.0, 0.0)  # length 0.99999: a pose written with few digits
    folder = write_colmap_text(tmp_path / "ok", [CAMERA], [image(1, "cam01.png", q=rounded)])
    (cam,) = read_colmap(folder, {"cam01"})
    expected = [[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]]  # +90 deg about x
    assert np.allclose(cam.rotation, expected, atol=1e-12)
    assert np.allclose(cam.rotation @ cam.rotation.T, np.eye(3), atol=1e-12)
    bad = write_colmap_text(tmp_path / "bad", [CAMERA], [image(1, "cam01.png", q=(1, 2, 2, 0))])
    with pytest.raises(CaptureError, match=r"image 1 \(cam01.png\): its rotation quaternion"):
        read_colmap(bad, {"cam01"})


def test_colmap_images_of_one_camera_in_frame_order_agree_or_are_refused(tmp_path):
    """frame_9 comes before frame_10 and gives the pose; a later frame moved by noise is
    accepted, one moved by a tenth of the distance between cameras is refused."""
    second = image(3, "cam02/frame_1.png", t=(1.0, 0.0, 2.0))
    lines = [image(1, "cam01/frame_10.png", t=(0.0, 0.0, 2.00001)), second]
    lines.insert(0, image(2, "cam01/frame_9.png"))
    cams = {c.id: c for c in read_colmap(write_colmap_text(tmp_path / "a", [CAMERA], lines), KNOWN)}
    assert "frame_9" in cams["cam01"].origin
    lines[1] = image(1, "cam01/frame_10.png", t=(0.0, 0.1, 2.0))
    with pytest.raises(CaptureError, match=r"image 1 \(cam01/frame_10.png\): camera 'cam01'"):
        read_colmap(write_colmap_text(tmp_path / "b", [CAMERA], lines), KNOWN)


# ------------------------------------------------------------------------------ frame order
def test_image_folder_frames_numbered_without_leading_zeros_keep_their_order(tmp_path):
    """1.png ... 12.png (as tools that number frames without padding write them) are read in
    time order, not 1, 10, 11, 12, 2, ...: each frame's grey level is its number."""
    import imageio.v3 as iio

    from mosiv_framework.capture.video import read_image_folder

    for n in range(1, 13):
        iio.imwrite(tmp_path / f"{n}.png", np.full((4, 6, 3), 10 * n, dtype=np.uint8))
    frames = read_image_folder(tmp_path)
    assert [int(f[0, 0, 0]) for f in frames] == [10 * n for n in range(1, 13)]


def test_image_folders_as_cameras_and_other_computers_leave_them(tmp_path):
    """Hidden files (macOS's ._ copies, .DS_Store) are not frames; a JPEG turned by its EXIF
    orientation is read as a viewer shows it; CMYK and grey + alpha frames become RGB; a
    folder mixing kinds of image is refused."""
    from PIL import Image

    from mosiv_framework.capture.video import read_image_folder

    turned = tmp_path / "turned"
    turned.mkdir()
    for n in range(2):
        image = Image.new("RGB", (6, 4), (200, 20, 20))
        exif = image.getexif()
        exif[0x0112] = 6  # orientation: rotate 90 deg clockwise to view
        image.save(turned / f"{n}.jpg", exif=exif, quality=95)
    (turned / "._0.jpg").write_bytes(b"\x00\x05\x16\x07 AppleDouble")
    (turned / ".DS_Store").write_bytes(b"\x00\x00\x00\x01Bud1")
    frames = read_image_folder(turned)
    assert frames.shape == (2, 6, 4, 3)  # the viewer's 4 x 6, not the stored 6 x 4
    assert abs(int(frames[0, 3, 2, 0]) - 200) < 8
    modes = tmp_path / "modes"
    modes.mkdir()
    Image.new("CMYK", (6, 4), (0, 0, 0, 0)).save(modes / "0.jpg", quality=95)  # white
    Image.new("CMYK", (6, 4), (0, 0, 0, 255)).save(modes / "1.jpg", quality=95)  # black
    frames = read_image_folder(modes)
    assert frames[0].min() > 240 and frames[1].max() < 15
    grey = tmp_path / "grey"
    grey.mkdir()
    Image.new("LA", (6, 4), (90, 128)).save(grey / "0.png")
    assert read_image_folder(grey).shape == (1, 4, 6, 3)
    Image.new("RGB", (6, 4)).save(grey / "0.jpg")
    with pytest.raises(CaptureError, match=r"several kinds \(.jpg, .png\)"):
        read_image_folder(grey)


def test_a_video_that_changes_rate_is_resampled_at_its_median_interval(tmp_path):
    """Ten frames, each a brighter grey, shown at 0, 1, 2, 3, 4, 10, 12, 14, 16, 18 / 30 s (a
    burst at 30 fps, a gap, then 15 fps): ffmpeg's constant-rate output would fill the clip at
    the container's rate; the import reads each frame once, then takes the frame nearest each
    instant of the median interval's grid (2 / 30 s): frames 0, 2, 4, 4, 5, 5, 6, 7, 8, 9."""
    import subprocess

    imageio_ffmpeg = pytest.importorskip("imageio_ffmpeg")
    from mosiv_framework.capture.video import read_video

    path = tmp_path / "vfr.mp4"
    grey_and_timing = "geq=lum='20+20*N':cb=128:cr=128,setpts='if(lt(N,5),N/30/TB,(N*2)/30/TB)'"
    command = [imageio_ffmpeg.get_ffmpeg_exe(), "-y", "-loglevel", "error", "-f", "lavfi"]
    command += ["-i", "color=size=32x24:rate=30", "-frames:v", "10", "-vf", grey_and_timing]
    subprocess.run([*command, "-fps_mode", "vfr", str(path)], check=True, timeout=60)
    frames, fps = read_video(path)
    assert len(frames) == 10 and fps == pytest.approx(15.0)
    steps = np.diff(frames.reshape(10, -1).mean(axis=1))
    repeated = np.abs(steps) < 3  # the same frame twice: 4, 4 and 5, 5
    assert repeated.tolist() == [False, False, True, False, True, False, False, False, False]
    assert np.all(steps[~repeated] > 15)  # otherwise in time order


def test_every_nth_frame_brought_down_as_it_is_read(tmp_path):
    """``every`` 3 and ``longest_side`` 16 on ten 32 x 24 frames: frames 0, 3, 6, 9 at 16 x 12,
    each still its own grey."""
    import subprocess

    imageio_ffmpeg = pytest.importorskip("imageio_ffmpeg")
    from mosiv_framework.capture.video import read_frames

    path = tmp_path / "grey.mp4"
    command = [imageio_ffmpeg.get_ffmpeg_exe(), "-y", "-loglevel", "error", "-f", "lavfi"]
    command += ["-i", "color=size=32x24:rate=30", "-frames:v", "10"]
    command += ["-vf", "geq=lum='20+20*N':cb=128:cr=128", str(path)]
    subprocess.run(command, check=True, timeout=60)
    frames, fps = read_frames(path, every=3, longest_side=16)
    assert frames.shape == (4, 12, 16, 3) and fps == pytest.approx(30.0)
    grey = frames.reshape(4, -1).mean(axis=1)
    full, _ = read_frames(path)
    np.testing.assert_allclose(grey, full.reshape(10, -1).mean(axis=1)[::3], atol=2.0)
    with pytest.raises(CaptureError, match="--every 0"):
        read_frames(path, every=0)


# ------------------------------------------------------------------- messages for mistakes
def test_mistakes_a_new_user_makes_are_named(tmp_path, caplog):
    """Both camera files given, too few frames kept, and a first frame that shows more
    objects than the materials name (warned: the smaller ones may be stray blobs)."""
    from mosiv_framework.capture import offsets as off
    from mosiv_framework.capture.importer import ImportSettings, load_cameras, read_objects
    from mosiv_framework.segment.track import first_frame_objects

    both = ImportSettings(
        out=tmp_path / "o", frames_dir=tmp_path, colmap=tmp_path, transforms=tmp_path / "t.json"
    )
    with pytest.raises(CaptureError, match="give only one of --colmap and --transforms"):
        load_cameras(both, {"cam01"})
    both.materials, both.objects_yaml = "elastic", tmp_path / "objects.yaml"
    with pytest.raises(CaptureError, match="give only one of --materials and --objects"):
        read_objects(both)
    videos = {"a": np.zeros((5, 2, 2, 3), np.uint8), "b": np.zeros((5, 2, 2, 3), np.uint8)}
    for step in (off.pad_late_cameras, off.apply_offsets):
        with pytest.raises(CaptureError, match="--frames 1: keep at least 2 frames"):
            step(videos, {"a": 0, "b": 0}, 1)
    centres = np.arange(30, dtype=float)[:, None] * np.ones(3)
    parts = [np.arange(0, 12), np.arange(12, 22), np.arange(22, 30)]
    with caplog.at_level("WARNING"):
        kept = first_frame_objects(parts, centres, 2)
    assert len(kept) == 2 and "shows 3 separate objects (12, 10, 8 voxels)" in caplog.text


def test_frame_rates_may_differ_by_less_than_half_a_frame_over_the_clip(tmp_path):
    from mosiv_framework.capture.video import common_fps

    rates = {"cam01": 29.97, "cam02": 30.0}
    assert common_fps(rates, None, tmp_path, 300) == pytest.approx(29.985)
    with pytest.raises(CaptureError, match="drift 0.6 frames apart"):
        common_fps(rates, None, tmp_path, 600)
    assert common_fps(rates, 30.0, tmp_path, 600) == 30.0  # --fps decides


def test_frames_are_checked_at_their_recorded_size_and_a_folder_of_hidden_files_named(tmp_path):
    """A 6 x 4 frame for a camera the model says is 8 x 6 is refused although both would be
    brought down to 6 x 4 (--resolution 6); a folder holding only hidden files has no frames."""
    from PIL import Image

    from mosiv_framework.capture.video import read_frames, read_image_folder

    folder = tmp_path / "cam01"
    folder.mkdir()
    for n in range(2):
        Image.new("RGB", (6, 4)).save(folder / f"{n}.png")
    expect = ((6, 8), "cameras.txt gives camera 'cam01'")
    with pytest.raises(CaptureError, match="frames are 6x4 pixels, but cameras.txt gives"):
        read_frames(folder, longest_side=16, expect=expect)
    assert read_frames(folder, longest_side=16, expect=((4, 6), "ok"))[0].shape == (2, 4, 6, 3)
    hidden = tmp_path / "hidden"
    hidden.mkdir()
    (hidden / "._0.png").write_bytes(b"\x00\x05\x16\x07")
    with pytest.raises(CaptureError, match="holds no image frames"):
        read_image_folder(hidden)
