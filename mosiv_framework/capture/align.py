"""From the recording's world (its units, its up axis) to the scene's: metres, z up, ground
at z = 0.

A recording point ``p`` lands at ``scale * Q p + offset`` in the scene, with ``scale`` the
metres per recording unit, ``Q`` the smallest rotation taking the recording's up direction to +z,
and ``offset`` = (0, 0, -ground height) once the ground is known. A world-to-camera ``[R | t]``
(recording units) becomes ``[R Q^T | scale t - R Q^T offset]`` (metres): the same projection.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field

import numpy as np

from mosiv_framework.capture.common import CaptureError, SourceCamera
from mosiv_framework.capture.options import AXES, METRES_PER_UNIT
from mosiv_framework.capture.rotations import rotation_to_z
from mosiv_framework.scene.cameras import Camera


def parse_units(text: str | None) -> float:
    """Metres per recording unit from ``m``, ``cm``, ... or a positive number; default m."""
    if text is None:
        return 1.0
    key = str(text).strip().lower()
    if key in METRES_PER_UNIT:
        return METRES_PER_UNIT[key]
    try:
        value = float(key)
    except ValueError:
        value = -1.0
    if not (value > 0 and np.isfinite(value)):
        raise CaptureError(
            f"--units {text!r}: give one of {', '.join(METRES_PER_UNIT)} or the metres per "
            "unit as a positive number"
        )
    return value


def parse_up(text: str | None) -> np.ndarray | None:
    """The recording's up direction from ``x``, ``y``, ``z`` (optionally signed, ``-y``) or
    ``a,b,c``; None when not given (inferred from the cameras)."""
    if text is None:
        return None
    t = str(text).strip().lower()
    m = re.fullmatch(r"([+-]?)([xyz])", t)
    if m:
        v = np.zeros(3)
        v[AXES[m.group(2)]] = -1.0 if m.group(1) == "-" else 1.0
        return v
    try:
        v = np.array([float(p) for p in t.split(",")])
    except ValueError:
        v = np.zeros(0)
    if v.shape != (3,) or not np.all(np.isfinite(v)) or np.linalg.norm(v) < 1e-9:
        raise CaptureError(f"--up {text!r}: give x, y, z, -x, -y, -z or a vector a,b,c")
    return v / np.linalg.norm(v)


def cameras_up(cameras: list[SourceCamera]) -> np.ndarray:
    """The average of the cameras' up directions (minus their image y axis), normalised."""
    ups = np.stack([-c.rotation[1] for c in cameras])
    mean = ups.mean(axis=0)
    if np.linalg.norm(mean) < 0.3:  # cameras rolled every which way: no common up
        raise CaptureError(
            "cannot infer the up direction: the cameras' up vectors disagree; give --up"
        )
    return mean / np.linalg.norm(mean)


def parse_ground(text: str | None) -> tuple[int, float] | str | None:
    """``AXIS=VALUE`` (the plane where the recording's coordinate AXIS equals VALUE, in
    recording units) -> (axis index, value); ``none`` -> "none" (no ground); None: fit it."""
    if text is None:
        return None
    t = str(text).strip().lower()
    if t == "none":
        return "none"
    m = re.fullmatch(r"([xyz])\s*=\s*(.+)", t)
    try:
        value = float(m.group(2)) if m else float("nan")
    except ValueError:
        value = float("nan")
    if not m or not np.isfinite(value):
        raise CaptureError(
            f"--ground {text!r}: give AXIS=VALUE in the recording's coordinates and units "
            "(e.g. y=0 for a y-up recording), or none"
        )
    return AXES[m.group(1)], value


@dataclass
class Alignment:
    """scene point = scale * rotation @ recording point + offset (metres, z up)."""

    scale: float
    rotation: np.ndarray
    offset: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def points(self, p: np.ndarray) -> np.ndarray:
        return self.scale * np.asarray(p) @ self.rotation.T + self.offset

    def world_to_camera(self, w2c: np.ndarray) -> np.ndarray:
        out = np.eye(4)
        r = w2c[:3, :3] @ self.rotation.T
        out[:3, :3] = r
        out[:3, 3] = self.scale * w2c[:3, 3] - r @ self.offset
        return out

    def camera(self, cam: SourceCamera) -> Camera:
        k = cam.intrinsics
        return Camera(
            id=cam.id, width=k.width, height=k.height, fx=k.fx, fy=k.fy, cx=k.cx, cy=k.cy,
            world_to_camera=self.world_to_camera(cam.world_to_camera),
        )  # fmt: skip

    def as_dict(self) -> dict:
        return {
            "scale": self.scale,
            "rotation": self.rotation.tolist(),
            "offset": self.offset.tolist(),
        }


def ground_height_given(ground: tuple[int, float], align: Alignment, up: np.ndarray) -> float:
    """Height (m, after scale and rotation, before the offset) of the plane ``axis = value``;
    CaptureError unless that plane is horizontal, i.e. ``axis`` is the up axis."""
    axis, value = ground
    normal = np.zeros(3)
    normal[axis] = 1.0
    if abs(float(normal @ up)) < 0.999:
        raise CaptureError(
            f"--ground {'xyz'[axis]}={value:g}: that plane is not horizontal for the up "
            f"direction {np.round(up, 3).tolist()}; name the up axis (or give --up)"
        )
    return float(align.points(normal * value)[2])


@dataclass(frozen=True)
class RigFrame:
    """A recording's world named by its ``units`` (a key of METRES_PER_UNIT) and ``up`` axis
    (``x``, ``y`` or ``z``): the frame ``mosiv data capture`` writes cameras in.

    A scene point p (m, z up) is at ``scale * M p`` in the rig's world, with ``scale`` the rig's
    units per metre and ``M`` the inverse of the import's rotation to z up (``up="y"``: x stays,
    y <- z, z <- -y, the usual y-up convention of graphics tools). Camera frames keep the OpenCV
    axes, so a world-to-camera ``[R | t]`` becomes ``[R M^T | scale t]``: the rotation sees the
    rig's axes, the translation is in the rig's units, and every projection is unchanged.
    """

    units: str = "m"
    up: str = "z"

    def __post_init__(self) -> None:
        if self.units not in METRES_PER_UNIT:
            raise ValueError(f"units {self.units!r}: choose one of {sorted(METRES_PER_UNIT)}")
        if self.up not in AXES:
            raise ValueError(f"up axis {self.up!r}: choose one of {sorted(AXES)}")

    @property
    def scale(self) -> float:
        """Rig units per metre."""
        return 1.0 / METRES_PER_UNIT[self.units]

    @property
    def rotation(self) -> np.ndarray:
        """M: scene axes (z up) -> rig axes."""
        return rotation_to_z(parse_up(self.up)).T

    def world_to_camera(self, scene_w2c: np.ndarray) -> np.ndarray:
        """A scene world-to-camera 4x4 (m, z up) -> the rig's (its units, its up axis)."""
        out = np.eye(4)
        out[:3, :3] = np.asarray(scene_w2c)[:3, :3] @ self.rotation.T
        out[:3, 3] = self.scale * np.asarray(scene_w2c)[:3, 3]
        return out

    def scene_world_to_camera(self, rig_w2c: np.ndarray) -> np.ndarray:
        """The inverse of ``world_to_camera``: a rig world-to-camera back in scene metres, z up."""
        return Alignment(1.0 / self.scale, self.rotation.T).world_to_camera(np.asarray(rig_w2c))
