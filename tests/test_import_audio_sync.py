"""Time offsets from the cameras' sound (``mosiv data import --offsets audio``): a clap heard by
every camera of a rig without a common clock gives the frames each camera drops."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from mosiv_framework.capture import CaptureError, import_recording
from mosiv_framework.capture.audio_sync import MIN_PEAK_RATIO, estimate_audio_offsets, lag_of
from mosiv_framework.capture.importer import _audio_offsets

imageio_ffmpeg = pytest.importorskip("imageio_ffmpeg")

HERE = Path(__file__).resolve().parent
if str(HERE) not in sys.path:
    sys.path.insert(0, str(HERE))
from capture_fakes import (  # noqa: E402
    LATE,
    N_FRAMES,
    render_spheres,
    settings,
    sphere_paths,
    write_capture,
)

FPS = 24.0


def clap(at: float, seed: int) -> str:
    """An ffmpeg audio source: faint room noise, and a 30 ms clap (a decaying noise burst) at
    ``at`` seconds; each seed its own noise, as each microphone hears its own."""
    burst = f"if(between(t,{at},{at}+0.03),(random({seed + 7})-0.5)*exp(-(t-{at})*80),0)"
    return f"aevalsrc='0.01*(random({seed})-0.5)+{burst}':s=16000"


def with_sound(video: Path | None, out: Path, sound: str, seconds: float, shift: float = 0.0):
    """``video`` (or a plain grey clip) with ``sound`` as its audio track, the audio starting
    ``shift`` s after the video."""
    exe = imageio_ffmpeg.get_ffmpeg_exe()
    if video is None:
        command = [exe, "-y", "-v", "error", "-f", "lavfi", "-i", "color=size=32x24:rate=24"]
    else:
        command = [exe, "-y", "-v", "error", "-i", str(video)]
    command += ["-itsoffset", str(shift)] if shift else []
    command += ["-f", "lavfi", "-t", str(seconds), "-i", sound, "-map", "0:v:0", "-map", "1:a:0"]
    video_codec = ["-c:v", "libx264"] if video is None else ["-c:v", "copy"]
    subprocess.run(
        [*command, *video_codec, "-c:a", "aac", "-t", str(seconds), str(out)], check=True
    )
    return out


def test_offsets_from_a_clap_with_audio_that_starts_late(tmp_path):
    """cam_01 hears the clap 3 frames later into its video than cam_00 (it started 3 frames
    earlier), cam_02 7.24 frames later (rounded to 7, remainder 0.24); cam_03's audio track
    starts 0.1 s after its video and holds the clap 0.1 s earlier: the same instant as
    cam_00's."""
    at = {"cam_00": 1.0, "cam_01": 1.0 + 3 / FPS, "cam_02": 1.0 + 7.24 / FPS, "cam_03": 0.9}
    shift = {"cam_03": 0.1}
    sources = {
        cam: with_sound(None, tmp_path / f"{cam}.mp4", clap(t, i), 3.0, shift.get(cam, 0.0))
        for i, (cam, t) in enumerate(at.items())
    }
    found = estimate_audio_offsets(sources, dict.fromkeys(sources, FPS))
    assert found.frames == {"cam_00": 0, "cam_01": 3, "cam_02": 7, "cam_03": 0}
    assert found.remainders["cam_02"] == pytest.approx(0.24, abs=0.05)
    assert all(abs(r) < 0.05 for c, r in found.remainders.items() if c != "cam_02")
    assert min(r for c, r in found.peak_ratios.items() if c != "cam_00") > 10


def test_sound_that_cannot_synchronise_is_refused_naming_the_camera(tmp_path):
    """Room noise without a clap gives no clear peak; a camera without an audio track has
    nothing to compare."""
    sources = {"cam_00": with_sound(None, tmp_path / "cam_00.mp4", clap(1.0, 1), 3.0)}
    noise = "aevalsrc='0.01*(random(5)-0.5)':s=16000"
    sources["cam_01"] = with_sound(None, tmp_path / "cam_01.mp4", noise, 3.0)
    with pytest.raises(CaptureError, match="sound of camera 'cam_01'.*does not match"):
        estimate_audio_offsets(sources, dict.fromkeys(sources, FPS))
    silent = tmp_path / "silent"
    silent.mkdir()
    exe = imageio_ffmpeg.get_ffmpeg_exe()
    command = [exe, "-y", "-v", "error", "-f", "lavfi", "-i", "color=size=32x24:rate=24:d=1"]
    subprocess.run([*command, str(silent / "cam_01.mp4")], check=True)
    sources["cam_01"] = silent / "cam_01.mp4"
    with pytest.raises(CaptureError, match="camera 'cam_01' .* has no sound"):
        estimate_audio_offsets(sources, dict.fromkeys(sources, FPS))


