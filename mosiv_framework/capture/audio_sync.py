"""Per-camera time offsets from the cameras' own sound (``--offsets audio``).

Cameras of a rig without a common clock still hear the same room: a clap, a slate, the impact
itself. Each camera's sound is decoded by ffmpeg onto its container's timeline (resampled to
``AUDIO_RATE``, silence padded where the audio starts after the video), so that a sound at
sample ``s`` comes ``s / AUDIO_RATE - v0`` seconds after the camera's first shown frame (shown
at ``v0``). Each camera's onset envelope is cross-correlated with the first camera's (by name);
the lag of the peak, corrected for the cameras' ``v0``, is how much earlier that camera
started::

    amplitude = mean of |x| over 1 ms, then over the last 5 ms   (ENVELOPE_RATE a second)
    onset = max(0, amplitude - amplitude_prev)   (a clap's attack; its reverberation decays
                                                  and counts for nothing, and the microphones'
                                                  gains and polarity drop out)
    lag_c = argmax_l sum_t onset_c(t + l) onset_ref(t)
    delay_c = lag_c - v0_c + v0_ref
    frames to drop_c = round((delay_c - min delay) * read rate_c)

``read rate``: the frames per second of the camera's frames as read (its container's rate
over ``--every`` and the whole multiple of a faster camera), so offsets and their sub-frame
remainders are in frames as read. A lag is kept only where its peak stands ``MIN_PEAK_RATIO``
times above the correlation's next peak (peaks at least ``PEAK_EXCLUSION_S`` apart): noise
alone, or sounds that repeat (a metronome), give no clear peak and are refused with the camera
named.
"""

from __future__ import annotations

import subprocess
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mosiv_framework.capture.common import CaptureError

#: samples per second the sound is decoded at
AUDIO_RATE = 8000
#: samples per second of the onset envelope the cameras are compared by: a millisecond, far
#: below a frame (and a 30-minute clip is 1.8 million samples)
ENVELOPE_RATE = 1000
#: the amplitude's smoothing before its rises are taken (s): on a clap ringing for 1 s (RT60) the
#: peak ratio is 1.3 unsmoothed, 3.0 at 5 ms; room noise alone stays at 1.3 there (at 20 ms it
#: reaches 3.7, and noise would pass for a clap)
SMOOTHING_S = 0.005
#: the correlation's peak over its highest value further than PEAK_EXCLUSION_S from it, at least
#: (noise alone gives 1.0-1.4; a clap heard by two cameras, tens to hundreds)
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


def onset_envelope(sound: np.ndarray) -> np.ndarray:
    """The sound's onsets at ENVELOPE_RATE: the rises of its mean amplitude over each
    1 / ENVELOPE_RATE s, scaled to unit mean (the microphones' gains differ)."""
    block = AUDIO_RATE // ENVELOPE_RATE
    n = len(sound) // block
    amplitude = np.abs(sound[: n * block].astype(np.float64)).reshape(n, block).mean(axis=1)
    # a causal mean over SMOOTHING_S: a ringing tail then decays smoothly instead of rising
    # and falling with its noise (the same delay in every camera leaves the lag as it is)
    width = max(1, round(SMOOTHING_S * ENVELOPE_RATE))
    amplitude = np.convolve(amplitude, np.ones(width) / width, mode="full")[:n]
    onset = np.maximum(np.diff(amplitude, prepend=amplitude[:1]), 0.0)
    mean = float(onset.mean()) if onset.size else 0.0
    return onset / mean if mean > 0 else onset


def lag_of(sound: np.ndarray, reference: np.ndarray) -> tuple[float, float]:
    """(seconds by which ``sound`` hears what ``reference`` hears later, the peak ratio: the
    correlation's highest peak over its next, peaks PEAK_EXCLUSION_S apart at least)."""
    from scipy.signal import correlate, correlation_lags, find_peaks

    a, b = onset_envelope(sound), onset_envelope(reference)
    a, b = a - a.mean(), b - b.mean()
    corr = correlate(a, b, mode="full", method="fft")
    lags = correlation_lags(len(a), len(b), mode="full")
    peaks, _ = find_peaks(corr, distance=max(1, round(PEAK_EXCLUSION_S * ENVELOPE_RATE)))
    if peaks.size == 0:
        return 0.0, 0.0
    heights = np.sort(corr[peaks])[::-1]
    best = peaks[int(np.argmax(corr[peaks]))]
    other = float(heights[1]) if heights.size > 1 else 0.0
    ratio = float(corr[best]) / other if other > 0 else float("inf")
    return float(lags[best]) / ENVELOPE_RATE, ratio


def estimate_audio_offsets(
    sources: Mapping[str, Path],
    read_rates: Mapping[str, float],
    first_frame_s: Mapping[str, float] | None = None,
) -> AudioOffsets:
    """Frames each camera drops so that its frame i shows the instant the others' frame i
    shows, from the sound of each video in ``sources`` (camera id -> file); ``read_rates``:
    camera id -> frames as read per second of its container's time; ``first_frame_s``: when
    each camera's first frame is shown on its container's timeline (default 0). CaptureError
    naming a camera without sound (an image folder has none) or whose sound does not match the
    first camera's."""
    first_frame_s = first_frame_s or {}
    sounds = {}
    for cam, path in sorted(sources.items()):
        sound = read_sound(path) if path.is_file() else None
        if sound is None or not np.any(sound):
            raise CaptureError(
                f"--offsets audio: camera {cam!r} ({path}) has no sound to synchronise by (every "
                "camera must be a video with an audio track); give --offsets CAM:N,... or let "
                "the import estimate them from motion onset"
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
    exact = {cam: (d - first) * read_rates[cam] for cam, d in delays.items()}
    frames = {cam: int(round(x)) for cam, x in exact.items()}
    remainders = {cam: exact[cam] - frames[cam] for cam in exact}
    return AudioOffsets(frames, remainders, ratios)
