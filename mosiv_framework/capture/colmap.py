"""COLMAP sparse models, read and written through pycolmap.

COLMAP stores world-to-camera poses in the OpenCV convention (x_cam = R x_world + t) and pixel
coordinates with pixel centres at integer + 0.5, as ``mosiv-scene/1`` does, so poses and
intrinsics carry over unchanged. A model is a folder with ``cameras``, ``images`` and
``points3D``, all text (``.txt``) or all binary (``.bin``), with or without the ``rigs`` and
``frames`` files of COLMAP 3.12 and later (https://colmap.github.io/format.html). The writer
puts the cameras in a rig's units and up axis (``align.RigFrame``), one image per camera (each
its own trivial rig and frame), and no 3-D points.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pycolmap

from mosiv_framework.capture.align import RigFrame
from mosiv_framework.capture.common import (
    CaptureError,
    SourceCamera,
    camera_key,
    natural_key,
    no_frames_message,
    one_pose_per_camera,
)
from mosiv_framework.capture.lens import Distortion, Intrinsics
from mosiv_framework.capture.options import WRITE_MODELS

#: supported camera models -> their parameters in COLMAP's order, named as ``Distortion`` and
#: ``Intrinsics`` name them (``f``: fx = fy)
MODELS: dict[str, tuple[str, ...]] = {
    "SIMPLE_PINHOLE": ("f", "cx", "cy"),
    "PINHOLE": ("fx", "fy", "cx", "cy"),
    "SIMPLE_RADIAL": ("f", "cx", "cy", "k1"),
    "RADIAL": ("f", "cx", "cy", "k1", "k2"),
    "OPENCV": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2"),
    "FULL_OPENCV": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"),
    "SIMPLE_RADIAL_FISHEYE": ("f", "cx", "cy", "k1"),
    "RADIAL_FISHEYE": ("f", "cx", "cy", "k1", "k2"),
    "OPENCV_FISHEYE": ("fx", "fy", "cx", "cy", "k1", "k2", "k3", "k4"),
}
#: the models whose coefficients bend the angle from the axis (lens.Distortion "fisheye")
FISHEYE_MODELS = ("SIMPLE_RADIAL_FISHEYE", "RADIAL_FISHEYE", "OPENCV_FISHEYE")
#: the files of a model, each as .txt or .bin
MODEL_FILES = ("cameras", "images", "points3D")


def _supported() -> str:
    return f"supported models: {', '.join(MODELS)}"


# ---------------------------------------------------------------------------------- reading
def _model_extension(root: Path) -> str:
    """'.bin' or '.txt', binary first as COLMAP reads; CaptureError naming the missing files."""
    for ext in (".bin", ".txt"):
        if all((root / f"{name}{ext}").is_file() for name in MODEL_FILES):
            return ext
    if not root.is_dir():
        raise CaptureError(f"COLMAP model folder {str(root)!r} does not exist or is not a folder")
    ext = ".bin" if any((root / f"{n}.bin").is_file() for n in MODEL_FILES) else ".txt"
    missing = [f"{n}{ext}" for n in MODEL_FILES if not (root / f"{n}{ext}").is_file()]
    raise CaptureError(
        f"{root}: not a COLMAP sparse model: {', '.join(missing)} missing; a model holds "
        "cameras, images and points3D, all .txt or all .bin (points3D may list no points)"
    )


def _unknown_model_name(path: Path) -> str | None:
    """Where a cameras.txt names a model COLMAP does not know, and which, else None: pycolmap
    says only "Camera model does not exist", without the line or the name."""
    known = set(pycolmap.CameraModelId.__members__)
    lines = path.read_text(encoding="utf-8", errors="replace").splitlines()
    for n, line in enumerate(lines, start=1):
        tok = line.split()
        if tok and not tok[0].startswith("#") and len(tok) > 1 and tok[1] not in known:
            return f"{path}: line {n}: camera model {tok[1]!r} is unknown; {_supported()}"
    return None


def _data_lines(path: Path):
    """(line number, tokens) of a COLMAP text file's lines, comments and blank lines too."""
    lines = path.read_text(encoding="utf-8", errors="replace").splitlines()
    return [(n, line.split()) for n, line in enumerate(lines, start=1)]


