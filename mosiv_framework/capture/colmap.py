"""COLMAP sparse models: cameras read from cameras.txt / images.txt (or cameras.bin /
images.bin), and written as text.

COLMAP stores world-to-camera poses in the OpenCV convention (quaternion qw qx qy qz and
translation t: x_cam = R x_world + t) and pixel coordinates with pixel centres at integer + 0.5,
as ``mosiv-scene/1`` does, so poses and intrinsics carry over unchanged.

Text files (https://colmap.github.io/format.html): ``cameras.txt`` ``CAMERA_ID MODEL WIDTH
HEIGHT PARAMS[]``; ``images.txt`` two lines per image, ``IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID
NAME`` and a line of 2-D points; ``points3D.txt``. The writer puts cameras in a rig's units and
up axis (``align.RigFrame``) and leaves the points empty.
"""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np

from mosiv_framework.capture.align import RigFrame
from mosiv_framework.capture.common import (
    CaptureError,
    SourceCamera,
    camera_key,
    no_frames_message,
)
from mosiv_framework.capture.lens import Distortion, Intrinsics
from mosiv_framework.capture.rotations import quaternion_to_rotation, rigid, rotation_to_quaternion
from mosiv_framework.errors import OutputError

#: supported camera models: name -> (binary model id, parameter names)
MODELS: dict[str, tuple[int, tuple[str, ...]]] = {
    "SIMPLE_PINHOLE": (0, ("f", "cx", "cy")),
    "PINHOLE": (1, ("fx", "fy", "cx", "cy")),
    "SIMPLE_RADIAL": (2, ("f", "cx", "cy", "k1")),
    "RADIAL": (3, ("f", "cx", "cy", "k1", "k2")),
    "OPENCV": (4, ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2")),
}
#: every model COLMAP knows (binary id -> (name, number of parameters)), to name unsupported ones
ALL_MODEL_IDS: dict[int, tuple[str, int]] = {
    0: ("SIMPLE_PINHOLE", 3), 1: ("PINHOLE", 4), 2: ("SIMPLE_RADIAL", 4), 3: ("RADIAL", 5),
    4: ("OPENCV", 8), 5: ("OPENCV_FISHEYE", 8), 6: ("FULL_OPENCV", 12), 7: ("FOV", 5),
    8: ("SIMPLE_RADIAL_FISHEYE", 4), 9: ("RADIAL_FISHEYE", 5), 10: ("THIN_PRISM_FISHEYE", 12),
    11: ("RAD_TAN_THIN_PRISM_FISHEYE", 16),
}  # fmt: skip
#: models the writer can write (both hold the lens; RADIAL needs fx = fy and no p1, p2)
WRITE_MODELS = ("OPENCV", "RADIAL")


def _intrinsics(model: str, width: int, height: int, params, where: str):
    """(Intrinsics, Distortion) of one COLMAP camera; CaptureError for an unsupported model."""
    if model not in MODELS:
        raise CaptureError(
            f"{where}: camera model {model!r} is not supported; supported models: "
            f"{', '.join(MODELS)} (undistort the images to PINHOLE with COLMAP otherwise)"
        )
    names = MODELS[model][1]
    if len(params) != len(names):
        raise CaptureError(
            f"{where}: model {model} takes {len(names)} parameters ({' '.join(names)}), "
            f"got {len(params)}"
        )
    p = dict(zip(names, (float(v) for v in params)))
    fx, fy = (p["f"], p["f"]) if "f" in p else (p["fx"], p["fy"])
    k = Intrinsics(int(width), int(height), fx, fy, p["cx"], p["cy"])
    return k, Distortion.from_mapping(p)


def _text_lines(path: Path) -> list[str]:
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise OutputError(f"{path}: cannot be read ({exc})") from exc
    return [line.strip() for line in text.splitlines() if not line.lstrip().startswith("#")]


def _read_cameras_txt(path: Path) -> dict[int, tuple[Intrinsics, Distortion, str]]:
    cams = {}
    for n, line in enumerate(_text_lines(path), start=1):
        if not line:
            continue
        tok = line.split()
        where = f"{path}: camera line {n} ({' '.join(tok[:2])})"
        try:
            cam_id, model, width, height = int(tok[0]), tok[1], int(tok[2]), int(tok[3])
        except (IndexError, ValueError) as exc:
            raise CaptureError(f"{where}: expected CAMERA_ID MODEL WIDTH HEIGHT PARAMS...") from exc
        try:
            params = [float(v) for v in tok[4:]]
        except ValueError as exc:
            raise CaptureError(f"{where}: parameters must be numbers ({exc})") from exc
        cams[cam_id] = (*_intrinsics(model, width, height, params, where), model)
    return cams


def _read_images_txt(path: Path) -> list[tuple[str, int, np.ndarray, str]]:
    """(image name, camera id, world_to_camera, where) of every image of images.txt."""
    lines = _text_lines(path)
    while lines and not lines[0]:  # blank lines before the first image carry no points
        lines.pop(0)
    images = []
    for i in range(0, len(lines), 2):  # each image: a pose line, then a line of 2-D points
        tok = lines[i].split()
        if not tok:
            continue
        where = f"{path}: image line {i + 1}"
        if len(tok) < 10:
            raise CaptureError(
                f"{where}: expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME, got {lines[i]!r}"
            )
        try:
            q, t = np.array(tok[1:5], float), np.array(tok[5:8], float)
            cam_id = int(tok[8])
        except ValueError as exc:
            raise CaptureError(f"{where}: QW..TZ must be numbers, CAMERA_ID an integer") from exc
        name = " ".join(tok[9:])
        images.append((name, cam_id, rigid(quaternion_to_rotation(q), t), f"{where} ({name})"))
    return images


def _unpack(fh, fmt: str, path: Path):
    size = struct.calcsize(fmt)
    data = fh.read(size)
    if len(data) != size:
        raise CaptureError(f"{path}: ends early (truncated binary model)")
    return struct.unpack(fmt, data)


def _read_cameras_bin(path: Path) -> dict[int, tuple[Intrinsics, Distortion, str]]:
    cams = {}
    with open(path, "rb") as fh:
        (count,) = _unpack(fh, "<Q", path)
        for _ in range(count):
            cam_id, model_id, width, height = _unpack(fh, "<iiQQ", path)
            where = f"{path}: camera {cam_id}"
            if model_id not in ALL_MODEL_IDS:
                raise CaptureError(
                    f"{where}: unknown camera model id {model_id}; supported models: "
                    f"{', '.join(MODELS)}"
                )
            model, n_params = ALL_MODEL_IDS[model_id]
            params = _unpack(fh, f"<{n_params}d", path)
            cams[cam_id] = (*_intrinsics(model, width, height, params, where), model)
    return cams


def _read_images_bin(path: Path) -> list[tuple[str, int, np.ndarray, str]]:
    images = []
    with open(path, "rb") as fh:
        (count,) = _unpack(fh, "<Q", path)
        for _ in range(count):
            image_id, *qt, cam_id = _unpack(fh, "<i7di", path)
            name = b""
            while (ch := fh.read(1)) not in (b"\x00", b""):
                name += ch
            (n_points,) = _unpack(fh, "<Q", path)
            fh.seek(24 * n_points, 1)  # x, y (double) and point3D id (int64) per 2-D point
            pose = rigid(quaternion_to_rotation(np.array(qt[:4])), np.array(qt[4:]))
            text = name.decode("utf-8", "replace")
            images.append((text, cam_id, pose, f"{path}: image {image_id} ({text})"))
    return images


def read_colmap(model_dir: str | Path, known: set[str]) -> list[SourceCamera]:
    """The cameras of a COLMAP sparse model folder, one per camera id in ``known`` (the videos'
    names; see ``common.camera_key``). A camera filmed by several images (one per frame) takes
    the pose of its first image by name: the rig is assumed static."""
    root = Path(model_dir)
    if (root / "cameras.txt").is_file() and (root / "images.txt").is_file():
        cams, images = (
            _read_cameras_txt(root / "cameras.txt"),
            _read_images_txt(root / "images.txt"),
        )
    elif (root / "cameras.bin").is_file() and (root / "images.bin").is_file():
        cams, images = (
            _read_cameras_bin(root / "cameras.bin"),
            _read_images_bin(root / "images.bin"),
        )
    else:
        raise CaptureError(
            f"{root}: not a COLMAP sparse model; expected cameras.txt and images.txt "
            "(or cameras.bin and images.bin)"
        )
    out: dict[str, SourceCamera] = {}
    for name, cam_id, pose, where in sorted(images):
        key = camera_key(name, known)
        if key is None:
            raise CaptureError(no_frames_message(where, name))
        if key in out:
            continue
        if cam_id not in cams:
            raise CaptureError(f"{where}: CAMERA_ID {cam_id} is not in the model's cameras")
        k, dist, model = cams[cam_id]
        out[key] = SourceCamera(key, k, dist, pose, where, model=model)
    return list(out.values())


# ---------------------------------------------------------------------------------- writing
def camera_line(camera_id: int, camera, d: Distortion, model: str, size: tuple[int, int]) -> str:
    """One line of cameras.txt for a ``scene.cameras.Camera`` recorded at ``size`` (w, h);
    ValueError when ``model`` cannot describe the camera and lens."""
    if d.k3 != 0.0:
        raise ValueError(f"camera {camera.id!r}: k3 = {d.k3} fits neither OPENCV nor RADIAL")
    if model == "OPENCV":
        params = [camera.fx, camera.fy, camera.cx, camera.cy, d.k1, d.k2, d.p1, d.p2]
    elif model == "RADIAL":
        if abs(camera.fx - camera.fy) > 1e-9 * abs(camera.fx) or not d.radial_only:
            raise ValueError(
                f"camera {camera.id!r}: COLMAP's RADIAL model needs fx = fy and no tangential "
                f"terms (fx={camera.fx}, fy={camera.fy}, p1={d.p1}, p2={d.p2}); use OPENCV"
            )
        params = [camera.fx, camera.cx, camera.cy, d.k1, d.k2]
    else:
        raise ValueError(f"camera model {model!r}: choose one of {WRITE_MODELS}")
    return f"{camera_id} {model} {size[0]} {size[1]} " + " ".join(repr(float(p)) for p in params)


def write_colmap_text(
    folder: Path,
    cameras: list,
    *,
    names: list[str],
    sizes: list[tuple[int, int]] | None = None,
    distortion: Distortion | None = None,
    model: str = "OPENCV",
    rig: RigFrame | None = None,
) -> Path:
    """cameras.txt, images.txt and an empty points3D.txt for the scene ``cameras`` into
    ``folder``, poses in the ``rig``'s world (default metres, z up).

    Camera i (1-based ids in file order) is image i named ``names[i]``, recorded at
    ``sizes[i]`` = (width, height) (default: the camera's own size)."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    rig, distortion = rig or RigFrame(), distortion or Distortion()
    sizes = sizes or [(c.width, c.height) for c in cameras]
    cam_lines = ["# Camera list with one line of data per camera:"]
    cam_lines.append("#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]")
    img_lines = ["# Image list with two lines of data per image:"]
    img_lines.append("#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME")
    img_lines.append("#   POINTS2D[] as (X, Y, POINT3D_ID)")
    for i, (camera, name, size) in enumerate(zip(cameras, names, sizes), start=1):
        cam_lines.append(camera_line(i, camera, distortion, model, size))
        w2c = rig.world_to_camera(np.asarray(camera.world_to_camera, dtype=np.float64))
        q = rotation_to_quaternion(w2c[:3, :3])
        numbers = " ".join(repr(float(v)) for v in (*q, *w2c[:3, 3]))
        img_lines += [f"{i} {numbers} {i} {name}", ""]
    (folder / "cameras.txt").write_text("\n".join(cam_lines) + "\n")
    (folder / "images.txt").write_text("\n".join(img_lines) + "\n")
    (folder / "points3D.txt").write_text(
        "# 3D point list with one line of data per point: none (cameras only)\n"
    )
    return folder
