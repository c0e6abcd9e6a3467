"""The recording protocol of the paper's benchmark (section 4.1), shared by every scene source
(mosiv-synth, mosiv-genesis, third-party generators): cameras on the upper hemisphere, the
ballistic aim that makes objects meet in mid-air, and the checks of a clip's options.

Camera directions follow a Fibonacci (golden-angle) spiral over the band of elevations
[ELEVATION_MIN, ELEVATION_MAX]: equal steps in z = sin(elevation) cut the band into equal-area
strips (Archimedes), and the golden-angle azimuth spreads consecutive cameras as far apart as
possible, so any number of cameras covers the band evenly. Very low views (grazing the table)
and the zenith (where "up" in the image is undefined) are left out.
"""

from __future__ import annotations

import math
from typing import Any

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


def launch_velocity(start, target, t: float, acceleration) -> np.ndarray:
    """v0 [3] (m/s) with start + v0 t + a t^2 / 2 = target: the ballistic aim under a constant
    acceleration a (gravity plus any concealed steady force) that reaches ``target`` at t (s)."""
    a = np.asarray(acceleration, dtype=np.float64)
    return (np.asarray(target) - np.asarray(start) - 0.5 * a * t * t) / t


def name_list(value: Any, what: str, valid: tuple[str, ...], problems: list[str]) -> list[str]:
    """``"random"``/None -> [], ``"a,b"`` or ``["a", "b"]`` -> ["a", "b"], each checked
    against ``valid`` (unknown names are appended to ``problems``)."""
    if value is None or value == "random":
        return []
    items = value.split(",") if isinstance(value, str) else list(value)
    names = [str(v).strip() for v in items if str(v).strip()]
    problems += [
        f"{what}: unknown name {n!r}; valid: random or {', '.join(valid)}"
        for n in names
        if n not in valid
    ]
    return names


def check_clip(
    *,
    n_objects: int,
    per_object: dict[str, list[str]],
    resolution: int,
    n_cameras: int,
    n_frames: int,
    observed_frames: int,
    problems: list[str],
) -> None:
    """The protocol's limits on a clip, each violation appended to ``problems``: 2 or 3 objects,
    one name per object in each list of ``per_object`` (or none: random), at least 16 pixels,
    one camera and two frames, observed frames within the clip."""
    if n_objects not in (2, 3):
        problems.append(f"n_objects={n_objects!r}: the protocol uses 2 or 3 objects")
    for what, names in per_object.items():
        if names and len(names) != n_objects:
            problems.append(
                f"{what}: {len(names)} names given for n_objects={n_objects}; "
                "give one per object or 'random'"
            )
    if resolution < 16:
        problems.append(f"resolution={resolution}: must be at least 16 pixels")
    if n_cameras < 1:
        problems.append(f"n_cameras={n_cameras}: must be at least 1")
    if n_frames < 2:
        problems.append(f"n_frames={n_frames}: must be at least 2")
    if not 1 <= observed_frames <= n_frames:
        problems.append(f"observed_frames={observed_frames}: must lie in 1..n_frames={n_frames}")
