"""Per-camera time offsets from the cameras' own sound (``--offsets audio``).

Cameras of a rig without a common clock still hear the same room: a clap, a slate, the impact
itself. Each camera's sound is decoded by ffmpeg onto its container's timeline (resampled to
``AUDIO_RATE``, silence padded where the audio starts after the video), so that sample ``s`` is
heard ``s / AUDIO_RATE - v0`` seconds after the camera's first video frame (shown at ``v0``).
Each camera's envelope is cross-correlated with the first camera's; the lag of the peak is how
much later the same sound comes in that camera's video, i.e. how much earlier it started::

    envelope = smooth(|x - x_prev|)            (transients; the microphones' gain and polarity
                                                drop out)
    lag_c = argmax_l sum_t env_c(t + l) env_ref(t)
    frames to drop_c = round((lag_c - min lag) * fps)

A lag is kept only where its peak stands ``MIN_PEAK_RATIO`` times above the correlation's
other peaks (further than ``PEAK_EXCLUSION_S`` from it): noise alone, or sounds that repeat
(a metronome), give no clear peak and are refused with the camera named.
"""

from __future__ import annotations

import subprocess
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mosiv_framework.capture.common import CaptureError

#: samples per second the sound is compared at (a millisecond is 8 samples: far below a frame)
AUDIO_RATE = 8000
#: the envelope's smoothing window (s): keeps a clap's onset, drops the waveform's phase
SMOOTHING_S = 0.002
#: the correlation's peak over its highest value further than PEAK_EXCLUSION_S from it, at least
#: (noise alone gives 1.0-1.4; a clap heard by two cameras, hundreds)
MIN_PEAK_RATIO = 2.0
PEAK_EXCLUSION_S = 0.05


@dataclass(frozen=True)
class AudioOffsets:
    """Frames to drop per camera, the sub-frame remainder of each (frames, in -0.5..0.5) and
    the peak ratio each lag was found with."""

    frames: dict[str, int]
    remainders: dict[str, float]
    peak_ratios: dict[str, float]


def read_sound(path: Path) -> np.ndarray | None:
    """Mono samples (float32, AUDIO_RATE a second) of a video's first audio stream on its
    container's timeline (sample 0 at time 0), or None where it has no audio stream."""
    import imageio_ffmpeg

    command = [imageio_ffmpeg.get_ffmpeg_exe(), "-v", "error", "-i", str(path), "-map", "0:a:0"]
    command += ["-af", "aresample=async=1:first_pts=0", "-ac", "1", "-ar", str(AUDIO_RATE)]
    done = subprocess.run([*command, "-f", "f32le", "-"], capture_output=True)
    if done.returncode != 0 or not done.stdout:
        return None
    return np.frombuffer(done.stdout, dtype=np.float32)


def envelope(sound: np.ndarray) -> np.ndarray:
    """The sound's transient envelope: |first difference| smoothed over SMOOTHING_S, scaled to
    unit mean (the microphones' gains differ)."""
    change = np.abs(np.diff(sound.astype(np.float64), prepend=float(sound[0]) if sound.size else 0))
    width = max(1, round(SMOOTHING_S * AUDIO_RATE))
    smooth = np.convolve(change, np.ones(width) / width, mode="same")
    mean = float(smooth.mean()) if smooth.size else 0.0
    return smooth / mean if mean > 0 else smooth


def lag_of(sound: np.ndarray, reference: np.ndarray) -> tuple[float, float]:
    """(seconds by which ``sound`` hears what ``reference`` hears later, the peak ratio)."""
    from scipy.signal import correlate, correlation_lags

    a, b = envelope(sound), envelope(reference)
    a, b = a - a.mean(), b - b.mean()
    corr = correlate(a, b, mode="full", method="fft")
    lags = correlation_lags(len(a), len(b), mode="full")
    best = int(np.argmax(corr))
    away = np.abs(lags - lags[best]) > PEAK_EXCLUSION_S * AUDIO_RATE
    other = float(corr[away].max()) if away.any() else 0.0
    ratio = float(corr[best]) / other if other > 0 else float("inf")
    return float(lags[best]) / AUDIO_RATE, ratio


def estimate_audio_offsets(
    sources: Mapping[str, Path], fps: float, first_frame_s: Mapping[str, float] | None = None
) -> AudioOffsets:
    """Frames each camera's video drops so that its frame i shows the instant the others'
    frame i shows, from the sound of each video in ``sources`` (camera id -> file); ``fps``:
    the frames' rate as read; ``first_frame_s``: when each camera's first frame is shown on
    its container's timeline (default 0). CaptureError naming a camera without sound or whose
    sound does not match the first camera's."""
    first_frame_s = first_frame_s or {}
    sounds = {}
    for cam, path in sorted(sources.items()):
        sound = read_sound(path) if path.is_file() else None
        if sound is None or not np.any(sound):
            raise CaptureError(
                f"--offsets audio: camera {cam!r} ({path}) has no sound to synchronise by; give "
                "--offsets CAM:N,... or let the import estimate them from motion onset"
            )
        sounds[cam] = sound
    reference = next(iter(sounds))
    delays, ratios = {reference: 0.0}, {reference: float("inf")}
    for cam, sound in sounds.items():
        if cam == reference:
            continue
        lag, ratio = lag_of(sound, sounds[reference])
        if not ratio >= MIN_PEAK_RATIO:
            raise CaptureError(
                f"--offsets audio: the sound of camera {cam!r} ({sources[cam]}) does not match "
                f"that of {reference!r}: the best match stands only {ratio:.2f}x above the next "
                f"(at least {MIN_PEAK_RATIO:g} needed); record a clap heard by every camera, or "
                "give --offsets"
            )
        # the same sound comes `lag` s later in this camera's audio, so its first frame was
        # shown that much earlier, less the difference in when each first frame is shown
        delays[cam] = lag - first_frame_s.get(cam, 0.0) + first_frame_s.get(reference, 0.0)
        ratios[cam] = ratio
    first = min(delays.values())
    exact = {cam: (d - first) * fps for cam, d in delays.items()}
    frames = {cam: int(round(x)) for cam, x in exact.items()}
    remainders = {cam: exact[cam] - frames[cam] for cam in exact}
    return AudioOffsets(frames, remainders, ratios)
