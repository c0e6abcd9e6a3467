"""Rules of cameras.json (docs/SCENE_FORMAT.md): OpenCV pinhole cameras with rigid extrinsics."""

from __future__ import annotations

import re
from pathlib import Path

from mosiv_framework.scene.cameras import rigidity_problems
from mosiv_framework.scene.check_common import (
    ABSENT,
    Fields,
    Meta,
    Report,
    is_number,
    load_json,
    shown,
)

# camera ids become folder names, so they must be plain, portable names
CAMERA_ID = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.-]*$")


def check_cameras(root: Path, report: Report, meta: Meta) -> None:
    """Check cameras.json; record each valid camera id and its size in ``meta.cameras``."""
    data = load_json(root, "cameras.json", report)
    if data is None:
        return
    f = Fields(report, "cameras.json", data)
    convention = data.get("convention", ABSENT)
    if convention != "opencv":
        f.bad(
            "convention",
            "missing" if convention is ABSENT else f"is {shown(convention)}, expected 'opencv'",
        )
    cameras = data.get("cameras")
    if not isinstance(cameras, list) or not cameras:
        f.bad("cameras", f"must be a non-empty list, got {shown(cameras)}")
        return
    for i, cam in enumerate(cameras):
        if not isinstance(cam, dict):
            f.bad(f"cameras[{i}]", f"must be a JSON object, got {shown(cam)}")
            continue
        _check_camera(report, meta, i, cam)
    check_every_frame_recorded(report, meta)


def _check_camera(report: Report, meta: Meta, i: int, cam: dict) -> None:
    cid = cam.get("id")
    label = cid[:40] if isinstance(cid, str) else shown(cid, 40)
    cf = Fields(report, "cameras.json", cam, f"cameras[{i}] ({label}).")
    if not isinstance(cid, str) or not CAMERA_ID.match(cid):
        cf.bad(
            "id",
            f"must be a name of letters, digits, '_', '.' or '-' (it names a folder), "
            f"got {shown(cid)}",
        )
        cid = None
    elif cid in meta.cameras:
        cf.bad("id", f"duplicate camera id {cid!r}")
        cid = None
    width, height = cf.integer("width", minimum=1), cf.integer("height", minimum=1)
    cf.number("fx", positive=True)
    cf.number("fy", positive=True)
    cf.number("cx")
    cf.number("cy")
    matrix = cam.get("world_to_camera", ABSENT)
    if matrix is ABSENT:
        cf.bad("world_to_camera", "missing")
    elif not (
        isinstance(matrix, list)
        and len(matrix) == 4
        and all(isinstance(row, list) and len(row) == 4 for row in matrix)
        and all(is_number(x) for row in matrix for x in row)
    ):
        cf.bad("world_to_camera", f"must be 4 rows of 4 numbers, got {shown(matrix)}")
    else:
        for reason in rigidity_problems(matrix):
            cf.bad("world_to_camera", f"not a rigid transform: {reason}")
    if cid is not None:
        size_ok = width is not None and height is not None
        meta.cameras[cid] = (width, height) if size_ok else None
        span = _recorded_frames(cf, cam.get("frames", ABSENT), meta.n_frames)
        if span is not None:
            meta.camera_frames[cid] = span


def _recorded_frames(cf: Fields, span: object, n_frames: int | None) -> tuple[int, int] | None:
    """The optional ``frames`` field: [first, last] frames the camera recorded (a camera that
    started late or stopped early); None when absent (every frame) or invalid (reported)."""
    if span is ABSENT:
        return None
    if not (
        isinstance(span, list)
        and len(span) == 2
        and all(isinstance(x, int) and not isinstance(x, bool) for x in span)
    ):
        cf.bad("frames", f"must be [first, last], two frame numbers, got {shown(span)}")
        return None
    first, last = span
    limit = "" if n_frames is None else f" <= {n_frames - 1} (n_frames = {n_frames})"
    if not 0 <= first <= last or (n_frames is not None and last >= n_frames):
        cf.bad("frames", f"must satisfy 0 <= first <= last{limit}, got {span}")
        return None
    return first, last


def check_every_frame_recorded(report: Report, meta: Meta) -> None:
    """Every frame of the scene is recorded by at least one camera."""
    if meta.n_frames is None or not meta.camera_frames or not meta.cameras:
        return
    full = [c for c in meta.cameras if c not in meta.camera_frames]
    if full:
        return
    unseen = [
        t
        for t in range(meta.n_frames)
        if not any(a <= t <= b for a, b in meta.camera_frames.values())
    ]
    if unseen:
        report.add(
            "cameras.json",
            f"no camera records frame(s) {', '.join(map(str, unseen[:8]))}"
            f"{' ...' if len(unseen) > 8 else ''}: every frame needs at least one camera "
            "(see the cameras' frames fields)",
        )
