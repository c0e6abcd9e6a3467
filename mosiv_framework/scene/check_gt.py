"""Rules of the ground truth in gt/ (docs/SCENE_FORMAT.md): points.npz, params.json and
effects.json, and ``read_points``, the only way the framework opens points.npz.

points.npz is read member by member with ``zipfile`` and numpy's ``.npy`` header reader: an
array whose dtype holds Python objects is a pickle, and pickles can run code, so it is refused
from its header and never loaded. Declared sizes are checked against the stored bytes before any
data is read, so a truncated or lying file is a problem, not a crash or a huge allocation.
"""

from __future__ import annotations

import math
import zipfile
from collections.abc import Callable
from pathlib import Path

import numpy as np

from mosiv_framework.scene.check_common import (
    Fields,
    Meta,
    Report,
    finite,
    is_number,
    kind_reason,
    load_json,
    path_kind,
    shown,
)

POINTS = "gt/points.npz"
PARAMS = "gt/params.json"
EFFECTS = "gt/effects.json"
#: parameter names of gt/params.json (a generator's own names go under "generator_params")
# and the physically admissible range of each (open bounds unless the text says otherwise)
GT_PARAM_RANGES: dict[str, tuple[str, Callable[[float], bool]]] = {
    "E": ("> 0 Pa", lambda v: v > 0),
    "nu": ("in (-1, 0.5)", lambda v: -1.0 < v < 0.5),
    "rho": ("> 0 kg/m^3", lambda v: v > 0),
    "yield_stress": (">= 0 Pa", lambda v: v >= 0),
    "friction_angle": ("in [0, 90) degrees", lambda v: 0 <= v < 90),
    "viscosity": (">= 0 Pa s", lambda v: v >= 0),
    "bulk_modulus": ("> 0 Pa", lambda v: v > 0),
    "friction": (">= 0", lambda v: v >= 0),
}
GT_PARAM_NAMES = tuple(GT_PARAM_RANGES)


def check_gt(root: Path, report: Report, meta: Meta, *, required: bool | None = None) -> None:
    """Check gt/. ``required``: True reports a missing gt/ (the caller needs ground truth),
    None checks gt/ only when present, False skips it."""
    if required is False:
        return
    kind = path_kind(root / "gt")
    if kind == "missing":
        if required:
            report.add(
                "gt", "missing folder; this command needs ground truth (points.npz, params.json)"
            )
        return
    if kind != "folder":
        report.add("gt", kind_reason(kind, "the ground-truth folder"))
        return
    read_points(root, report, meta)
    params = load_json(root, PARAMS, report)
    if params is not None:
        check_gt_params(report, params, meta)
    effects = load_json(root, EFFECTS, report, required=False)
    if effects is not None:
        check_gt_effects(report, effects)


# ---------------------------------------------------------------------------------- points
def _header(fh, rel: str, key: str, size: int, report: Report) -> tuple | None:
    """(shape, fortran_order, dtype) of one .npy member, or None (reported) if it is refused."""
    version = np.lib.format.read_magic(fh)
    if version == (1, 0):
        shape, fortran, dtype = np.lib.format.read_array_header_1_0(fh)
    else:
        shape, fortran, dtype = np.lib.format.read_array_header_2_0(fh)
    if dtype.hasobject:
        report.add(
            rel,
            f"{key}: dtype {dtype} holds Python objects (a pickle); refused, never loaded "
            "(pickles can run code); store float32 [T, N, 3] arrays",
        )
        return None
    needed = fh.tell() + math.prod(shape) * dtype.itemsize
    if size < needed:
        report.add(rel, f"{key}: truncated ({size} bytes stored, its header needs {needed})")
        return None
    return shape, fortran, dtype


def _read_members(path: Path, rel: str, report: Report) -> tuple[dict[str, np.ndarray], set]:
    """The arrays that could be read, and the keys of every .npy member (read or not)."""
    arrays: dict[str, np.ndarray] = {}
    keys: set[str] = set()
    try:
        archive = zipfile.ZipFile(path)
    except (zipfile.BadZipFile, OSError, ValueError, EOFError) as exc:
        report.add(rel, f"cannot be read as .npz (not a valid zip archive: {exc})")
        return arrays, keys
    with archive:
        for info in archive.infolist():
            key = info.filename.removesuffix(".npy")
            if key == info.filename or info.is_dir():
                report.add(rel, f"member {info.filename!r} is not a .npy array")
                continue
            keys.add(key)
            try:
                with archive.open(info) as fh:
                    if _header(fh, rel, key, info.file_size, report) is None:
                        continue
                with archive.open(info) as fh:
                    arr = np.lib.format.read_array(fh, allow_pickle=False)
                # read from a stream the array is a read-only view of the bytes; torch and
                # callers that edit positions need a writable one
                arrays[key] = arr if arr.flags.writeable else arr.copy()
            except Exception as exc:  # zip, zlib or header corruption: a property of the file
                report.add(rel, f"{key}: cannot be read ({type(exc).__name__}: {exc})")
    return arrays, keys


