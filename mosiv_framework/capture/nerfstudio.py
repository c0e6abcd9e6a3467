"""Cameras from a nerfstudio ``transforms.json``.

Poses are camera-to-world matrices in the OpenGL convention (x right, y up, z backwards), 4x4
or 3x4 (the last row [0, 0, 0, 1] implied); intrinsics ``fl_x``, ``fl_y``, ``cx``, ``cy``,
``w``, ``h`` and distortion ``k1``, ``k2``, ``k3``, ``p1``, ``p2`` are given once at the top
level or per frame (per-frame values win). Written the instant-ngp / Blender way, the focal
length comes from the field of view ``camera_angle_x`` (and ``camera_angle_y``), and a missing
principal point is the image centre. ``fl_y`` defaults to ``fl_x`` (a single focal length, as
COLMAP's SIMPLE_* models write it).

A capture rig's cameras do not move, so the frames of one camera must agree on its pose and
lens up to registration noise (``common.one_pose_per_camera``); frames that disagree are
refused rather than one of them silently kept.
``applied_transform`` and ``applied_scale`` (nerfstudio's record of how it moved COLMAP's
world into the file's) are not undone: the poses are read in the file's own world, in which
``--up`` and ``--ground`` are then given.
"""

from __future__ import annotations

import json
import logging
import math
from pathlib import Path

import numpy as np

from mosiv_framework.capture.common import (
    CaptureError,
    SourceCamera,
    camera_key,
    natural_key,
    no_frames_message,
    one_pose_per_camera,
)
from mosiv_framework.capture.lens import Distortion, Intrinsics
from mosiv_framework.errors import OutputError
from mosiv_framework.scene.cameras import rigidity_problems

log = logging.getLogger(__name__)

#: OpenGL camera axes -> OpenCV camera axes (flip y and z)
GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])
#: camera models nerfstudio reads as a perspective camera with fl_x, fl_y, cx, cy and k1-k3,
#: p1, p2 (the SIMPLE_* and RADIAL models are OPENCV with some coefficients zero), and its
#: fisheye camera (k1-k4 on the angle from the axis: lens.Distortion "fisheye")
SUPPORTED = ("OPENCV", "PINHOLE", "SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV_FISHEYE")
#: distortion coefficients MOSIV's perspective lens takes from a transforms.json
COEFFICIENTS = ("k1", "k2", "k3", "p1", "p2")
#: those of a fisheye camera (nerfstudio's OPENCV_FISHEYE)
FISHEYE_COEFFICIENTS = ("k1", "k2", "k3", "k4")


def _number(value, key: str, where: str) -> float:
    try:
        number = float(value)
    except (TypeError, ValueError) as exc:
        raise CaptureError(f"{where}: {key!r} must be a number, got {value!r}") from exc
    if not math.isfinite(number):
        raise CaptureError(f"{where}: {key!r} must be a finite number, got {value!r}")
    return number


def _field(frame: dict, top: dict, key: str, where: str, *, required: bool = True):
    value = frame.get(key, top.get(key))
    if value is None:
        if required:
            raise CaptureError(f"{where}: lacks {key!r} (per frame or at the top level)")
        return None
    return _number(value, key, where)


def _size(frame: dict, top: dict, key: str, where: str) -> int:
    value = _field(frame, top, key, where)
    if value != int(value) or value <= 0:
        raise CaptureError(f"{where}: {key!r} must be a positive whole number of pixels")
    return int(value)


def _focal(frame: dict, top: dict, axis: str, size: int, where: str) -> float | None:
    """``fl_<axis>``, else from the field of view ``camera_angle_<axis>`` (radians)."""
    focal = _field(frame, top, f"fl_{axis}", where, required=False)
    if focal is not None:
        return focal
    angle = _field(frame, top, f"camera_angle_{axis}", where, required=False)
    if angle is None:
        return None
    if not 0.0 < angle < math.pi:
        raise CaptureError(f"{where}: 'camera_angle_{axis}' must lie in (0, pi) radians")
    return 0.5 * size / math.tan(0.5 * angle)


def _intrinsics(frame: dict, top: dict, where: str) -> Intrinsics:
    w, h = _size(frame, top, "w", where), _size(frame, top, "h", where)
    fx = _focal(frame, top, "x", w, where)
    if fx is None:
        raise CaptureError(
            f"{where}: lacks 'fl_x' (or the field of view 'camera_angle_x'), per frame or at "
            "the top level"
        )
    fy = _focal(frame, top, "y", h, where)
    cx = _field(frame, top, "cx", where, required=False)
    cy = _field(frame, top, "cy", where, required=False)
    return Intrinsics(
        w, h, fx, fx if fy is None else fy, w / 2 if cx is None else cx, h / 2 if cy is None else cy
    )


