"""The rules of ``mosiv-scene/1`` (SCENE_FORMAT.md) and the checker behind ``mosiv data check``.

``check_scene`` collects every problem of a scene folder, each naming the file (relative to the
scene) and the reason, and never stops at the first one. ``check_layout`` is the cheap part
(JSON files and which frame files exist, no image decoding) that ``read_scene`` runs on every
load. ``run_check`` is what the CLI calls.
"""

from __future__ import annotations

import json
import math
import re
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from mosiv_framework.scene.cameras import rigidity_problems

if TYPE_CHECKING:
    from mosiv_framework.scene.io import Scene

FORMAT = "mosiv-scene/1"
MATERIAL_FAMILIES = ("elastic", "plasticine", "sand", "newtonian", "non_newtonian", "snow")
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
# camera ids become folder names, so they must be plain, portable names
_CAMERA_ID = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.-]*$")
_FRAME_FILE = re.compile(r"^(\d{4,})\.png$")
_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def frame_name(frame: int) -> str:
    """File name of one frame: ``0003.png``."""
    return f"{frame:04d}.png"


@dataclass(frozen=True)
class Problem:
    """One thing wrong with a scene: the file (relative to the scene folder) and why."""

    file: str
    reason: str

    def __str__(self) -> str:
        return f"{self.file}: {self.reason}"


@dataclass
class _Meta:
    """What the JSON files validly declare; None/empty where they are broken."""

    n_frames: int | None = None
    object_ids: set[int] | None = None
    materials: dict[int, str] = field(default_factory=dict)
    # camera id -> (width, height), or None where the size fields are invalid
    cameras: dict[str, tuple[int, int] | None] = field(default_factory=dict)


class _Report:
    def __init__(self) -> None:
        self.problems: list[Problem] = []

    def add(self, file: str, reason: str) -> None:
        self.problems.append(Problem(file, reason))


# --------------------------------------------------------------------------- JSON helpers
def _is_number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _non_finite(obj: Any, where: str) -> list[str]:
    """Dotted paths of every NaN/inf number inside a parsed JSON value."""
    if isinstance(obj, float) and not math.isfinite(obj):
        return [f"{where or 'value'} = {obj}"]
    if isinstance(obj, dict):
        return [p for k, v in obj.items() for p in _non_finite(v, f"{where}.{k}" if where else k)]
    if isinstance(obj, list):
        return [p for i, v in enumerate(obj) for p in _non_finite(v, f"{where}[{i}]")]
    return []


def _load_json(root: Path, rel: str, report: _Report, *, required: bool = True) -> Any:
    """Parse ``root/rel``; report a missing file, bad JSON and every non-finite number."""
    path = root / rel
    if not path.is_file():
        if required:
            report.add(rel, "missing")
        return None
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        report.add(rel, f"is not valid JSON ({exc})")
        return None
    for where in _non_finite(data, ""):
        report.add(rel, f"non-finite number: {where}; every number must be finite")
    if not isinstance(data, dict):
        report.add(rel, f"top level must be a JSON object, got {type(data).__name__}")
        return None
    return data


_ABSENT = object()  # marks a missing key, distinct from a JSON null


class _Fields:
    """Typed access to one JSON object, reporting bad or missing fields against a file."""

    def __init__(self, report: _Report, file: str, data: dict, prefix: str = "") -> None:
        self.report, self.file, self.data, self.prefix = report, file, data, prefix

    def bad(self, key: str, reason: str) -> None:
        self.report.add(self.file, f"{self.prefix}{key}: {reason}")

    def _get(self, key: str, required: bool) -> Any:
        """The value, or _ABSENT when the key is missing (reported if required). A JSON null
        is returned as None and then rejected by the type check like any wrong type."""
        if key not in self.data:
            if required:
                self.bad(key, "missing")
            return _ABSENT
        return self.data[key]

    def number(self, key: str, *, positive: bool = False, required: bool = True) -> float | None:
        v = self._get(key, required)
        if v is _ABSENT:
            return None
        if not _is_number(v):
            self.bad(key, f"must be a number, got {v!r}")
            return None
        if not math.isfinite(v):
            return None  # already reported as non-finite
        if positive and v <= 0:
            self.bad(key, f"must be positive, got {v!r}")
            return None
        return float(v)

    def integer(self, key: str, *, minimum: int | None = None) -> int | None:
        v = self._get(key, True)
        if v is _ABSENT:
            return None
        if not (isinstance(v, int) and not isinstance(v, bool)):
            self.bad(key, f"must be an integer, got {v!r}")
            return None
        if minimum is not None and v < minimum:
            self.bad(key, f"must be at least {minimum}, got {v}")
            return None
        return v

    def string(self, key: str) -> str | None:
        v = self._get(key, True)
        if v is _ABSENT:
            return None
        if not isinstance(v, str) or not v:
            self.bad(key, f"must be a non-empty string, got {v!r}")
            return None
        return v

    def vec3(self, key: str, *, required: bool = True) -> tuple[float, float, float] | None:
        v = self._get(key, required)
        if v is _ABSENT:
            return None
        if not (isinstance(v, list) and len(v) == 3 and all(_is_number(x) for x in v)):
            self.bad(key, f"must be a list of 3 numbers, got {v!r}")
            return None
        if not all(math.isfinite(x) for x in v):
            return None
        return (float(v[0]), float(v[1]), float(v[2]))

    def sub(self, key: str, *, required: bool = True) -> _Fields | None:
        v = self._get(key, required)
        if v is _ABSENT:
            return None
        if not isinstance(v, dict):
            self.bad(key, f"must be a JSON object, got {v!r}")
            return None
        return _Fields(self.report, self.file, v, f"{self.prefix}{key}.")