def _camera_lines_problem(path: Path) -> tuple[str | None, set[int]]:
    """(a problem of cameras.txt: a parameter count its model does not take, or None; the
    camera ids it defines)."""
    ids: set[int] = set()
    for n, tok in _data_lines(path):
        if not tok or tok[0].startswith("#") or len(tok) < 4:
            continue
        model, params = tok[1], tok[4:]
        if model in MODELS and len(params) != len(MODELS[model]):
            return (
                f"{path}: line {n}: {model} takes {len(MODELS[model])} parameters "
                f"({', '.join(MODELS[model])}), got {len(params)}"
            ), ids
        if tok[0].isdigit():
            ids.add(int(tok[0]))
    return None, ids


def _image_camera_problem(path: Path, camera_ids: set[int], cameras: Path) -> str | None:
    """Where images.txt names a camera id that cameras.txt lacks (pycolmap calls it a missing
    "rig" and names no file). An image takes two lines; the second (its 2-D points) may be
    empty, so only the lines between images skip blanks and comments, as COLMAP reads."""
    lines, i = _data_lines(path), 0
    while i < len(lines):
        n, tok = lines[i]
        i += 1
        if not tok or tok[0].startswith("#"):
            continue
        i += 1  # the image's points line, whatever it holds
        if len(tok) >= 10 and tok[8].isdigit() and int(tok[8]) not in camera_ids:
            return (
                f"{path}: line {n}: image {tok[0]} ({' '.join(tok[9:])}) names camera_id "
                f"{tok[8]}, which {cameras} does not define"
            )
    return None


def _text_model_problem(root: Path) -> str | None:
    """A clear message for a text model pycolmap could not read, where one is found: an
    unknown model name, a wrong parameter count, an image of a camera that is not defined."""
    cameras = root / "cameras.txt"
    problem = _unknown_model_name(cameras)
    if problem:
        return problem
    problem, ids = _camera_lines_problem(cameras)
    return problem or _image_camera_problem(root / "images.txt", ids, cameras)


def _binary_size_problem(path: Path, records) -> str | None:
    """Where a binary model file's records, read by their own counts and sizes, do not end
    exactly at its end: a truncated or padded file, which pycolmap reads as garbage or fails
    on with an allocation error. ``records(data)`` yields each record's byte length."""
    data = path.read_bytes()
    if len(data) < 8:
        return f"{path}: {len(data)} bytes, shorter than its record count; the file is truncated"
    end = 8
    try:
        for length in records(data):
            end += length
            if end > len(data):
                break
    except ValueError:  # an unknown camera model id: pycolmap's reading names it
        return None
    if end == len(data):
        return None
    count = int.from_bytes(data[:8], "little")
    return (
        f"{path}: its {count} records take {end} bytes or more but the file has {len(data)}; "
        "the file is truncated or not a COLMAP binary model"
    )


def _camera_records(data: bytes):
    """Byte lengths of cameras.bin's records: id (uint32), model id (int32), width and height
    (uint64), then the model's parameters (float64)."""
    count, at = int.from_bytes(data[:8], "little"), 8
    for _ in range(count):
        if at + 8 > len(data):
            yield 24  # runs past the end
            return
        model = int.from_bytes(data[at + 4 : at + 8], "little", signed=True)
        n = len(
            pycolmap.Camera.create_from_model_id(1, pycolmap.CameraModelId(model), 1.0, 1, 1).params
        )
        yield 24 + 8 * n
        at += 24 + 8 * n


def _image_records(data: bytes):
    """Byte lengths of images.bin's records: id (uint32), rotation (4 float64), translation
    (3 float64), camera id (uint32), a NUL-terminated name, the number of 2-D points (uint64)
    and 24 bytes per point."""
    count, at = int.from_bytes(data[:8], "little"), 8
    for _ in range(count):
        name_end = data.find(b"\0", at + 64)
        if name_end < 0 or name_end + 9 > len(data):
            yield len(data) + 1 - at  # runs past the end
            return
        points = int.from_bytes(data[name_end + 1 : name_end + 9], "little")
        length = name_end + 9 - at + 24 * points
        yield length
        at += length


