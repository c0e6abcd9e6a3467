"""When a video's frames were taken, and an even-rate sequence made from an uneven one.

Simulation steps frames at one rate (docs/SCENE_FORMAT.md: ``fps``), so an import must hand it
evenly spaced frames. Phones and many action cameras record at a variable frame rate: under
load or in low light the encoder drops or stretches frames, and the container's timestamps
say so while the frame count does not. Read back to back, such a clip runs fast after each gap,
and every velocity identified from it is wrong there.

``presentation_times`` reads the timestamps of the video's packets with ffmpeg's ``framecrc``
muxer (stream copy: nothing is decoded), and ``even_frames`` picks, for each instant of an even
grid at the clip's median interval, the frame shown nearest to it: a gap repeats the frame
before or after it, a burst drops frames. A clip whose intervals all lie within
``UNEVEN_TOLERANCE`` of their median is left as it is.
"""

from __future__ import annotations

import logging
import subprocess
from fractions import Fraction
from pathlib import Path

import numpy as np

logger = logging.getLogger(__name__)

#: a clip is uneven when some frame interval strays more than this fraction from the median
UNEVEN_TOLERANCE = 0.25


def presentation_times(path: Path) -> np.ndarray | None:
    """Seconds at which the first video stream's frames are shown, in presentation order, or
    None where ffmpeg gives no timestamps (a stream without them, or a file it cannot read:
    decoding then reports the file)."""
    import imageio_ffmpeg

    command = [imageio_ffmpeg.get_ffmpeg_exe(), "-v", "error", "-i", str(path)]
    command += ["-map", "0:v:0", "-c", "copy", "-f", "framecrc", "-"]
    done = subprocess.run(command, capture_output=True, text=True)
    if done.returncode != 0:
        return None
    return parse_framecrc(done.stdout)


def parse_framecrc(text: str) -> np.ndarray | None:
    """Presentation times (s, sorted) from framecrc output: a ``#tb 0: NUM/DEN`` time base,
    then one ``stream, dts, pts, duration, size, crc`` line per packet."""
    base, stamps = None, []
    for line in text.splitlines():
        if line.startswith("#tb 0:"):
            base = Fraction(line.split(":", 1)[1].strip())
        elif line and not line.startswith("#"):
            fields = [f.strip() for f in line.split(",")]
            if len(fields) < 3 or not fields[2].lstrip("-").isdigit():
                return None  # a packet without a timestamp
            stamps.append(int(fields[2]))
    if base is None or not stamps:
        return None
    return np.sort(np.asarray(stamps, dtype=np.float64)) * float(base)


def even_frames(times: np.ndarray) -> tuple[np.ndarray, float] | None:
    """(index of the frame shown nearest each instant of an even grid, the grid's rate in
    frames per second) for frames shown at ``times`` (s, sorted); None when the intervals are
    even already (within ``UNEVEN_TOLERANCE`` of their median) or too few to tell."""
    if len(times) < 3:
        return None
    intervals = np.diff(times)
    median = float(np.median(intervals))
    if not median > 0 or np.all(np.abs(intervals - median) <= UNEVEN_TOLERANCE * median):
        return None
    steps = int(np.floor((times[-1] - times[0]) / median + 0.5))
    grid = times[0] + median * np.arange(steps + 1)
    after = np.clip(np.searchsorted(times, grid), 1, len(times) - 1)
    nearer_before = grid - times[after - 1] <= times[after] - grid
    return np.where(nearer_before, after - 1, after), 1.0 / median


def describe(times: np.ndarray, picks: np.ndarray) -> str:
    """A log line's worth on an uneven clip and what resampling did to it."""
    intervals = np.diff(times) * 1000.0
    used = np.bincount(picks, minlength=len(times))
    return (
        f"frame intervals {intervals.min():.1f}-{intervals.max():.1f} ms (median "
        f"{np.median(intervals):.1f}): {int((used > 1).sum())} frames shown more than once, "
        f"{int((used == 0).sum())} left out"
    )
