"""The benchmark protocol shared by scene sources: cameras, ballistic aim, clip option checks."""

from __future__ import annotations

import numpy as np
import pytest

from mosiv_framework.scene.protocol import (
    ELEVATION_MAX,
    ELEVATION_MIN,
    check_clip,
    hemisphere_directions,
    launch_velocity,
    name_list,
)


def test_cameras_are_spread_over_the_upper_hemisphere():
    d = hemisphere_directions(11, azimuth0=0.3)
    assert np.allclose(np.linalg.norm(d, axis=1), 1.0)
    elevation = np.arcsin(d[:, 2])
    assert np.all(elevation >= ELEVATION_MIN) and np.all(elevation <= ELEVATION_MAX)
    # no two cameras closer than 25 degrees: evenly spread, not clustered
    cos = d @ d.T - 2 * np.eye(11)
    assert np.degrees(np.arccos(cos.max())) > 25.0


@pytest.mark.parametrize("acceleration", [(0.0, 0.0, -9.8), (1.5, 0.0, -12.0)])
def test_launch_velocity_reaches_the_target_on_time(acceleration):
    a = np.array(acceleration)
    start, target, t = np.array([0.1, -0.2, 0.3]), np.array([-0.05, 0.1, 0.25]), 0.2
    v0 = launch_velocity(start, target, t, a)
    assert np.allclose(start + v0 * t + 0.5 * a * t * t, target)


def test_clip_checks_name_every_problem():
    problems: list[str] = []
    names = name_list("egg,teapot", "shapes", ("egg", "pawn"), problems)
    check_clip(
        n_objects=4,
        per_object={"shapes": names},
        resolution=8,
        n_cameras=0,
        n_frames=1,
        observed_frames=3,
        problems=problems,
    )
    text = "\n".join(problems)
    for needle in ("'teapot'", "n_objects=4", "resolution=8", "n_cameras=0", "n_frames=1"):
        assert needle in text
    assert "observed_frames=3" in text
    assert name_list("random", "shapes", ("egg",), []) == []
