"""Rules of the frame files (docs/SCENE_FORMAT.md): ``rgb/<camera>/<frame:04d>.png`` (8-bit
RGB) and ``masks/<camera>/<frame:04d>.png`` (8-bit object ids), one per camera and frame.

``check_frames`` looks only at names and file types (cheap: ``read_scene`` runs it on every
load); ``check_images`` decodes every PNG.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from mosiv_framework.scene.check_common import Meta, Report, frame_name, kind_reason, path_kind

FRAME_FILE = re.compile(r"^(\d{4,})\.png$")
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
KINDS = ("rgb", "masks")


def _list(root: Path, rel: str, report: Report) -> list[Path] | None:
    """Sorted entries of folder ``root/rel``, or None (reported) when it cannot be listed."""
    try:
        return sorted((root / rel).iterdir())
    except OSError as exc:
        report.add(rel, f"cannot be listed ({exc.strerror or exc})")
        return None


def check_frames(root: Path, report: Report, meta: Meta) -> list[tuple[str, str, str]]:
    """Report missing, extra and non-file frames; return (kind, camera id, rel path) of every
    frame that is a readable file (symbolic links to files count as files)."""
    present: list[tuple[str, str, str]] = []
    for kind in KINDS:
        top_kind = path_kind(root / kind)
        if top_kind != "folder":
            reason = kind_reason(top_kind, f"a folder ({kind}/<camera_id>/<frame:04d>.png)")
            report.add(kind, "missing folder" if top_kind == "missing" else reason)
            continue
        for entry in _list(root, kind, report) or []:
            entry_kind = path_kind(entry)
            if entry.name.startswith(".") and entry_kind == "folder":
                continue
            rel = f"{kind}/{entry.name}"
            if entry_kind != "folder":
                if entry_kind == "file":
                    report.add(rel, f"unexpected file; {kind}/ holds camera folders")
                else:
                    report.add(rel, kind_reason(entry_kind, "a camera folder"))
            elif entry.name not in meta.cameras and meta.cameras:
                report.add(
                    rel, f"folder for camera {entry.name!r}, which cameras.json does not declare"
                )
        for cid in meta.cameras:
            span = meta.camera_frames.get(cid)
            present += _check_camera_frames(root, report, kind, cid, meta.n_frames, span)
    return present


def _check_camera_frames(
    root: Path,
    report: Report,
    kind: str,
    cid: str,
    n_frames: int | None,
    span: tuple[int, int] | None = None,
) -> list[tuple[str, str, str]]:
    """Problems of one camera's frame folder; ``span``: the (first, last) frames the camera
    recorded where cameras.json gives them (None: every frame of the scene)."""
    folder = f"{kind}/{cid}"
    folder_kind = path_kind(root / folder)
    if folder_kind != "folder":
        if folder_kind == "missing":
            report.add(folder, f"missing folder: camera {cid!r} has no {kind} frames")
        else:
            report.add(folder, kind_reason(folder_kind, f"the folder of camera {cid!r}"))
        return []
    frames: list[int] = []  # frame numbers of canonically named entries, files or not
    readable: set[int] = set()  # those that are files
    for entry in _list(root, folder, report) or []:
        name = entry.name
        match = FRAME_FILE.match(name)
        if match and name == frame_name(int(match.group(1))):
            frames.append(int(match.group(1)))
            entry_kind = path_kind(entry)
            if entry_kind == "file":
                readable.add(frames[-1])
            else:
                report.add(f"{folder}/{name}", kind_reason(entry_kind, "a PNG file"))
        elif name.endswith(".tmp"):
            report.add(f"{folder}/{name}", "temporary file left by an interrupted write")
        else:
            report.add(f"{folder}/{name}", "unexpected file (frames are named 0000.png, ...)")
    if n_frames is None:  # scene.json is broken; only what is there can be checked
        return [(kind, cid, f"{folder}/{frame_name(i)}") for i in sorted(readable)]
    first, last = (0, n_frames - 1) if span is None else span
    if span is None:
        rule = f"n_frames = {n_frames}, so frames run 0000..{n_frames - 1:04d}"
    else:
        rule = f"cameras.json: camera {cid!r} recorded frames {first:04d}..{last:04d}"
    inside = sorted(i for i in frames if first <= i <= last)
    for i in sorted(i for i in frames if not first <= i <= last):
        report.add(f"{folder}/{frame_name(i)}", f"extra frame ({rule})")
    # gaps between present frames, found without enumerating all n_frames names; a run of
    # several missing frames is one problem on the folder so a wrong n_frames stays readable
    previous = first - 1
    for i in [*inside, last + 1]:
        gap_first, gap_last = previous + 1, i - 1
        if gap_first == gap_last:
            report.add(f"{folder}/{frame_name(gap_first)}", f"missing frame ({rule})")
        elif gap_first < gap_last:
            report.add(
                folder,
                f"missing frames {gap_first:04d}..{gap_last:04d} "
                f"({gap_last - gap_first + 1} files; {rule})",
            )
        previous = i
    return [(kind, cid, f"{folder}/{frame_name(i)}") for i in inside if i in readable]


def decode_png(root: Path, rel: str, report: Report) -> np.ndarray | None:
    """The pixels of ``root/rel``, or None with the reason reported."""
    import imageio.v3 as iio  # imported here: it takes ~80 ms and most callers never need it

    try:
        raw = (root / rel).read_bytes()
    except OSError as exc:
        report.add(rel, f"cannot be read ({exc.strerror or exc})")
        return None
    if not raw.startswith(PNG_SIGNATURE):
        report.add(rel, "is not a PNG file (missing PNG signature)")
        return None
    try:
        return np.asarray(iio.imread(raw, extension=".png"))
    except Exception as exc:  # any decoder failure is a property of the file, reported as such
        report.add(rel, f"broken PNG, cannot be decoded ({type(exc).__name__}: {exc})")
        return None


def check_images(root: Path, report: Report, meta: Meta, present) -> None:
    """Decode every frame of ``present`` (from ``check_frames``): channels, bit depth, size
    against cameras.json, mask ids against scene.json, and every object in some mask."""
    seen: set[int] = set()
    masks_read = 0
    for kind, cid, rel in present:
        ids = _check_image(root, report, meta, kind, cid, rel)
        if ids is not None:
            seen |= ids
            masks_read += 1
    if masks_read and meta.object_ids:
        for k in sorted(meta.object_ids - seen):
            name = meta.names.get(k, "?")
            report.add(
                "masks",
                f"object {k} ({name}) of scene.json appears in no mask of any camera and "
                f"frame ({masks_read} masks read); it cannot be reconstructed",
            )


def _check_image(
    root: Path, report: Report, meta: Meta, kind: str, cid: str, rel: str
) -> set[int] | None:
    """Check one decoded frame; for a valid one-channel mask return the ids it holds."""
    img = decode_png(root, rel, report)
    if img is None:
        return None
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
    if kind != "masks" or img.ndim != 2:
        return None
    ids = set(np.flatnonzero(np.bincount(img.ravel().astype(np.int64))).tolist()) - {0}
    if meta.object_ids is not None:
        unknown = sorted(ids - meta.object_ids)
        if unknown:
            report.add(
                rel,
                f"contains object id(s) {unknown} not declared in scene.json "
                f"(declared: {sorted(meta.object_ids)})",
            )
    return ids
