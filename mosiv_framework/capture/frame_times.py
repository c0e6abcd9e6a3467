"""When a video's frames were taken, and an even-rate sequence made from an uneven one.

Simulation steps frames at one rate (docs/SCENE_FORMAT.md: ``fps``), so an import must hand it
evenly spaced frames. Phones and many action cameras record at a variable frame rate: under
load or in low light the encoder drops or stretches frames, and the container's timestamps
say so while the frame count does not. Read back to back, such a clip runs fast after each gap,
and every velocity identified from it is wrong there.

``presentation_times`` reads the timestamps of the video's packets with ffmpeg's ``framecrc``
muxer (stream copy: nothing is decoded; packets an edit list discards are left out, as the
decoder leaves them out), and ``even_frames`` picks, for each instant of an even grid at the
clip's regular rate, the frame shown nearest to it: a gap repeats the frame before or after
it, a burst drops frames. A clip whose intervals all lie within ``UNEVEN_TOLERANCE`` of their
median (or a tick and a half of its time base) is left as it is.
"""

from __future__ import annotations

import functools
import logging
import subprocess
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path

import numpy as np

logger = logging.getLogger(__name__)

#: a clip is uneven when some frame interval strays more than this fraction from the median
#: (and more than TICKS_TOLERATED ticks of its time base: a 1 ms base quantises 30 fps to
#: intervals of 33 and 34 ms, 300 fps to 3 and 4)
UNEVEN_TOLERANCE = 0.25
TICKS_TOLERATED = 1.5
#: framecrc's packet flag for a packet the container's edit list discards (a clip cut without
#: re-encoding keeps the frames before its cut, marked so; they are never shown)
DISCARD_FLAG = 0x4


@dataclass(frozen=True)
class Timestamps:
    """When each shown frame of a video is shown (s, sorted), and its time base's tick (s)."""

    times: np.ndarray
    tick: float

    def regular(self) -> np.ndarray:
        """Which frame intervals are regular: within the tolerance of the median."""
        intervals = np.diff(self.times)
        median = float(np.median(intervals))
        slack = max(UNEVEN_TOLERANCE * median, TICKS_TOLERATED * self.tick)
        return np.abs(intervals - median) <= slack

    def rate(self) -> float:
        """Frames per second: one over the median interval, dequantised: the mean of the
        intervals within TICKS_TOLERATED ticks of the median (a 1 ms base gives 30 fps as 33
        and 34 ms, whose median is either; a burst's shortened neighbours stay out)."""
        intervals = np.diff(self.times)
        median = float(np.median(intervals))
        near = np.abs(intervals - median) <= TICKS_TOLERATED * self.tick + 1e-12 * median
        return 1.0 / float(intervals[near].mean())


def presentation_times(path: Path) -> Timestamps | None:
    """When the first video stream's frames are shown, in presentation order, or None where
    ffmpeg gives no timestamps (a stream without them, or a file it cannot read: decoding
    then reports the file). An import asks for each video's up to three times (its rate, its
    frames, its sound's offset): the file is read once while it stays unchanged."""
    try:
        stat = Path(path).stat()
    except OSError:  # decoding names the missing or unreadable file
        return None
    return _read_times(str(Path(path).resolve()), stat.st_mtime_ns, stat.st_size)


@functools.lru_cache(maxsize=64)
def _read_times(path: str, mtime_ns: int, size: int) -> Timestamps | None:
    """``presentation_times`` of the file as it is at (mtime_ns, size): a file rewritten in
    place is read again."""
    import imageio_ffmpeg

    command = [imageio_ffmpeg.get_ffmpeg_exe(), "-v", "error", "-i", path]
    command += ["-map", "0:v:0", "-c", "copy", "-f", "framecrc", "-"]
    done = subprocess.run(command, capture_output=True, text=True)
    if done.returncode != 0:
        return None
    return parse_framecrc(done.stdout)


def parse_framecrc(text: str) -> Timestamps | None:
    """Presentation times from framecrc output: a ``#tb 0: NUM/DEN`` time base, then one
    ``stream, dts, pts, duration, size, crc[, F=flags]`` line per packet; packets an edit
    list discards (flag DISCARD_FLAG) are not shown and are left out."""
    base, stamps = None, []
    for line in text.splitlines():
        if line.startswith("#tb 0:"):
            base = Fraction(line.split(":", 1)[1].strip())
        elif line and not line.startswith("#"):
            fields = [f.strip() for f in line.split(",")]
            if len(fields) < 3 or not fields[2].lstrip("-").isdigit():
                return None  # a packet without a timestamp
            flags = [f for f in fields[6:] if f.startswith("F=")]
            if flags and int(flags[0][2:], 16) & DISCARD_FLAG:
                continue
            stamps.append(int(fields[2]))
    if base is None or not stamps:
        return None
    return Timestamps(np.sort(np.asarray(stamps, dtype=np.float64)) * float(base), float(base))


def even_frames(stamps: Timestamps) -> tuple[np.ndarray, float] | None:
    """(index of the frame shown nearest each instant of an even grid, the grid's rate in
    frames per second: ``Timestamps.rate``) for frames shown at ``stamps``; None when the
    intervals are even already (all regular) or too few to tell."""
    times = stamps.times
    if len(times) < 3:
        return None
    if not np.median(np.diff(times)) > 0 or stamps.regular().all():
        return None
    rate = stamps.rate()
    steps = int(np.floor((times[-1] - times[0]) * rate + 0.5))
    grid = times[0] + np.arange(steps + 1) / rate
    after = np.clip(np.searchsorted(times, grid), 1, len(times) - 1)
    nearer_before = grid - times[after - 1] <= times[after] - grid
    return np.where(nearer_before, after - 1, after), rate


def describe(stamps: Timestamps, picks: np.ndarray) -> str:
    """A log line's worth on an uneven clip and what resampling did to it."""
    times = stamps.times
    intervals = np.diff(times) * 1000.0
    used = np.bincount(picks, minlength=len(times))
    return (
        f"frame intervals {intervals.min():.1f}-{intervals.max():.1f} ms (median "
        f"{np.median(intervals):.1f}): {int((used > 1).sum())} frames shown more than once, "
        f"{int((used == 0).sum())} left out"
    )
