"""Rules of scene.json (docs/SCENE_FORMAT.md): format, clip length, world box and objects."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from mosiv_framework.scene.check_common import (
    ABSENT,
    FORMAT,
    MATERIAL_FAMILIES,
    Fields,
    Meta,
    Report,
    load_json,
    shown,
)

# masks are 8-bit PNGs holding object ids, so ids above 255 cannot be drawn
MAX_OBJECTS = 255


def check_meta(root: Path, report: Report, meta: Meta) -> None:
    """Check scene.json; record what it validly declares in ``meta``."""
    data = load_json(root, "scene.json", report)
    if data is None:
        return
    f = Fields(report, "scene.json", data)
    fmt = data.get("format", ABSENT)
    if fmt != FORMAT:
        f.bad("format", "missing" if fmt is ABSENT else f"is {shown(fmt)}, expected {FORMAT!r}")
    f.string("name")
    f.number("fps", positive=True)
    n_frames = f.integer("n_frames", minimum=1)
    meta.n_frames = n_frames
    observed = f.integer("observed_frames", minimum=1)
    if n_frames is not None and observed is not None and observed > n_frames:
        f.bad("observed_frames", f"{observed} exceeds n_frames = {n_frames}")
    units = data.get("units", "m")
    if units != "m":
        f.bad("units", f"is {shown(units)}; mosiv-scene/1 scenes are in metres ('m')")
    up = f.vec3("up", required=False)
    if up is not None and not any(up):
        f.bad("up", "must be a non-zero vector")
    f.vec3("gravity")
    _check_domain(f)
    _check_objects(f, data.get("objects", ABSENT), meta)


def _check_domain(f: Fields) -> None:
    lower = upper = None
    domain = f.sub("domain")
    if domain is not None:
        lower, upper = domain.vec3("lower"), domain.vec3("upper")
        if lower is not None and upper is not None:
            for axis, lo, hi in zip("xyz", lower, upper, strict=True):
                if lo >= hi:
                    domain.bad("lower", f"{axis} = {lo} must be below upper {axis} = {hi}")
    if f.data.get("ground") is not None:  # absent or null both mean no ground
        ground = f.sub("ground")
        height = ground.number("height") if ground is not None else None
        if height is not None and lower is not None and upper is not None:
            if not lower[2] <= height < upper[2]:
                ground.bad(
                    "height", f"{height} lies outside the domain's z range [{lower[2]}, {upper[2]})"
                )


def _check_objects(f: Fields, objects: Any, meta: Meta) -> None:
    if objects is ABSENT:
        f.bad("objects", "missing")
        return
    if not isinstance(objects, list) or not objects:
        f.bad("objects", f"must be a non-empty list, got {shown(objects)}")
        return
    if len(objects) > MAX_OBJECTS:
        f.bad("objects", f"{len(objects)} objects; masks are 8-bit, so at most {MAX_OBJECTS}")
    ids: list[int] = []
    all_ok = True
    for i, obj in enumerate(objects):
        if not isinstance(obj, dict):
            f.bad(f"objects[{i}]", f"must be a JSON object, got {shown(obj)}")
            all_ok = False
            continue
        of = Fields(f.report, f.file, obj, f"objects[{i}].")
        oid = of.integer("id", minimum=1)
        name = of.string("name")
        material = of.string("material")
        if material is not None and material not in MATERIAL_FAMILIES:
            of.bad(
                "material",
                f"unknown material family {material!r}; valid: {', '.join(MATERIAL_FAMILIES)}",
            )
            material = None
        if oid is None:
            all_ok = False
            continue
        ids.append(oid)
        if material is not None:
            meta.materials[oid] = material
        if name is not None:
            meta.names[oid] = name
    counts: dict[int, int] = {}
    for k in ids:
        counts[k] = counts.get(k, 0) + 1
    duplicates = sorted(k for k, n in counts.items() if n > 1)
    if duplicates:
        f.bad("objects", f"duplicate object id(s) {duplicates}; ids must be unique")
    if all_ok and not duplicates and sorted(ids) != list(range(1, len(ids) + 1)):
        f.bad("objects", f"ids are {sorted(ids)}; they must be exactly 1..K = 1..{len(ids)}")
    meta.object_ids = set(ids)