def _load(root: Path) -> tuple[pycolmap.Reconstruction, str]:
    """The model in ``root`` and the extension of its files; CaptureError when unreadable."""
    ext = _model_extension(root)
    if ext == ".bin":
        for name, records in (("cameras", _camera_records), ("images", _image_records)):
            problem = _binary_size_problem(root / f"{name}.bin", records)
            if problem:
                raise CaptureError(problem)
    rec = pycolmap.Reconstruction()
    try:
        (rec.read_binary if ext == ".bin" else rec.read_text)(str(root))
    except (ValueError, IndexError, KeyError, RuntimeError, MemoryError) as exc:
        unknown = _text_model_problem(root) if ext == ".txt" else None
        # pycolmap prefixes its failed checks with the C++ source line: of no use here
        reason = re.sub(r"^\[[^\]]*\]\s*", "", str(exc)).strip()
        if "camera model" in reason.lower():  # e.g. a model id of a newer COLMAP in a .bin
            reason += f"; {_supported()}"
        raise CaptureError(
            unknown or f"{root}: COLMAP cannot read this {ext} model: {reason}"
        ) from exc
    return rec, ext


def _intrinsics(camera: pycolmap.Camera, where: str) -> tuple[Intrinsics, Distortion]:
    """(Intrinsics, Distortion) of one COLMAP camera; CaptureError for an unsupported model or
    a focal length that is not positive (as a truncated binary model leaves it)."""
    model = camera.model.name
    if model not in MODELS:
        raise CaptureError(
            f"{where}: camera model {model!r} is not supported; {_supported()} "
            "(undistort the images to PINHOLE with COLMAP otherwise)"
        )
    p = dict(zip(MODELS[model], (float(v) for v in camera.params)))
    fx, fy = (p["f"], p["f"]) if "f" in p else (p["fx"], p["fy"])
    if not (fx > 0 and fy > 0 and camera.width > 0 and camera.height > 0):
        raise CaptureError(
            f"{where}: focal lengths and image size must be positive, got fx={fx}, fy={fy}, "
            f"{camera.width}x{camera.height} pixels"
        )
    k = Intrinsics(int(camera.width), int(camera.height), fx, fy, p["cx"], p["cy"])
    lens = "fisheye" if model in FISHEYE_MODELS else "opencv"
    return k, Distortion.from_mapping(p, model=lens)


def _pose(image, where: str) -> np.ndarray:
    """The image's 4x4 world-to-camera matrix; its quaternion must be of unit length (to
    rounding: one written with a few digits is normalised)."""
    quat = np.asarray(image.cam_from_world().rotation.quat, dtype=np.float64)
    norm = float(np.linalg.norm(quat))
    if not abs(norm - 1.0) <= 1e-3:
        raise CaptureError(
            f"{where}: its rotation quaternion (QW QX QY QZ) has length {norm:.6g}, not 1: not "
            "a rotation"
        )
    pose = np.eye(4)
    pose[:3, :3] = pycolmap.Rotation3d(quat / norm).matrix()
    pose[:3, 3] = np.asarray(image.cam_from_world().translation, dtype=np.float64)
    return pose


def read_colmap(model_dir: str | Path, known: set[str]) -> list[SourceCamera]:
    """The cameras of a COLMAP sparse model folder, one per camera id in ``known`` (the videos'
    names; see ``common.camera_key``). A camera filmed by several images (one per frame) takes
    the pose of its first registered image (by name, frame_9 before frame_10); the others that
    are registered must agree with it up to registration noise: the rig is static
    (``common.one_pose_per_camera``)."""
    root = Path(model_dir)
    rec, ext = _load(root)
    views: dict[str, list[SourceCamera]] = {}
    unposed: dict[str, str] = {}
    for image in sorted(rec.images.values(), key=lambda im: natural_key(im.name)):
        where = f"{root / ('images' + ext)}: image {image.image_id} ({image.name})"
        key = camera_key(image.name, known)
        if key is None:
            raise CaptureError(no_frames_message(where, image.name))
        if not image.has_pose:
            unposed.setdefault(key, where)
            continue
        camera = rec.cameras[image.camera_id]
        k, dist = _intrinsics(camera, f"{root / ('cameras' + ext)}: camera {image.camera_id}")
        source = SourceCamera(key, k, dist, _pose(image, where), where, model=camera.model.name)
        views.setdefault(key, []).append(source)
    for key, where in unposed.items():
        if key not in views:
            raise CaptureError(
                f"{where}: has no pose (its frame is not registered in the model), and no other "
                f"image of camera {key!r} has one"
            )
    return one_pose_per_camera(views)


