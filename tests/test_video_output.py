"""Videos of a run: GIF by default, MP4 (H.264 through imageio-ffmpeg) when the recipe asks."""

from __future__ import annotations

import imageio.v3 as iio
import numpy as np
import pytest

from mosiv_framework.errors import ConfigError
from mosiv_framework.pipeline.video import write_video
from mosiv_framework.recipes import load_recipe

QUICKSTART = "recipes/quickstart.yaml"


def _frames(n: int = 6, size: int = 32) -> list[np.ndarray]:
    # a bright square moving across a dark frame: a codec that dropped or reordered frames
    # would move it elsewhere
    frames = []
    for t in range(n):
        image = np.full((size, size, 3), 20, dtype=np.uint8)
        image[8:16, 4 * t : 4 * t + 8] = 230
        frames.append(image)
    return frames


@pytest.mark.parametrize("suffix", ["gif", "mp4"])
def test_a_video_keeps_its_frames_in_order(tmp_path, suffix):
    frames = _frames()
    path = write_video(frames, tmp_path / f"clip.{suffix}", fps=12)
    decoded = iio.imread(path)
    assert decoded.shape[0] == len(frames)
    for t, original in enumerate(frames):
        # where the square is in each decoded frame (lossy H.264: compare its column, not pixels)
        bright = decoded[t, ..., :3].mean(axis=-1) > 128
        columns = np.nonzero(bright.any(axis=0))[0]
        assert abs(columns.mean() - (4 * t + 3.5)) < 1.0, (suffix, t)
        assert original.shape == decoded[t, ..., :3].shape


def test_an_unknown_video_suffix_is_named(tmp_path):
    with pytest.raises(ConfigError, match=r"clip\.avi.*\.gif or \.mp4"):
        write_video(_frames(), tmp_path / "clip.avi", fps=12)


def test_the_recipe_chooses_the_video_format():
    assert load_recipe(QUICKSTART, []).evaluate.video_format == "gif"
    assert load_recipe(QUICKSTART, ["evaluate.video_format=mp4"]).evaluate.video_format == "mp4"
    with pytest.raises(ConfigError, match=r"evaluate.video_format='avi': must be one of gif, mp4"):
        load_recipe(QUICKSTART, ["evaluate.video_format=avi"])