# ------------------------------------------------------------------------ scene.json rules
def _check_scene_json(root: Path, report: _Report, meta: _Meta) -> None:
    data = _load_json(root, "scene.json", report)
    if data is None:
        return
    f = _Fields(report, "scene.json", data)
    fmt = data.get("format", _ABSENT)
    if fmt != FORMAT:
        f.bad("format", "missing" if fmt is _ABSENT else f"is {fmt!r}, expected {FORMAT!r}")
    f.string("name")
    f.number("fps", positive=True)
    n_frames = f.integer("n_frames", minimum=1)
    meta.n_frames = n_frames
    observed = f.integer("observed_frames", minimum=1)
    if n_frames is not None and observed is not None and observed > n_frames:
        f.bad("observed_frames", f"{observed} exceeds n_frames = {n_frames}")
    units = data.get("units", "m")
    if units != "m":
        f.bad("units", f"is {units!r}; mosiv-scene/1 scenes are in metres ('m')")
    up = f.vec3("up", required=False)
    if up is not None and not any(up):
        f.bad("up", "must be a non-zero vector")
    f.vec3("gravity")
    lower = upper = None
    domain = f.sub("domain")
    if domain is not None:
        lower, upper = domain.vec3("lower"), domain.vec3("upper")
        if lower is not None and upper is not None:
            for axis, lo, hi in zip("xyz", lower, upper, strict=True):
                if lo >= hi:
                    domain.bad("lower", f"{axis} = {lo} must be below upper {axis} = {hi}")
    if data.get("ground") is not None:  # absent or null both mean no ground
        ground = f.sub("ground")
        height = ground.number("height") if ground is not None else None
        if height is not None and lower is not None and upper is not None:
            if not lower[2] <= height < upper[2]:
                ground.bad(
                    "height", f"{height} lies outside the domain's z range [{lower[2]}, {upper[2]})"
                )
    _check_objects(f, data.get("objects", _ABSENT), meta)


def _check_objects(f: _Fields, objects: Any, meta: _Meta) -> None:
    if objects is _ABSENT:
        f.bad("objects", "missing")
        return
    if not isinstance(objects, list) or not objects:
        f.bad("objects", f"must be a non-empty list, got {objects!r}")
        return
    ids: list[int] = []
    all_ok = True
    for i, obj in enumerate(objects):
        if not isinstance(obj, dict):
            f.bad(f"objects[{i}]", f"must be a JSON object, got {obj!r}")
            all_ok = False
            continue
        of = _Fields(f.report, f.file, obj, f"objects[{i}].")
        oid = of.integer("id", minimum=1)
        of.string("name")
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
    duplicates = sorted({k for k in ids if ids.count(k) > 1})
    if duplicates:
        f.bad("objects", f"duplicate object id(s) {duplicates}; ids must be unique")
    if all_ok and not duplicates and sorted(ids) != list(range(1, len(ids) + 1)):
        f.bad("objects", f"ids are {sorted(ids)}; they must be exactly 1..K = 1..{len(ids)}")
    meta.object_ids = set(ids)


