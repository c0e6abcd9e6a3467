"""Cameras evenly spaced on the upper hemisphere around the table (paper, section 4.1).

Directions follow a Fibonacci (golden-angle) spiral over the band of elevations
[ELEVATION_MIN, ELEVATION_MAX]: equal steps in z = sin(elevation) cut the band into equal-area
strips (Archimedes), and the golden-angle azimuth spreads consecutive cameras as far apart as
possible, so any number of cameras covers the band evenly. Very low views (grazing the table)
and the zenith (where "up" in the image is undefined) are left out.
"""

from __future__ import annotations

import math

import numpy as np

from mosiv_framework.scene.cameras import Camera

ELEVATION_MIN = math.radians(12.0)
ELEVATION_MAX = math.radians(70.0)
LOOK_AT = (0.0, 0.0, 0.15)  # m: the middle of the action, between table and collision point
DISTANCE = 1.15  # m from LOOK_AT
# horizontal field of view: ~0.95 m wide at the look-at point, enough for launches up to
# ~0.35 m from the centre and heights up to ~0.45 m from every view
FOV_DEG = 45.0
_GOLDEN_ANGLE = math.pi * (3.0 - math.sqrt(5.0))


def hemisphere_directions(n: int, *, azimuth0: float = 0.0) -> np.ndarray:
    """[n, 3] unit vectors from the look-at point towards the cameras (z > 0)."""
    z0, z1 = math.sin(ELEVATION_MIN), math.sin(ELEVATION_MAX)
    i = np.arange(n) + 0.5
    z = z1 - (z1 - z0) * i / n  # equal-area strips of the band
    azimuth = azimuth0 + _GOLDEN_ANGLE * np.arange(n)
    r = np.sqrt(1.0 - z * z)
    return np.stack([r * np.cos(azimuth), r * np.sin(azimuth), z], axis=1)


def hemisphere_cameras(
    n: int,
    *,
    resolution: int,
    azimuth0: float = 0.0,
    distance: float = DISTANCE,
    look_at=LOOK_AT,
    fov_deg: float = FOV_DEG,
) -> list[Camera]:
    """``n`` square cameras (``resolution`` pixels) at ``distance`` m from ``look_at``, on the
    upper hemisphere, each looking at ``look_at`` with world z up in the image."""
    target = np.asarray(look_at, dtype=np.float64)
    return [
        Camera.look_at(
            target + distance * d,
            target,
            (0.0, 0.0, 1.0),
            id=f"cam_{i:02d}",
            width=resolution,
            height=resolution,
            fov_deg=fov_deg,
        )
        for i, d in enumerate(hemisphere_directions(n, azimuth0=azimuth0))
    ]