def _distortion(frame: dict, top: dict, where: str, model: str) -> Distortion:
    if model == "OPENCV_FISHEYE":
        tangential = [c for c in ("p1", "p2") if _field(frame, top, c, where, required=False)]
        if tangential:  # nerfstudio's fisheye has none either: say what is not used
            log.warning("%s: %s of a fisheye camera are not used", where, ", ".join(tangential))
        values = {c: _field(frame, top, c, where, required=False) for c in FISHEYE_COEFFICIENTS}
        return Distortion.from_mapping({c: v or 0.0 for c, v in values.items()}, model="fisheye")
    k4 = _field(frame, top, "k4", where, required=False)
    if k4:
        raise CaptureError(
            f"{where}: 'k4' = {k4:g} (the r^8 radial term) is not part of MOSIV's perspective "
            f"lens ({', '.join(COEFFICIENTS)}): for a fisheye lens set camera_model "
            "OPENCV_FISHEYE; else undistort the images first, or refit without k4"
        )
    values = {c: _field(frame, top, c, where, required=False) for c in COEFFICIENTS}
    return Distortion.from_mapping({c: v or 0.0 for c, v in values.items()})


def _pose(frame: dict, where: str) -> np.ndarray:
    """The frame's world-to-camera matrix (OpenCV axes) from its GL camera-to-world."""
    try:
        c2w = np.asarray(frame["transform_matrix"], dtype=np.float64)
    except (KeyError, TypeError, ValueError) as exc:
        raise CaptureError(f"{where}.transform_matrix: missing or not a 4x4 matrix") from exc
    if c2w.shape == (3, 4):  # the last row of a rigid transform, left out
        c2w = np.vstack([c2w, [0.0, 0.0, 0.0, 1.0]])
    problems = rigidity_problems(c2w, atol=1e-3)
    if problems:
        raise CaptureError(f"{where}.transform_matrix: {problems[0]}")
    return np.linalg.inv(c2w @ GL_TO_CV)


def _camera(frame: dict, top: dict, key: str, where: str) -> SourceCamera:
    model = str(frame.get("camera_model", top.get("camera_model", "OPENCV")))
    if model not in SUPPORTED:
        raise CaptureError(
            f"{where}: camera_model {model!r} is not supported; supported: {', '.join(SUPPORTED)}"
        )
    k, dist, w2c = (
        _intrinsics(frame, top, where),
        _distortion(frame, top, where, model),
        _pose(frame, where),
    )
    return SourceCamera(key, k, dist, w2c, f"{where}.transform_matrix", model=model)


def _note_world_changes(top: dict, path: Path) -> None:
    moved = [k for k in ("applied_transform", "applied_scale", "orientation_override") if k in top]
    if moved:
        log.info(
            "%s: %s recorded there are not undone; the poses are read in the file's own world, "
            "in which --up and --ground are given",
            path,
            ", ".join(moved),
        )


def read_nerfstudio(path: str | Path, known: set[str]) -> list[SourceCamera]:
    """The cameras of ``transforms.json``, one per camera id in ``known`` (videos' names; a
    frame's ``file_path`` names its camera as in ``common.camera_key``). Several frames of one
    camera must agree on its pose and lens (static rig); the first by file path is kept."""
    path = Path(path)
    try:
        top = json.loads(path.read_text(encoding="utf-8"))
    except OSError as exc:
        raise OutputError(f"{path}: cannot be read ({exc})") from exc
    except ValueError as exc:
        raise CaptureError(f"{path}: not valid JSON ({exc})") from exc
    frames = top.get("frames") if isinstance(top, dict) else None
    if not isinstance(frames, list) or not frames:
        raise CaptureError(f"{path}: 'frames' must be a non-empty list of camera frames")
    bad = [i for i, f in enumerate(frames) if not isinstance(f, dict)]
    if bad:
        raise CaptureError(f"{path}: frames[{bad[0]}] must be an object with 'file_path' and more")
    _note_world_changes(top, path)
    views: dict[str, list[SourceCamera]] = {}
    order = sorted(
        range(len(frames)), key=lambda i: natural_key(str(frames[i].get("file_path", "")))
    )
    for i in order:
        frame = frames[i]
        where = f"{path}: frames[{i}]"
        name = str(frame.get("file_path", ""))
        if not name:
            raise CaptureError(f"{where}: lacks 'file_path'")
        key = camera_key(name, known)
        if key is None:
            raise CaptureError(no_frames_message(f"{where} ({name})", name))
        views.setdefault(key, []).append(_camera(frame, top, key, where))
    return one_pose_per_camera(views)
