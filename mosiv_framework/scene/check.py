"""The rules of ``mosiv-scene/1`` (docs/SCENE_FORMAT.md): the one validator of scene folders.

``validate_scene`` lists every problem of a scene folder, each naming the file (relative to the
scene), the field or key, the value and what is valid, and never stops at the first one nor
raises on bad input; ``require_valid_scene`` raises SceneFormatError with all of them. Commands
that read a scene call one of them before any work starts. ``check_layout`` is the cheap part
(JSON files and which frame files exist, no image decoding) that ``read_scene`` runs on every
load. ``run_check`` is what ``mosiv data check`` calls.

The rules live by what they check: ``check_meta`` (scene.json), ``check_cameras``
(cameras.json), ``check_frames`` (rgb/, masks/) and ``check_gt`` (gt/).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from mosiv_framework.scene.check_cameras import check_cameras
from mosiv_framework.scene.check_common import (
    FORMAT,
    MATERIAL_FAMILIES,
    Meta,
    Problem,
    Report,
    frame_name,
    kind_reason,
    path_kind,
)
from mosiv_framework.scene.check_frames import check_frames, check_images
from mosiv_framework.scene.check_gt import GT_PARAM_NAMES, GT_PARAM_RANGES, check_gt
from mosiv_framework.scene.check_meta import check_meta

if TYPE_CHECKING:
    from mosiv_framework.scene.io import Scene

__all__ = [
    "FORMAT",
    "GT_PARAM_NAMES",
    "GT_PARAM_RANGES",
    "MATERIAL_FAMILIES",
    "Problem",
    "check_layout",
    "check_scene",
    "frame_name",
    "require_valid_scene",
    "run_check",
    "summary",
    "validate_scene",
]


# ------------------------------------------------------------------------------ entry points
def _root_problem(root: Path) -> Problem | None:
    """Why ``root`` is not a scene folder to read, or None when it is a folder."""
    kind = path_kind(root)
    if kind == "folder":
        return None
    if kind == "missing":
        reason = f"scene folder {str(root)!r} does not exist"
    elif kind == "file":
        reason = (
            f"{str(root)!r} is a file, not a scene folder; give the folder that holds "
            "scene.json, cameras.json, rgb/ and masks/"
        )
    else:
        reason = f"scene folder {str(root)!r} {kind_reason(kind, 'a folder')}"
    return Problem(".", reason)


def _guarded(report: Report, file: str, rule: Callable[[], Any]) -> Any:
    """Run one group of rules so that a fault in the checker itself still ends as a problem
    naming the files it was checking, never as a traceback instead of the other problems."""
    try:
        return rule()
    except Exception as exc:  # a checker bug must not hide the problems already found
        report.add(file, f"could not be checked ({type(exc).__name__}: {exc}); please report")
        return None


def _collect(path: str | Path, *, images: bool, need_ground_truth: bool | None) -> list[Problem]:
    root = Path(path)
    problem = _root_problem(root)
    if problem is not None:
        return [problem]
    report, meta = Report(), Meta()
    _guarded(report, "scene.json", lambda: check_meta(root, report, meta))
    _guarded(report, "cameras.json", lambda: check_cameras(root, report, meta))
    present = _guarded(report, "rgb, masks", lambda: check_frames(root, report, meta))
    if images and present:
        _guarded(report, "rgb, masks", lambda: check_images(root, report, meta, present))
    if need_ground_truth is not False:
        _guarded(report, "gt", lambda: check_gt(root, report, meta, required=need_ground_truth))
    return report.problems


def validate_scene(path: str | Path, *, need_ground_truth: bool | None = None) -> list[str]:
    """Every problem of a scene folder as ``"file: reason"`` lines (file relative to the
    scene folder); an empty list for a valid scene. Never raises on bad input and never writes.

    Checks scene.json and cameras.json field by field, which frame files exist and that each is
    a readable file, decodes every PNG (size, channels, bit depth, mask ids, every object in
    some mask), and checks gt/ (points.npz: one finite float32 [n_frames, N, 3] array per
    object, read without pickle; params.json; effects.json).

    Args:
        path: the scene folder.
        need_ground_truth: True when the caller reads gt/ (oracle reconstruction, evaluation
            against ground truth): a missing gt/ is then a problem. None checks gt/ only where
            it exists (a scene without ground truth is valid). False skips gt/.

    Returns:
        The problems, in the order found.
    """
    return [str(p) for p in check_scene(path, need_ground_truth=need_ground_truth)]


def require_valid_scene(path: str | Path, *, need_ground_truth: bool | None = None) -> None:
    """Raise SceneFormatError listing every problem of ``validate_scene``, each prefixed with
    the scene folder; return None for a valid scene. Commands call it before any stage runs."""
    from mosiv_framework.errors import SceneFormatError

    problems = check_scene(path, need_ground_truth=need_ground_truth)
    if problems:
        root = Path(path)
        raise SceneFormatError(
            [str(p) if p.file == "." else f"{root / p.file}: {p.reason}" for p in problems]
        )


def check_layout(path: str | Path) -> list[Problem]:
    """Problems of the JSON files and of which frame files exist; decodes no image.

    This is the cheap check ``read_scene`` runs on every load.
    """
    return _collect(path, images=False, need_ground_truth=False)


def check_scene(path: str | Path, *, need_ground_truth: bool | None = None) -> list[Problem]:
    """Every problem of a scene folder as ``Problem`` objects (see ``validate_scene``)."""
    return _collect(path, images=True, need_ground_truth=need_ground_truth)


def summary(scene: Scene) -> str:
    """One line describing a scene: name, objects, cameras, frames and resolution."""
    sizes = sorted({(c.width, c.height) for c in scene.cameras})
    resolution = ", ".join(f"{w}x{h}" for w, h in sizes)
    materials = ", ".join(o.material for o in scene.objects)
    partial = "".join(
        f"; {cid} recorded frames {first}..{last} only"
        for cid, (first, last) in scene.camera_frames.items()
    )
    return (
        f"{scene.name}: {len(scene.objects)} objects ({materials}), "
        f"{len(scene.cameras)} cameras at {resolution}, {scene.n_frames} frames "
        f"({scene.observed_frames} observed) at {scene.fps:g} fps{partial}"
    )


def run_check(path: str | Path, *, out: Callable[[str], Any] = print) -> int:
    """``mosiv data check SCENE_DIR``: print every problem, or a summary; return the exit code.

    Returns 1 when the scene has problems (each printed as ``file: reason``), 0 otherwise.
    """
    from mosiv_framework.errors import SceneFormatError
    from mosiv_framework.scene.io import read_scene

    problems = check_scene(path)  # the same rules as validate_scene / require_valid_scene
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
