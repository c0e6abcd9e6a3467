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