# ---------------------------------------------------------------------- cameras.json rules
def _check_cameras_json(root: Path, report: _Report, meta: _Meta) -> None:
    data = _load_json(root, "cameras.json", report)
    if data is None:
        return
    f = _Fields(report, "cameras.json", data)
    convention = data.get("convention", _ABSENT)
    if convention != "opencv":
        f.bad(
            "convention",
            "missing" if convention is _ABSENT else f"is {convention!r}, expected 'opencv'",
        )
    cameras = data.get("cameras")
    if not isinstance(cameras, list) or not cameras:
        f.bad("cameras", f"must be a non-empty list, got {cameras!r}")
        return
    for i, cam in enumerate(cameras):
        if not isinstance(cam, dict):
            f.bad(f"cameras[{i}]", f"must be a JSON object, got {cam!r}")
            continue
        cid = cam.get("id")
        cf = _Fields(report, "cameras.json", cam, f"cameras[{i}] ({cid}).")
        if not isinstance(cid, str) or not _CAMERA_ID.match(cid):
            cf.bad(
                "id",
                f"must be a name of letters, digits, '_', '.' or '-' (it names a folder), "
                f"got {cid!r}",
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
        matrix = cam.get("world_to_camera", _ABSENT)
        if matrix is _ABSENT:
            cf.bad("world_to_camera", "missing")
        elif not (
            isinstance(matrix, list)
            and len(matrix) == 4
            and all(isinstance(row, list) and len(row) == 4 for row in matrix)
            and all(_is_number(x) for row in matrix for x in row)
        ):
            cf.bad("world_to_camera", f"must be 4 rows of 4 numbers, got {matrix!r}")
        else:
            for reason in rigidity_problems(matrix):
                cf.bad("world_to_camera", f"not a rigid transform: {reason}")
        if cid is not None:
            size_ok = width is not None and height is not None
            meta.cameras[cid] = (width, height) if size_ok else None


# ----------------------------------------------------------------------------- frame files
def _check_frame_files(root: Path, report: _Report, meta: _Meta) -> list[tuple[str, str, str]]:
    """Report missing/extra frame files; return (kind, camera id, rel path) of those present."""
    present: list[tuple[str, str, str]] = []
    for kind in ("rgb", "masks"):
        top = root / kind
        if not top.is_dir():
            report.add(kind, f"missing folder ({kind}/<camera_id>/<frame:04d>.png)")
            continue
        for entry in sorted(top.iterdir()):
            if entry.name.startswith(".") and entry.is_dir():
                continue
            if not entry.is_dir():
                report.add(f"{kind}/{entry.name}", f"unexpected file; {kind}/ holds camera folders")
            elif entry.name not in meta.cameras and meta.cameras:
                report.add(
                    f"{kind}/{entry.name}",
                    f"folder for camera {entry.name!r}, which cameras.json does not declare",
                )
        for cid in meta.cameras:
            present += _check_camera_frames(root, report, kind, cid, meta.n_frames)
    return present


def _check_camera_frames(
    root: Path, report: _Report, kind: str, cid: str, n_frames: int | None
) -> list[tuple[str, str, str]]:
    folder = f"{kind}/{cid}"
    if not (root / folder).is_dir():
        report.add(folder, f"missing folder: camera {cid!r} has no {kind} frames")
        return []
    frames: list[int] = []  # frame numbers of canonically named files
    for name in sorted(p.name for p in (root / folder).iterdir()):
        match = _FRAME_FILE.match(name)
        if match and name == frame_name(int(match.group(1))):
            frames.append(int(match.group(1)))
        elif name.endswith(".tmp"):
            report.add(f"{folder}/{name}", "temporary file left by an interrupted write")
        else:
            report.add(f"{folder}/{name}", "unexpected file (frames are named 0000.png, ...)")
    if n_frames is None:  # scene.json is broken; only what is there can be checked
        return [(kind, cid, f"{folder}/{frame_name(i)}") for i in sorted(frames)]
    span = f"n_frames = {n_frames}, so frames run 0000..{n_frames - 1:04d}"
    inside = sorted(i for i in frames if i < n_frames)
    for i in sorted(i for i in frames if i >= n_frames):
        report.add(f"{folder}/{frame_name(i)}", f"extra frame ({span})")
    # gaps between present frames, found without enumerating all n_frames names; a run of
    # several missing frames is one problem on the folder so a wrong n_frames stays readable
    previous = -1
    for i in [*inside, n_frames]:
        first, last = previous + 1, i - 1
        if first == last:
            report.add(f"{folder}/{frame_name(first)}", f"missing frame ({span})")
        elif first < last:
            report.add(
                folder,
                f"missing frames {first:04d}..{last:04d} ({last - first + 1} files; {span})",
            )
        previous = i
    return [(kind, cid, f"{folder}/{frame_name(i)}") for i in inside]


def _decode_png(root: Path, rel: str, report: _Report) -> np.ndarray | None:
    import imageio.v3 as iio  # imported here: it takes ~80 ms and most callers never need it

    raw = (root / rel).read_bytes()
    if not raw.startswith(_PNG_SIGNATURE):
        report.add(rel, "is not a PNG file (missing PNG signature)")
        return None
    try:
        return np.asarray(iio.imread(raw, extension=".png"))
    except Exception as exc:  # any decoder failure is a property of the file, reported as such
        report.add(rel, f"broken PNG, cannot be decoded ({type(exc).__name__}: {exc})")
        return None


def _check_image(root: Path, report: _Report, meta: _Meta, kind: str, cid: str, rel: str) -> None:
    img = _decode_png(root, rel, report)
    if img is None:
        return
    channels = 1 if img.ndim == 2 else img.shape[2]
    want = 3 if kind == "rgb" else 1
    if img.ndim not in (2, 3) or channels != want:
        what = "3 (RGB)" if kind == "rgb" else "1 (instance ids)"
        report.add(rel, f"has {channels} channel(s), expected {what}")
    if img.dtype != np.uint8:
        report.add(rel, f"has {img.dtype.itemsize * 8}-bit samples, expected 8-bit")
    size = meta.cameras.get(cid)
    if size is not None and (img.shape[1], img.shape[0]) != size:
        report.add(
            rel,
            f"is {img.shape[1]}x{img.shape[0]} pixels but cameras.json gives camera "
            f"{cid!r} {size[0]}x{size[1]} (width x height)",
        )
    if kind == "masks" and img.ndim == 2 and meta.object_ids is not None:
        ids = set(np.flatnonzero(np.bincount(img.ravel().astype(np.int64))).tolist())
        unknown = sorted(ids - {0} - meta.object_ids)
        if unknown:
            report.add(
                rel,
                f"contains object id(s) {unknown} not declared in scene.json "
                f"(declared: {sorted(meta.object_ids)})",
            )


# ------------------------------------------------------------------------------ gt/ files
def _check_gt(root: Path, report: _Report, meta: _Meta) -> None:
    if not (root / "gt").is_dir():
        return  # ground truth is optional
    _check_gt_points(root, report, meta)
    params = _load_json(root, "gt/params.json", report)
    if params is not None:
        _check_gt_params(report, params, meta)
    effects = _load_json(root, "gt/effects.json", report, required=False)
    if effects is not None:
        _check_gt_effects(report, effects)


def _check_gt_points(root: Path, report: _Report, meta: _Meta) -> None:
    rel = "gt/points.npz"
    if not (root / rel).is_file():
        report.add(rel, "missing (gt/ exists, so it must hold points.npz)")
        return
    try:
        with np.load(root / rel, allow_pickle=False) as npz:
            arrays = {k: npz[k] for k in npz.files}
    except Exception as exc:  # zip or array corruption: a property of the file
        report.add(rel, f"cannot be read as .npz ({type(exc).__name__}: {exc})")
        return
    if meta.object_ids is not None:
        expected = {f"obj_{k}" for k in meta.object_ids}
        for key in sorted(expected - set(arrays)):
            report.add(rel, f"{key}: missing (one array per object of scene.json)")
        for key in sorted(set(arrays) - expected):
            report.add(
                rel, f"{key}: not an object of scene.json (expected keys {sorted(expected)})"
            )
    for key, arr in sorted(arrays.items()):
        if arr.dtype != np.float32:
            report.add(rel, f"{key}: dtype {arr.dtype}, expected float32")
        if arr.ndim != 3 or arr.shape[2] != 3 or arr.shape[1] < 1:
            report.add(rel, f"{key}: shape {list(arr.shape)}, expected [T, N, 3] with N >= 1")
        elif meta.n_frames is not None and arr.shape[0] != meta.n_frames:
            report.add(
                rel, f"{key}: {arr.shape[0]} frames, scene.json has n_frames = {meta.n_frames}"
            )
        if np.issubdtype(arr.dtype, np.number) and not np.all(np.isfinite(arr)):
            report.add(rel, f"{key}: contains {int(np.sum(~np.isfinite(arr)))} non-finite numbers")


def _check_gt_params(report: _Report, data: dict, meta: _Meta) -> None:
    rel = "gt/params.json"
    generator = data.get("generator", "")
    if not isinstance(generator, str):
        report.add(rel, f"generator: must be a string naming the generator, got {generator!r}")
    objects = data.get("objects")
    if not isinstance(objects, list):
        report.add(rel, f"objects: must be a list, got {objects!r}")
        return
    seen: set[int] = set()
    for i, obj in enumerate(objects):
        if not isinstance(obj, dict):
            report.add(rel, f"objects[{i}]: must be a JSON object, got {obj!r}")
            continue
        of = _Fields(report, rel, obj, f"objects[{i}].")
        oid = of.integer("id", minimum=1)
        material = of.string("material")
        if oid is not None:
            seen.add(oid)
            if meta.object_ids is not None and oid not in meta.object_ids:
                of.bad("id", f"{oid} is not an object of scene.json")
            declared = meta.materials.get(oid)
            if material is not None and declared is not None and material != declared:
                of.bad("material", f"is {material!r} but scene.json says {declared!r}")
        params = obj.get("params")
        if not isinstance(params, dict):
            of.bad("params", f"must be a JSON object of name -> number, got {params!r}")
        else:
            for name, value in params.items():
                if name not in GT_PARAM_NAMES:
                    of.bad(
                        f"params.{name}",
                        f"unknown parameter name; valid: {', '.join(GT_PARAM_NAMES)} "
                        "(a generator's own names go under generator_params)",
                    )
                elif not _is_number(value):
                    of.bad(f"params.{name}", f"must be a number, got {value!r}")
                elif math.isfinite(value) and not GT_PARAM_RANGES[name][1](value):
                    of.bad(f"params.{name}", f"{value!r} is not {GT_PARAM_RANGES[name][0]}")
        of.vec3("initial_velocity", required=False)
    if meta.object_ids is not None:
        for k in sorted(meta.object_ids - seen):
            report.add(rel, f"objects: no entry for object {k} of scene.json")


def _check_gt_effects(report: _Report, data: dict) -> None:
    rel = "gt/effects.json"
    effects = data.get("effects")
    if not isinstance(effects, list):
        report.add(rel, f"effects: must be a list, got {effects!r}")
        return
    for i, effect in enumerate(effects):
        if not isinstance(effect, dict):
            report.add(rel, f"effects[{i}]: must be a JSON object, got {effect!r}")
            continue
        ef = _Fields(report, rel, effect, f"effects[{i}].")
        ef.string("kind")
        ef.sub("params")


# ------------------------------------------------------------------------------ entry points
def _start(path: str | Path) -> tuple[Path, _Report, _Meta] | list[Problem]:
    root = Path(path)
    if not root.is_dir():
        return [Problem(".", f"scene folder {str(root)!r} does not exist or is not a folder")]
    report, meta = _Report(), _Meta()
    _check_scene_json(root, report, meta)
    _check_cameras_json(root, report, meta)
    return root, report, meta


def check_layout(path: str | Path) -> list[Problem]:
    """Problems of the JSON files and of which frame files exist; decodes no image.

    This is the cheap check ``read_scene`` runs on every load.
    """
    started = _start(path)
    if isinstance(started, list):
        return started
    root, report, meta = started
    _check_frame_files(root, report, meta)
    return report.problems


def check_scene(path: str | Path) -> list[Problem]:
    """Every problem of a scene folder (empty list for a valid scene).

    Checks scene.json and cameras.json fields, which frames exist per camera, decodes every PNG
    (size, channels, bit depth, mask ids) and checks gt/ when present.
    """
    started = _start(path)
    if isinstance(started, list):
        return started
    root, report, meta = started
    for kind, cid, rel in _check_frame_files(root, report, meta):
        _check_image(root, report, meta, kind, cid, rel)
    _check_gt(root, report, meta)
    return report.problems


def summary(scene: Scene) -> str:
    """One line describing a scene: name, objects, cameras, frames and resolution."""
    sizes = sorted({(c.width, c.height) for c in scene.cameras})
    resolution = ", ".join(f"{w}x{h}" for w, h in sizes)
    materials = ", ".join(o.material for o in scene.objects)
    return (
        f"{scene.name}: {len(scene.objects)} objects ({materials}), "
        f"{len(scene.cameras)} cameras at {resolution}, {scene.n_frames} frames "
        f"({scene.observed_frames} observed) at {scene.fps:g} fps"
    )


def run_check(path: str | Path, *, out: Callable[[str], Any] = print) -> int:
    """``mosiv data check SCENE_DIR``: print every problem, or a summary; return the exit code.

    Returns 1 when the scene has problems (each printed as ``file: reason``), 0 otherwise.
    """
    from mosiv_framework.errors import SceneFormatError
    from mosiv_framework.scene.io import read_scene

    problems = check_scene(path)
    if not problems:
        try:
            out(f"ok: {summary(read_scene(path))}")
            return 0
        except SceneFormatError as exc:  # only if the two checks ever disagree; still report
            problems = [Problem(".", p) for p in exc.problems]
    for problem in problems:
        out(str(problem))
    out(f"{len(problems)} problem(s) in {path}")
    return 1
