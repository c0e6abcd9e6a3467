"""Cameras from a nerfstudio ``transforms.json``.

Poses are camera-to-world matrices in the OpenGL convention (x right, y up, z backwards);
intrinsics ``fl_x``, ``fl_y``, ``cx``, ``cy``, ``w``, ``h`` and distortion ``k1``, ``k2``,
``k3``, ``p1``, ``p2`` are given once at the top level or per frame (per-frame values win).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from mosiv_framework.capture.common import (
    CaptureError,
    SourceCamera,
    camera_key,
    no_frames_message,
)
from mosiv_framework.capture.lens import Distortion, Intrinsics
from mosiv_framework.errors import OutputError
from mosiv_framework.scene.cameras import rigidity_problems

#: OpenGL camera axes -> OpenCV camera axes (flip y and z)
GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])
SUPPORTED = ("OPENCV", "PINHOLE")


def _field(frame: dict, top: dict, key: str, where: str, *, required: bool = True):
    value = frame.get(key, top.get(key))
    if value is None:
        if required:
            raise CaptureError(f"{where}: lacks {key!r} (per frame or at the top level)")
        return 0.0
    try:
        return float(value)
    except (TypeError, ValueError) as exc:
        raise CaptureError(f"{where}: {key!r} must be a number, got {value!r}") from exc


def _camera(frame: dict, top: dict, key: str, where: str) -> SourceCamera:
    model = str(frame.get("camera_model", top.get("camera_model", "OPENCV")))
    if model not in SUPPORTED:
        raise CaptureError(
            f"{where}: camera_model {model!r} is not supported; supported: {', '.join(SUPPORTED)}"
        )
    k = Intrinsics(
        int(_field(frame, top, "w", where)),
        int(_field(frame, top, "h", where)),
        _field(frame, top, "fl_x", where),
        _field(frame, top, "fl_y", where),
        _field(frame, top, "cx", where),
        _field(frame, top, "cy", where),
    )
    dist = Distortion.from_mapping(
        {c: _field(frame, top, c, where, required=False) for c in ("k1", "k2", "k3", "p1", "p2")}
    )
    try:
        c2w = np.asarray(frame["transform_matrix"], dtype=np.float64)
    except (KeyError, TypeError, ValueError) as exc:
        raise CaptureError(f"{where}.transform_matrix: missing or not a 4x4 matrix") from exc
    problems = rigidity_problems(c2w, atol=1e-3)
    if problems:
        raise CaptureError(f"{where}.transform_matrix: {problems[0]}")
    w2c = np.linalg.inv(c2w @ GL_TO_CV)
    return SourceCamera(key, k, dist, w2c, f"{where}.transform_matrix", model=model)


def read_nerfstudio(path: str | Path, known: set[str]) -> list[SourceCamera]:
    """The cameras of ``transforms.json``, one per camera id in ``known`` (videos' names; a
    frame's ``file_path`` names its camera as in ``common.camera_key``). Several frames of one
    camera: the first by file path is used (static rig)."""
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
    out: dict[str, SourceCamera] = {}
    order = sorted(range(len(frames)), key=lambda i: str(frames[i].get("file_path", "")))
    for i in order:
        frame = frames[i]
        where = f"{path}: frames[{i}]"
        name = str(frame.get("file_path", ""))
        if not name:
            raise CaptureError(f"{where}: lacks 'file_path'")
        key = camera_key(name, known)
        if key is None:
            raise CaptureError(no_frames_message(f"{where} ({name})", name))
        if key not in out:
            out[key] = _camera(frame, top, key, where)
    return list(out.values())
