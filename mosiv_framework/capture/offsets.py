"""Per-camera time offsets: how many leading frames each camera's video drops so that frame i
of every camera shows the same instant.

Given as ``cam_01:3,cam_02:0`` (``cam_01=3`` works too; or the ``offsets`` mapping of the objects YAML), or estimated
from motion onset: per camera, the first frame whose mean absolute difference to the frame
before exceeds ``k`` times the median difference of the first ``baseline`` frames (sensor
noise and compression flicker set that median); the onsets are aligned to the earliest.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from mosiv_framework.capture.common import CaptureError

#: a difference threshold never below this (grey levels of 0..255): noise-free rendered video
#: has a zero median difference, and compression flicker stays below it
MIN_THRESHOLD = 0.5


def parse_offsets(text: str | Mapping | None, cameras: list[str], where: str) -> dict | None:
    """Camera id -> frames to drop, from ``"cam:frames,..."`` or a mapping; None when absent
    (estimate them). ``"none"`` means all zero (a synchronised rig). Cameras not named get 0;
    the smallest offset is moved to 0 so negative values (a camera that started late) work."""
    if text is None:
        return None
    if isinstance(text, str) and text.strip().lower() == "none":
        return {c: 0 for c in cameras}
    if isinstance(text, str):
        pairs = {}
        for item in [p.strip() for p in text.split(",") if p.strip()]:
            for mark in (":", "="):  # cam_01:3 as the import documents, cam_01=3 as well
                cam, sep, value = item.rpartition(mark)
                if sep:
                    break
            if not sep:
                raise CaptureError(f"{where} {item!r}: give CAMERA:FRAMES, e.g. cam_01:3")
            pairs[cam] = value
    elif isinstance(text, Mapping):
        pairs = dict(text)
    else:
        raise CaptureError(f"{where}: expected a mapping camera -> frames, got {text!r}")
    out = {c: 0 for c in cameras}
    for cam, value in pairs.items():
        if str(cam) not in out:
            raise CaptureError(f"{where}: unknown camera {cam!r}; cameras: {', '.join(cameras)}")
        try:
            out[str(cam)] = int(value)
        except (TypeError, ValueError):
            raise CaptureError(
                f"{where}: {cam}: frames must be an integer, got {value!r}"
            ) from None
    low = min(out.values())
    return {c: v - low for c, v in out.items()}


def frame_differences(frames: np.ndarray) -> np.ndarray:
    """[T - 1] mean absolute difference (grey levels) between consecutive frames [T, H, W, 3]."""
    f = frames.astype(np.int16)
    return np.abs(np.diff(f, axis=0)).mean(axis=(1, 2, 3))


def motion_onset(frames: np.ndarray, *, k: float = 4.0, baseline: int = 3) -> int | None:
    """Index of the first frame that differs from its predecessor by more than ``k`` x the
    median difference of the first ``baseline`` frame pairs (at least MIN_THRESHOLD); None when
    nothing moves."""
    d = frame_differences(frames)
    if d.size == 0:
        return None
    threshold = max(k * float(np.median(d[:baseline])), MIN_THRESHOLD)
    moving = np.nonzero(d > threshold)[0]
    return int(moving[0]) + 1 if moving.size else None


def estimate_offsets(videos: Mapping[str, np.ndarray], **kw) -> dict[str, int]:
    """Camera id -> frames to drop so that all motion onsets fall on the same frame."""
    onsets = {cam: motion_onset(v, **kw) for cam, v in videos.items()}
    still = sorted(c for c, o in onsets.items() if o is None)
    if still:
        raise CaptureError(
            f"cannot estimate time offsets: nothing moves in camera(s) {', '.join(still)} "
            "(no motion onset); give --offsets (or --offsets none for a synchronised rig)"
        )
    first = min(onsets.values())
    return {cam: o - first for cam, o in onsets.items()}


#: what the import does with cameras that started after the first ones (``--late-cameras``)
LATE_CAMERA_POLICIES = ("trim", "drop", "keep")


def cameras_left_out(offsets: Mapping[str, int], policy: str) -> list[str]:
    """The cameras the import leaves out under ``policy``: "trim" none (every camera that
    started earlier drops the leading frames the late ones lack, so all cameras keep the
    common frames), "drop" the cameras that started late (offset below the largest), so that
    the others keep every frame, "keep" none (every camera keeps every frame it recorded; the
    late ones are declared as such, ``pad_late_cameras``). CaptureError for an unknown policy,
    or where "drop" would leave fewer than two cameras."""
    if policy not in LATE_CAMERA_POLICIES:
        valid = ", ".join(LATE_CAMERA_POLICIES)
        raise CaptureError(f"--late-cameras {policy!r}: valid values are {valid}")
    if policy in ("trim", "keep") or not offsets:
        return []
    first = max(offsets.values())
    late = sorted(c for c, o in offsets.items() if o < first)
    kept = sorted(c for c in offsets if c not in late)
    if late and len(kept) < 2:
        raise CaptureError(
            f"--late-cameras drop would leave {len(kept)} camera ({', '.join(kept)}): "
            f"{', '.join(late)} started later (offsets {dict(offsets)}); use --late-cameras "
            "trim to keep every camera over the common frames"
        )
    return late


def pad_late_cameras(
    videos: Mapping[str, np.ndarray], offsets: Mapping[str, int], n_frames: int | None
) -> tuple[dict[str, np.ndarray], dict[str, tuple[int, int]]]:
    """``--late-cameras keep``: every camera drops the frames all of them are to drop (the
    smallest offset), and the clip starts with the camera that started first (the largest
    offset) and ends with the one that stopped last (or after ``n_frames``). A camera that
    started ``d`` frames late gets ``d`` leading frames of zeros, one that stopped early
    trailing zeros, which the scene declares as not recorded. Returns (videos of equal
    length, camera id -> (first, last) recorded frames of the cameras that did not record
    every frame). CaptureError naming the cameras when fewer than two frames remain, a
    camera starts after the last frame kept, or ``n_frames`` exceeds every camera."""
    if n_frames is not None and n_frames < 2:
        raise CaptureError(f"--frames {n_frames}: keep at least 2 frames")
    given = [offsets.get(cam, 0) for cam in videos]
    common, first = min(given, default=0), max(given, default=0)
    starts = {cam: first - offsets.get(cam, 0) for cam in videos}
    ends = {cam: starts[cam] + len(v) - common for cam, v in videos.items()}  # exclusive
    longest = max(ends.values())
    if n_frames is not None and n_frames > longest:
        raise CaptureError(f"--frames {n_frames}: the cameras cover {longest} frames at most")
    n = longest if n_frames is None else n_frames
    if n < 2:
        raise CaptureError(f"too few frames after the offsets: {n}")
    late = sorted(cam for cam, start in starts.items() if start >= n)
    if late:
        raise CaptureError(f"camera(s) {', '.join(late)} start after the last kept frame {n - 1}")
    out = {}
    for cam, video in videos.items():
        if starts[cam] == 0 and common == 0 and len(video) == n:  # all of it, unpadded:
            out[cam] = video  # not copied (a view of part of it would hold the rest too)
            continue
        shape = video.shape[1:]
        before = np.zeros((starts[cam],) + shape, video.dtype)
        after = np.zeros((max(0, n - ends[cam]),) + shape, video.dtype)
        out[cam] = np.concatenate([before, video[common:], after])[:n]
    spans = {
        cam: (starts[cam], min(ends[cam], n) - 1)
        for cam in videos
        if starts[cam] > 0 or ends[cam] < n
    }
    return out, spans


def apply_offsets(
    videos: Mapping[str, np.ndarray], offsets: Mapping[str, int], n_frames: int | None
) -> dict[str, np.ndarray]:
    """Drop each camera's leading frames; keep the first ``n_frames`` if given. CaptureError
    naming each camera's count when the counts then differ."""
    if n_frames is not None and n_frames < 2:
        raise CaptureError(f"--frames {n_frames}: keep at least 2 frames")
    out = {cam: v[offsets.get(cam, 0) :] for cam, v in videos.items()}
    if n_frames is not None:
        short = {c: len(v) for c, v in out.items() if len(v) < n_frames}
        if short:
            raise CaptureError(f"--frames {n_frames}: camera(s) have fewer frames {short}")
        out = {cam: v[:n_frames] for cam, v in out.items()}
    counts = {cam: len(v) for cam, v in out.items()}
    if len(set(counts.values())) > 1:
        raise CaptureError(
            f"cameras have different frame counts after the offsets {dict(offsets)}: {counts}; "
            "trim the videos, fix the offsets, or give --frames N to keep the first N"
        )
    if min(counts.values()) < 2:
        raise CaptureError(f"too few frames after the offsets: {counts}")
    return out
