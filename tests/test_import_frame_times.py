"""Videos recorded at a variable frame rate (phones, action cameras): the import reads when
each frame was shown and hands the simulator frames at even times."""

from __future__ import annotations

import subprocess
from pathlib import Path

import numpy as np
import pytest

from mosiv_framework.capture.frame_times import (
    Timestamps,
    even_frames,
    parse_framecrc,
    presentation_times,
)
from mosiv_framework.capture.video import read_video

imageio_ffmpeg = pytest.importorskip("imageio_ffmpeg")

FPS, N, GAP_AT, GAP = 24, 20, 10, 2  # frames from GAP_AT on are shown GAP intervals late
#: grey level per frame: frame i is 10 i (H.264 at crf 0 keeps it to a level or two)
LEVEL = 10


def write_clip(path: Path, levels=None, fps: float = FPS) -> Path:
    """Grey frames of the given ``levels`` (default LEVEL * i for N frames) at ``fps``,
    constant rate, losslessly (crf 0)."""
    writer = imageio_ffmpeg.write_frames(
        str(path), (32, 32), fps=fps, codec="libx264", output_params=["-crf", "0"],
        macro_block_size=1,
    )  # fmt: skip
    writer.send(None)
    for level in [LEVEL * i for i in range(N)] if levels is None else levels:
        writer.send(np.full((32, 32, 3), level, dtype=np.uint8))
    writer.close()
    return path


@pytest.fixture(scope="module")
def clips(tmp_path_factory) -> dict[str, Path]:
    """An even clip and the same frames with a gap: frames GAP_AT.. shown GAP frames late (as a
    phone's encoder stretches a frame under load), their timestamps kept (passthrough)."""
    folder = tmp_path_factory.mktemp("clips")
    even = write_clip(folder / "even.mp4")
    late = f"setpts='(N+{GAP}*gte(N\\,{GAP_AT}))/({FPS}*TB)'"
    command = [imageio_ffmpeg.get_ffmpeg_exe(), "-y", "-v", "error", "-i", str(even)]
    command += ["-vf", late, "-fps_mode", "passthrough", "-c:v", "libx264", "-crf", "0"]
    subprocess.run([*command, str(folder / "uneven.mp4")], check=True)
    return {"even": even, "uneven": folder / "uneven.mp4"}


def levels(frames: np.ndarray) -> list[int]:
    """Which source frame each frame is (its grey level over LEVEL, rounded)."""
    return [round(float(f.mean()) / LEVEL) for f in frames]


def test_presentation_times_of_an_even_and_an_uneven_clip(clips):
    even = presentation_times(clips["even"])
    np.testing.assert_allclose(even.times, np.arange(N) / FPS, atol=1e-6)
    assert even.regular().all() and even.rate() == pytest.approx(FPS, rel=1e-6)
    uneven = presentation_times(clips["uneven"])
    shown = (np.arange(N) + GAP * (np.arange(N) >= GAP_AT)) / FPS
    np.testing.assert_allclose(uneven.times, shown, atol=1e-6)
    assert not uneven.regular().all() and uneven.rate() == pytest.approx(FPS, rel=1e-6)


def test_a_millisecond_time_base_is_not_a_variable_frame_rate(tmp_path):
    """Matroska keeps times in milliseconds: 300 fps comes out as intervals of 3 and 4 ms,
    30 fps as 33 and 34. Both are even clips, read frame for frame at their true rate."""
    for fps, n in ((300, 40), (30, 12)):
        path = write_clip(tmp_path / f"clip_{fps}.mkv", [5 * i for i in range(n)], fps)
        stamps = presentation_times(path)
        assert stamps.tick == pytest.approx(1e-3) and stamps.regular().all()
        assert even_frames(stamps) is None and stamps.rate() == pytest.approx(fps, rel=0.02)
        frames, _ = read_video(path)
        assert len(frames) == n


def test_frames_an_edit_list_hides_are_not_timestamps(tmp_path):
    """A clip cut without re-encoding keeps the packets before its cut, flagged discarded:
    the timestamps are those of the frames the decoder shows."""
    exe = imageio_ffmpeg.get_ffmpeg_exe()
    long = tmp_path / "long.mp4"
    make = [exe, "-y", "-v", "error", "-f", "lavfi", "-i", "color=size=32x24:rate=30:d=4"]
    subprocess.run([*make, "-c:v", "libx264", "-g", "60", str(long)], check=True)
    cut = tmp_path / "cut.mp4"
    subprocess.run([exe, "-y", "-v", "error", "-ss", "1.5", "-i", str(long), "-c", "copy", str(cut)],
                   check=True)  # fmt: skip
    frames, _ = read_video(cut)
    stamps = presentation_times(cut)
    assert len(stamps.times) == len(frames) < 120 and stamps.times[0] >= 0.0