def read_points(root: Path, report: Report, meta: Meta) -> dict[str, np.ndarray]:
    """Read and check gt/points.npz: one ``obj_<k>`` per object of scene.json, each float32
    [T, N, 3] with N >= 1, T = n_frames and every value finite. Returns the arrays read
    (also the faulty ones; the problems say what is wrong)."""
    kind = path_kind(root / POINTS)
    if kind != "file":
        reason = kind_reason(kind, "a .npz file")
        if kind == "missing":
            reason += " (gt/ exists, so it must hold points.npz)"
        report.add(POINTS, reason)
        return {}
    arrays, keys = _read_members(root / POINTS, POINTS, report)
    if meta.object_ids is not None:
        expected = {f"obj_{k}" for k in meta.object_ids}
        for key in sorted(expected - keys):
            report.add(POINTS, f"{key}: missing (one array per object of scene.json)")
        for key in sorted(keys - expected):
            report.add(
                POINTS, f"{key}: not an object of scene.json (expected keys {sorted(expected)})"
            )
    lengths = {key: arr.shape[0] for key, arr in arrays.items() if arr.ndim == 3}
    for key, arr in sorted(arrays.items()):
        if arr.dtype != np.float32:
            report.add(POINTS, f"{key}: dtype {arr.dtype}, expected float32")
        if arr.ndim != 3 or arr.shape[2] != 3 or arr.shape[1] < 1:
            report.add(POINTS, f"{key}: shape {list(arr.shape)}, expected [T, N, 3] with N >= 1")
        elif meta.n_frames is not None and arr.shape[0] != meta.n_frames:
            report.add(
                POINTS,
                f"{key}: {arr.shape[0]} frames, scene.json has n_frames = {meta.n_frames} "
                "(every object needs a position for every frame)",
            )
        elif meta.n_frames is None and len(set(lengths.values())) > 1:
            report.add(POINTS, f"{key}: {arr.shape[0]} frames; the arrays disagree: {lengths}")
        if np.issubdtype(arr.dtype, np.number) and not np.all(np.isfinite(arr)):
            report.add(
                POINTS, f"{key}: contains {int(np.sum(~np.isfinite(arr)))} non-finite numbers"
            )
    return arrays


# ---------------------------------------------------------------------------- params.json
def check_gt_params(report: Report, data: dict, meta: Meta) -> None:
    """gt/params.json: one entry per object of scene.json with its id, material (matching
    scene.json) and ``params``, a name -> number map of known names in their ranges."""
    generator = data.get("generator", "")
    if not isinstance(generator, str):
        report.add(
            PARAMS, f"generator: must be a string naming the generator, got {shown(generator)}"
        )
    objects = data.get("objects")
    if not isinstance(objects, list):
        report.add(PARAMS, f"objects: must be a list, got {shown(objects)}")
        return
    seen: set[int] = set()
    for i, obj in enumerate(objects):
        if not isinstance(obj, dict):
            report.add(PARAMS, f"objects[{i}]: must be a JSON object, got {shown(obj)}")
            continue
        of = Fields(report, PARAMS, obj, f"objects[{i}].")
        oid = of.integer("id", minimum=1)
        material = of.string("material")
        if oid is not None:
            if oid in seen:
                of.bad("id", f"duplicate entry for object {oid}")
            seen.add(oid)
            if meta.object_ids is not None and oid not in meta.object_ids:
                of.bad("id", f"{oid} is not an object of scene.json")
            declared = meta.materials.get(oid)
            if material is not None and declared is not None and material != declared:
                of.bad("material", f"is {material!r} but scene.json says {declared!r}")
        _check_param_values(of, obj.get("params"))
        of.vec3("initial_velocity", required=False)
    if meta.object_ids is not None:
        for k in sorted(meta.object_ids - seen):
            report.add(PARAMS, f"objects: no entry for object {k} of scene.json")


def _check_param_values(of: Fields, params) -> None:
    if not isinstance(params, dict):
        of.bad("params", f"must be a JSON object of name -> number, got {shown(params)}")
        return
    for name, value in params.items():
        if name not in GT_PARAM_NAMES:
            of.bad(
                f"params.{name}",
                f"unknown parameter name; valid: {', '.join(GT_PARAM_NAMES)} "
                "(a generator's own names go under generator_params)",
            )
        elif not is_number(value):
            of.bad(f"params.{name}", f"must be a number, got {shown(value)}")
        elif finite(value) and not GT_PARAM_RANGES[name][1](value):
            of.bad(f"params.{name}", f"{value!r} is not {GT_PARAM_RANGES[name][0]}")


def check_gt_effects(report: Report, data: dict) -> None:
    """gt/effects.json: a list of effects, each with a ``kind`` and a ``params`` object."""
    effects = data.get("effects")
    if not isinstance(effects, list):
        report.add(EFFECTS, f"effects: must be a list, got {shown(effects)}")
        return
    for i, effect in enumerate(effects):
        if not isinstance(effect, dict):
            report.add(EFFECTS, f"effects[{i}]: must be a JSON object, got {shown(effect)}")
            continue
        ef = Fields(report, EFFECTS, effect, f"effects[{i}].")
        ef.string("kind")
        ef.sub("params")
