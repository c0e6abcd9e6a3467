"""Frames of a recording: one video file or one folder of images per camera.

A frames folder holds, per camera, either a video (``<camera id>.mp4``, ``.mov``, ``.avi``,
``.mkv``, ``.m4v``, ``.webm``) or a folder ``<camera id>/`` of images (``.png``, ``.jpg``,
``.jpeg``, ``.bmp``, ``.tif``, ``.tiff``) taken in file-name order, numbers read as numbers
(2.png before 10.png). The camera id is the video's file stem or the folder's name.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from mosiv_framework.capture import frame_times
from mosiv_framework.capture.common import CaptureError, natural_key
from mosiv_framework.errors import OutputError, StageNotAvailable

logger = logging.getLogger(__name__)

VIDEO_SUFFIXES = (".mp4", ".mov", ".avi", ".mkv", ".m4v", ".webm")
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")
#: suffixes that name one kind of image
SAME_KIND = {".jpeg": ".jpg", ".tiff": ".tif"}


def _is_frame(path: Path) -> bool:
    """An image file that is not hidden (.DS_Store, macOS's ._frame.png copies)."""
    return (
        path.is_file() and not path.name.startswith(".") and path.suffix.lower() in IMAGE_SUFFIXES
    )


def find_sources(folder: str | Path) -> dict[str, Path]:
    """Camera id -> its video file or image folder in ``folder``; CaptureError when there are
    none or when one id has both a video and a folder."""
    root = Path(folder)
    if not root.is_dir():
        raise CaptureError(f"frames folder {str(root)!r} does not exist or is not a folder")
    sources: dict[str, Path] = {}
    for entry in sorted(root.iterdir()):
        if entry.name.startswith("."):
            continue
        if entry.is_file() and entry.suffix.lower() in VIDEO_SUFFIXES:
            key = entry.stem
        elif entry.is_dir() and any(_is_frame(p) for p in entry.iterdir()):
            key = entry.name
        else:
            continue
        if key in sources:
            raise CaptureError(
                f"{root}: camera {key!r} has two sources ({sources[key].name}, {entry.name}); "
                "keep one"
            )
        sources[key] = entry
    if not sources:
        raise CaptureError(
            f"{root}: holds no video ({', '.join(VIDEO_SUFFIXES)}) and no folder of images; "
            "give one video or image folder per camera"
        )
    return sources


def rgb8(image: np.ndarray, where: str) -> np.ndarray:
    """Any decoded image -> uint8 [H, W, 3]."""
    img = np.asarray(image)
    if img.dtype == np.uint16:
        img = (img // 257).astype(np.uint8)
    if img.dtype != np.uint8:
        raise CaptureError(f"{where}: pixels are {img.dtype}; expected 8- or 16-bit images")
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=2)
    if img.ndim != 3 or img.shape[2] not in (3, 4):
        raise CaptureError(f"{where}: shape {list(img.shape)} is not an RGB image")
    return np.ascontiguousarray(img[..., :3])


def shrunk_size(height: int, width: int, longest_side: int | None) -> tuple[int, int]:
    """(height, width) of a frame whose longest side is brought down to ``longest_side``
    pixels (None, or a frame already that small: unchanged)."""
    if longest_side is None or max(height, width) <= longest_side:
        return height, width
    scale = longest_side / max(height, width)
    return max(1, round(height * scale)), max(1, round(width * scale))


def shrink(frame: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """``frame`` uint8 [H, W, 3] resampled to ``size`` (height, width) with Pillow's Lanczos
    filter, which averages over the footprint when it shrinks (no aliasing)."""
    if frame.shape[:2] == size:
        return frame
    from PIL import Image

    image = Image.fromarray(frame).resize((size[1], size[0]), Image.Resampling.LANCZOS)
    return np.asarray(image)


#: what a camera's frames must measure before any shrinking: ((height, width), who says so)
Expected = tuple[tuple[int, int], str]


def _check_size(frame: np.ndarray, expect: Expected | None, where: str) -> None:
    """A frame's size as recorded against the camera's (``expect``), so that a shrunk frame
    never hides frames of another camera's size."""
    if expect is not None and frame.shape[:2] != expect[0]:
        (h, w), who = expect
        raise CaptureError(
            f"{where}: frames are {frame.shape[1]}x{frame.shape[0]} pixels, but {who} {w}x{h}"
        )


def read_video(
    path: Path,
    *,
    every: int = 1,
    longest_side: int | None = None,
    expect: Expected | None = None,
) -> tuple[np.ndarray, float | None]:
    """Frames uint8 [T, H, W, 3] and the frame rate of a video file (ffmpeg via imageio):
    every ``every``-th frame from the first, each brought down to ``longest_side`` pixels as
    it is decoded (so a long high-resolution clip never sits in memory at full size). The
    rate returned is the video's own; ``expect``: the size the frames must have as recorded.
    A clip recorded at a variable frame rate is first resampled to even times at its regular
    rate, which is returned (frame_times.py)."""
    try:
        import imageio.v2 as iio2
        import imageio_ffmpeg  # noqa: F401 -- imageio's FFMPEG format needs it
    except ImportError as exc:
        raise StageNotAvailable(
            f"{path}: reading videos needs imageio-ffmpeg (pip install imageio-ffmpeg)"
        ) from exc
    copies, even_rate = _frame_copies(path, every)
    try:
        # passthrough: every decoded frame once; ffmpeg's default constant-rate output would
        # repeat or drop frames of a variable-frame-rate or high-speed video
        reader = iio2.get_reader(
            str(path), format="FFMPEG", output_params=["-fps_mode", "passthrough"]
        )
        try:
            fps = even_rate or reader.get_meta_data().get("fps")
            frames, decoded = [], 0
            for i, frame in enumerate(reader):
                decoded = i + 1
                if i == 0:
                    _check_size(frame, expect, str(path))
                n = (i % every == 0) if copies is None else (copies[i] if i < len(copies) else 0)
                if n:
                    frame = rgb8(frame, str(path))
                    size = shrunk_size(*frame.shape[:2], longest_side)
                    frames.extend([shrink(frame, size)] * int(n))
        finally:
            reader.close()
    except CaptureError:
        raise
    except Exception as exc:  # ffmpeg reports a broken file in many ways; all mean "unreadable"
        raise OutputError(f"{path}: cannot be read as a video ({exc})") from exc
    if not frames:
        raise OutputError(f"{path}: cannot be read as a video (it holds no frames)")
    if copies is not None and decoded != len(copies):
        logger.warning(
            "%s: %d frames decoded but %d timestamped: the even resampling may be off by the "
            "difference",
            path,
            decoded,
            len(copies),
        )
    return np.stack(frames), (float(fps) if fps else None)


def _frame_copies(path: Path, every: int) -> tuple[np.ndarray | None, float | None]:
    """(how many times each decoded frame is kept, the even rate) of a variable-frame-rate
    clip resampled to even times, then every ``every``-th; (None, None) for an even clip."""
    stamps = frame_times.presentation_times(path)
    uneven = frame_times.even_frames(stamps) if stamps is not None else None
    if uneven is None:
        return None, None
    picks, rate = uneven
    logger.warning(
        "%s: recorded at a variable frame rate, %s; resampled to %.4g fps",
        path,
        frame_times.describe(stamps, picks),
        rate,
    )
    return np.bincount(picks[::every], minlength=len(stamps.times)), rate


def read_image_folder(
    path: Path,
    *,
    every: int = 1,
    longest_side: int | None = None,
    expect: Expected | None = None,
) -> np.ndarray:
    """Frames uint8 [T, H, W, 3] of a folder of images, in file-name order with numbers read
    as numbers (2.png before 10.png): every ``every``-th from the first, each brought down to
    ``longest_side`` pixels; ``expect``: the size they must have as recorded."""
    # hidden files (.DS_Store, macOS's ._frame.png) are not frames
    files = sorted((p for p in path.iterdir() if _is_frame(p)), key=lambda p: natural_key(p.name))
    if not files:
        raise CaptureError(f"{path}: holds no image frames (hidden files are not frames)")
    kinds = sorted({SAME_KIND.get(p.suffix.lower(), p.suffix.lower()) for p in files})
    if len(kinds) > 1:
        raise CaptureError(
            f"{path}: holds frames of several kinds ({', '.join(kinds)}); a camera's frames are "
            "one sequence of one kind: keep one"
        )
    frames, first = [], None
    for f in files[::every]:
        try:
            frame = rgb8(read_image(f), str(f))
        except CaptureError:
            raise
        except Exception as exc:
            raise OutputError(f"{f}: cannot be read as an image ({exc})") from exc
        if first is None:
            _check_size(frame, expect, str(path))
            first = frame.shape
        elif frame.shape != first:
            raise CaptureError(
                f"{f}: is {frame.shape[1]}x{frame.shape[0]} pixels, but {files[0].name} is "
                f"{first[1]}x{first[0]}; a camera's frames share one size"
            )
        frames.append(shrink(frame, shrunk_size(*frame.shape[:2], longest_side)))
    return np.stack(frames)


def read_image(path: Path) -> np.ndarray:
    """One image as a viewer shows it: its EXIF orientation applied, and palette, CMYK,
    grey + alpha and other modes converted to RGB by Pillow; grey, RGB and RGBA are kept as
    stored (16-bit grey too) for ``rgb8``."""
    from PIL import Image, ImageOps

    with Image.open(path) as image:
        image = ImageOps.exif_transpose(image)
        if image.mode not in ("L", "I;16", "I;16B", "I;16L", "RGB", "RGBA", "I", "F"):
            image = image.convert("RGB")
        return np.array(image)  # a writable copy (torch reads it later)


def read_frames(
    source: Path,
    *,
    every: int = 1,
    longest_side: int | None = None,
    expect: Expected | None = None,
) -> tuple[np.ndarray, float | None]:
    """(frames uint8 [T, H, W, 3], the source's own fps or None) of one camera's video file or
    image folder: every ``every``-th frame, brought down to ``longest_side`` pixels, after
    checking their recorded size against ``expect`` ((height, width), who gives that size)."""
    if every < 1:
        raise CaptureError(f"--every {every}: must be a whole number >= 1")
    if longest_side is not None and longest_side < 16:
        raise CaptureError(f"--resolution {longest_side}: must be at least 16 pixels")
    kw = {"every": every, "longest_side": longest_side, "expect": expect}
    if source.is_dir():
        return read_image_folder(source, **kw), None
    return read_video(source, **kw)


#: a camera's rate is a whole multiple of the slowest camera's when within this fraction of it
WHOLE_MULTIPLE_TOLERANCE = 0.01


def rate_steps(sources: Mapping[str, Path]) -> dict[str, int]:
    """Camera id -> how many of its frames make one frame of the slowest video: 2 for a 60 fps
    camera beside 30 fps ones (every second frame shows the instants the others show), 1 for
    an image folder, a video at the slowest rate, or one whose rate is no whole multiple of it
    (``common_fps`` then names the rates that differ). Rates from the frames' timestamps
    (``frame_times.Timestamps.rate``)."""
    rates = {}
    for cam, path in sources.items():
        stamps = frame_times.presentation_times(path) if path.is_file() else None
        if stamps is not None and len(stamps.times) > 2 and np.median(np.diff(stamps.times)) > 0:
            rates[cam] = stamps.rate()
    slowest = min(rates.values(), default=None)
    steps = dict.fromkeys(sources, 1)
    for cam, rate in rates.items():
        ratio = rate / slowest
        whole = round(ratio)
        if whole >= 2 and abs(ratio - whole) <= WHOLE_MULTIPLE_TOLERANCE * whole:
            steps[cam] = whole
            logger.info(
                "%s records at %.4g fps, %dx the slowest camera's %.4g: every %s frame kept",
                sources[cam].name, rate, whole, slowest, _ordinal(whole),
            )  # fmt: skip
    return steps


def _ordinal(n: int) -> str:
    return {2: "second", 3: "third"}.get(n, f"{n}th")


def common_fps(
    rates: dict[str, float | None], given: float | None, folder: Path, n_frames: int = 1
) -> float:
    """The recording's frame rate: ``given`` (``--fps``) if set, else the videos' own rate.
    The cameras' rates must agree closely enough that over the clip (``n_frames``, the
    longest camera's) their clocks drift less than half a frame apart (29.97 and 30 fps do
    over 300 frames, not over 600), and within 1 % in any case."""
    if given is not None:
        if not given > 0:
            raise CaptureError(f"--fps {given}: must be positive")
        return float(given)
    known = {cam: r for cam, r in rates.items() if r}
    if not known:
        raise CaptureError(
            f"{folder}: the frames carry no frame rate (image folders, or videos whose rate "
            "ffmpeg does not report as a number); give --fps"
        )
    lo, hi = min(known.values()), max(known.values())
    drift = (hi - lo) / lo * n_frames  # frames apart at the clip's end
    if hi > 1.01 * lo or drift >= 0.5:
        raise CaptureError(
            f"{folder}: the videos' frame rates differ ({known}): over {n_frames} frames they "
            f"drift {drift:.2g} frames apart; convert them to one rate, or give --fps to take "
            "every frame as equally spaced at that rate"
        )
    return float(np.median(list(known.values())))