def test_an_uneven_clip_is_resampled_to_even_times(clips):
    """The gap of GAP missing intervals is filled by the frame shown nearest each instant:
    frame 9 (at 9/24 s) for 10/24, frame 10 (shown at 12/24) for 11/24 and 12/24; the rate is
    the median interval's, not the container's average (which the gap lowers)."""
    frames, fps = read_video(clips["uneven"])
    expected = list(range(GAP_AT)) + [GAP_AT - 1, GAP_AT] + list(range(GAP_AT, N))
    assert levels(frames) == expected and fps == pytest.approx(FPS)
    every_other, _ = read_video(clips["uneven"], every=2)
    assert levels(every_other) == expected[::2]


def test_even_frames_by_hand():
    """A burst (two frames 10 ms apart in a 40 ms clip) drops one; a clip within the tolerance
    is left alone; fewer than three frames say nothing."""
    times = np.array([0.0, 0.04, 0.05, 0.08, 0.12, 0.16])
    picks, rate = even_frames(Timestamps(times, 1e-6))
    assert picks.tolist() == [0, 1, 3, 4, 5] and rate == pytest.approx(25.0)
    assert even_frames(Timestamps(np.array([0.0, 0.041, 0.08, 0.122]), 1e-6)) is None
    assert even_frames(Timestamps(np.array([0.0, 0.5]), 1e-6)) is None


def test_framecrc_without_timestamps_or_time_base_gives_none():
    header = "#tb 0: 1/12288\n"
    stamps = parse_framecrc(header + "0, 0, 0, 512, 570, 0x1\n0, 512, 512, 512, 55, 0x2, F=0x0\n")
    assert stamps.times.tolist() == pytest.approx([0.0, 512 / 12288])
    assert stamps.tick == pytest.approx(1 / 12288)
    hidden = parse_framecrc(header + "0, -512, -512, 512, 9, 0x1, F=0x5\n0, 0, 0, 512, 9, 0x2\n")
    assert hidden.times.tolist() == [0.0]  # the discarded packet (flag 0x4) is not shown
    assert parse_framecrc(header + "0, 0, NOPTS, 512, 570, 0x1\n") is None
    assert parse_framecrc("0, 0, 0, 512, 570, 0x1\n") is None


def test_a_camera_at_twice_the_rate_keeps_every_second_frame(tmp_path):
    """A 48 fps camera beside a 24 fps one: rate_steps gives it 2, and read so its frames show
    the 24 fps camera's instants (grey level 10 x the time in 24ths of a second)."""
    from mosiv_framework.capture.video import rate_steps

    fast = write_clip(tmp_path / "fast.mp4", [LEVEL * j // 2 for j in range(2 * N)], 2 * FPS)
    slow = write_clip(tmp_path / "slow.mp4")
    steps = rate_steps({"slow": slow, "fast": fast, "folder": tmp_path})
    assert steps == {"slow": 1, "fast": 2, "folder": 1}
    frames, fps = read_video(fast, every=steps["fast"])
    assert levels(frames) == list(range(N)) and fps / 2 == pytest.approx(FPS)


def test_import_of_a_rig_with_a_camera_at_twice_the_rate(tmp_path):
    """The import tests' rig with cam_02 re-recorded at 48 fps (each frame shown twice): the
    import keeps every second frame of it, so all cameras agree on the frames and the rate."""
    import json
    import sys

    here = Path(__file__).resolve().parent
    if str(here) not in sys.path:
        sys.path.insert(0, str(here))
    from capture_fakes import render_spheres, settings, sphere_paths, write_capture

    from mosiv_framework.capture import import_recording
    from mosiv_framework.scene import read_scene

    scene = render_spheres(tmp_path / "scene", "slide", sphere_paths())
    capture = write_capture(scene, tmp_path / "capture", late={})
    video = capture / "videos" / "cam_02.mp4"
    slow = video.rename(video.with_suffix(".slow"))
    command = [imageio_ffmpeg.get_ffmpeg_exe(), "-y", "-v", "error", "-i", str(slow)]
    command += ["-vf", f"fps={2 * FPS}", "-c:v", "libx264", "-crf", "10", "-f", "mp4", str(video)]
    subprocess.run(command, check=True)
    slow.unlink()
    out = import_recording(settings(capture, tmp_path / "s", offsets="none"))
    got, original = read_scene(out), read_scene(scene)
    assert got.fps == pytest.approx(FPS) and got.n_frames == original.n_frames
    assert json.loads((out / "import.json").read_text())["offsets"]["cam_02"] == 0
    for t in (0, original.n_frames // 2, original.n_frames - 1):  # the same instants
        diff = np.abs(got.rgb("cam_02", t).astype(float) - original.rgb("cam_02", t)).mean()
        assert diff < 3.0, (t, diff)