# ---------------------------------------------------------------------------------- writing
def colmap_params(camera, d: Distortion, model: str) -> list[float]:
    """The parameters of a ``scene.cameras.Camera`` behind the lens ``d`` in COLMAP's ``model``;
    ValueError when ``model`` cannot describe the camera and lens."""
    if model not in WRITE_MODELS:
        raise ValueError(f"camera model {model!r}: choose one of {WRITE_MODELS}")
    fisheye_model = model in FISHEYE_MODELS
    if (d.model == "fisheye") != fisheye_model:
        fitting = "OPENCV_FISHEYE" if d.model == "fisheye" else "OPENCV, FULL_OPENCV or RADIAL"
        raise ValueError(
            f"camera {camera.id!r}: COLMAP's {model} cannot hold a {d.model} lens; use {fitting}"
        )
    pinhole = [camera.fx, camera.fy, camera.cx, camera.cy]
    if model == "OPENCV_FISHEYE":
        params = pinhole + [d.k1, d.k2, d.k3, d.k4]
    elif model == "FULL_OPENCV":
        params = pinhole + [d.k1, d.k2, d.p1, d.p2, d.k3, d.k4, d.k5, d.k6]
    elif model == "OPENCV":
        if not (d.polynomial and d.k3 == 0.0):
            raise ValueError(
                f"camera {camera.id!r}: k3..k6 = {d.k3}, {d.k4}, {d.k5}, {d.k6}: COLMAP's OPENCV "
                "model holds only k1, k2, p1, p2; use FULL_OPENCV"
            )
        params = pinhole + [d.k1, d.k2, d.p1, d.p2]
    else:  # RADIAL
        if abs(camera.fx - camera.fy) > 1e-9 * abs(camera.fx) or not d.radial_only:
            raise ValueError(
                f"camera {camera.id!r}: COLMAP's RADIAL model needs fx = fy and only k1, k2 "
                f"(fx={camera.fx}, fy={camera.fy}, lens {d.as_dict()}); use OPENCV or "
                "FULL_OPENCV"
            )
        params = [camera.fx, camera.cx, camera.cy, d.k1, d.k2]
    return [float(p) for p in params]


def write_colmap(
    folder: Path,
    cameras: list,
    *,
    names: list[str],
    sizes: list[tuple[int, int]] | None = None,
    distortion: Distortion | None = None,
    model: str = "OPENCV",
    rig: RigFrame | None = None,
    binary: bool = False,
) -> Path:
    """The scene ``cameras`` as a COLMAP model in ``folder`` (text, or binary with ``binary``),
    poses in the ``rig``'s world (default metres, z up); returns ``folder``.

    Camera i (1-based ids in list order) is image i named ``names[i]``, recorded at
    ``sizes[i]`` = (width, height) (default: the camera's own size). ValueError when ``model``
    cannot describe a camera and the lens."""
    rig, distortion = rig or RigFrame(), distortion or Distortion()
    sizes = sizes or [(c.width, c.height) for c in cameras]
    rec = pycolmap.Reconstruction()
    for i, (camera, name, size) in enumerate(zip(cameras, names, sizes), start=1):
        params = colmap_params(camera, distortion, model)
        rec.add_camera_with_trivial_rig(
            pycolmap.Camera(camera_id=i, model=model, width=size[0], height=size[1], params=params)
        )
        w2c = rig.world_to_camera(np.asarray(camera.world_to_camera, dtype=np.float64))
        image = pycolmap.Image(name=name, camera_id=i, image_id=i)
        rec.add_image_with_trivial_frame(image, pycolmap.Rigid3d(w2c[:3]))
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    (rec.write_binary if binary else rec.write_text)(str(folder))
    return folder