def reverberant(at: float, seconds: float, rt60: float, seed: int) -> np.ndarray:
    """A clap at ``at`` s in a room that rings for ``rt60`` s (its tail: noise decaying by
    60 dB over rt60), over faint room noise, at the decoder's rate."""
    rate = 8000
    rng = np.random.default_rng(seed)
    sound = 0.005 * rng.standard_normal(int(seconds * rate))
    tail = np.arange(int(rt60 * rate)) / rate
    ring = rng.standard_normal(tail.size) * 10 ** (-3 * tail / rt60)
    start = int(at * rate)
    sound[start : start + ring.size] += ring[: sound.size - start]
    return sound.astype(np.float32)


def test_a_clap_in_a_ringing_room_is_found():
    """A second of reverberation (the clap's own tail, 50 ms and more from it) does not
    count as a rival peak: the onsets, not the loudness, are compared."""
    reference = reverberant(1.0, 4.0, 1.0, 1)
    sound = reverberant(1.3, 4.0, 1.0, 2)
    lag, ratio = lag_of(sound, reference)
    assert lag == pytest.approx(0.3, abs=2e-3) and ratio >= MIN_PEAK_RATIO


def test_lag_sign_by_hand():
    """A click 0.25 s later in ``sound`` than in ``reference``: lag +0.25 s."""
    rate = 8000
    reference, sound = np.zeros(rate), np.zeros(rate)
    reference[2000:2040] = np.hanning(40)
    sound[4000:4040] = np.hanning(40)
    lag, ratio = lag_of(sound.astype(np.float32), reference.astype(np.float32))
    assert lag == pytest.approx(0.25, abs=2e-3) and ratio > 10


def test_import_with_offsets_from_sound(tmp_path):
    """The rig capture of the import tests (cam_01 and cam_03 started 2 and 1 frames late)
    with a clap at one instant of the scene in every camera's audio: the import finds the same
    offsets that the motion onsets give (the earliest cameras drop what the late ones lack)."""
    scene = render_spheres(tmp_path / "scene", "slide", sphere_paths())
    capture = write_capture(scene, tmp_path / "capture")
    videos = capture / "videos"
    seconds, instant = N_FRAMES / FPS, 0.5  # the clap, in the scene's time
    for i, path in enumerate(sorted(videos.glob("*.mp4"))):
        heard = instant - LATE.get(path.stem, 0) / FPS  # into this camera's video
        silent = path.rename(path.with_suffix(".silent"))
        with_sound(silent, path, clap(heard, i), seconds)
        silent.unlink()
    out = import_recording(settings(capture, tmp_path / "s", offsets="audio", late_cameras="trim"))
    record = json.loads((out / "import.json").read_text())
    late_most = max(LATE.values())
    assert record["offsets"] == {c: late_most - LATE.get(c, 0) for c in record["offsets"]}
    assert record["offsets_from"] == "audio" and record["offsets_estimated"] is True
    assert all(abs(r) < 0.1 for r in record["offset_remainders_frames"].values())


def test_a_video_shown_late_in_its_container_and_a_clip_cut_without_re_encoding(tmp_path):
    """cam_01's video starts 0.2 s into its container and hears the clap 3 frames later after
    its first frame than cam_00: it drops 3. cam_02 was cut from a longer clip without
    re-encoding (its edit list hides the first 1.5 s, whose packets stay in the file) and hears
    the clap 1 s after its first shown frame, as cam_00 does: it drops none."""
    exe = imageio_ffmpeg.get_ffmpeg_exe()
    cam_00 = with_sound(None, tmp_path / "cam_00.mp4", clap(1.0, 1), 3.0)
    grey = tmp_path / "grey.mp4"
    subprocess.run([exe, "-y", "-v", "error", "-f", "lavfi", "-i", "color=size=32x24:rate=24:d=3",
                    "-c:v", "libx264", str(grey)], check=True)  # fmt: skip
    late = [
        exe,
        "-y",
        "-v",
        "error",
        "-itsoffset",
        "0.2",
        "-i",
        str(grey),
        "-f",
        "lavfi",
        "-t",
        "3.2",
    ]
    late += ["-i", clap(1.2 + 3 / FPS, 2), "-map", "0:v:0", "-map", "1:a:0", "-c:v", "copy"]
    subprocess.run([*late, "-c:a", "aac", str(tmp_path / "cam_01.mp4")], check=True)
    long = with_sound(None, tmp_path / "long.mp4", clap(2.5, 3), 4.0)
    cut = [exe, "-y", "-v", "error", "-ss", "1.5", "-i", str(long), "-c", "copy"]
    subprocess.run([*cut, str(tmp_path / "cam_02.mp4")], check=True)
    sources = {c: tmp_path / f"{c}.mp4" for c in ("cam_00", "cam_01", "cam_02")}
    frames, how, remainders = _audio_offsets(sources, dict.fromkeys(sources, 1))
    assert how == "audio" and frames == {"cam_00": 0, "cam_01": 3, "cam_02": 0}
    assert all(abs(r) < 0.1 for r in remainders.values())
    assert cam_00.exists()
