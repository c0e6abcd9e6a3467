"""Cameras of a scene as a COLMAP sparse text model, in a rig's units and up axis.

A ``mosiv-scene/1`` world is metres with z up. A capture rig's world is whatever its calibration
chose; ``RigFrame`` says how the two relate: a point p (scene, m) is at ``scale * M p`` in the
rig's world, with ``scale`` the rig's units per metre and ``M`` the rotation taking the scene's
z-up axes to the rig's (``up="y"``: x stays, y <- z, z <- -y, the usual y-up convention of
graphics tools). Camera frames keep the OpenCV axes COLMAP uses too, so a world-to-camera
``[R | t]`` becomes ``[R M^T | scale t]``: the rotation sees the rig's axes, the translation is in
the rig's units, and every projection is unchanged.

Files (COLMAP's text format, https://colmap.github.io/format.html):
``cameras.txt`` ``CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]`` with ``OPENCV`` (fx fy cx cy k1 k2 p1 p2)
or ``RADIAL`` (f cx cy k1 k2); ``images.txt`` two lines per image, ``IMAGE_ID QW QX QY QZ TX TY TZ
CAMERA_ID NAME`` (the world-to-camera rotation as a unit quaternion, w first, and translation)
and an empty line of 2D points; ``points3D.txt`` empty. COLMAP, like ``mosiv-scene/1``, puts the
centre of the top-left pixel at (0.5, 0.5), so cx and cy carry over unchanged.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mosiv_framework.capture_out.distortion import Distortion

#: rig length units per metre
UNITS_PER_METRE: dict[str, float] = {"m": 1.0, "dm": 10.0, "cm": 100.0, "mm": 1000.0}
#: rotation taking the scene's z-up axes to a rig's axes, by the rig's up axis
UP_ROTATIONS: dict[str, np.ndarray] = {
    "z": np.eye(3),
    "y": np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]]),
}
CAMERA_MODELS = ("OPENCV", "RADIAL")


@dataclass(frozen=True)
class RigFrame:
    """The rig's world: ``units`` (a key of UNITS_PER_METRE) and ``up`` (a key of UP_ROTATIONS)."""

    units: str = "m"
    up: str = "z"

    def __post_init__(self) -> None:
        if self.units not in UNITS_PER_METRE:
            raise ValueError(f"units {self.units!r}: choose one of {sorted(UNITS_PER_METRE)}")
        if self.up not in UP_ROTATIONS:
            raise ValueError(f"up axis {self.up!r}: choose one of {sorted(UP_ROTATIONS)}")

    @property
    def scale(self) -> float:
        return UNITS_PER_METRE[self.units]

    @property
    def rotation(self) -> np.ndarray:
        return UP_ROTATIONS[self.up]

    def world_to_camera(self, scene_w2c: np.ndarray) -> np.ndarray:
        """A scene world-to-camera 4x4 (m, z up) -> the rig's (its units, its up axis)."""
        out = np.eye(4)
        out[:3, :3] = np.asarray(scene_w2c)[:3, :3] @ self.rotation.T
        out[:3, 3] = self.scale * np.asarray(scene_w2c)[:3, 3]
        return out

    def scene_world_to_camera(self, rig_w2c: np.ndarray) -> np.ndarray:
        """The inverse of ``world_to_camera``: a rig world-to-camera back in scene metres, z up."""
        out = np.eye(4)
        out[:3, :3] = np.asarray(rig_w2c)[:3, :3] @ self.rotation
        out[:3, 3] = np.asarray(rig_w2c)[:3, 3] / self.scale
        return out


def rotation_to_quaternion(rot: np.ndarray) -> np.ndarray:
    """A rotation matrix -> unit quaternion (w, x, y, z) with w >= 0 (Shepperd's method: the
    largest of the four squared components is taken first, so no division by a small number)."""
    m = np.asarray(rot, dtype=np.float64)
    trace = np.trace(m)
    diag = np.diag(m)
    squares = np.array([1.0 + trace, *(1.0 + 2.0 * diag - trace)])  # 4 q_i^2 for w, x, y, z
    i = int(np.argmax(squares))
    q = np.empty(4)
    q[i] = 0.5 * np.sqrt(squares[i])
    s = 0.25 / q[i]
    if i == 0:
        q[1:] = s * np.array([m[2, 1] - m[1, 2], m[0, 2] - m[2, 0], m[1, 0] - m[0, 1]])
    elif i == 1:
        q[[0, 2, 3]] = s * np.array([m[2, 1] - m[1, 2], m[0, 1] + m[1, 0], m[0, 2] + m[2, 0]])
    elif i == 2:
        q[[0, 1, 3]] = s * np.array([m[0, 2] - m[2, 0], m[0, 1] + m[1, 0], m[1, 2] + m[2, 1]])
    else:
        q[[0, 1, 2]] = s * np.array([m[1, 0] - m[0, 1], m[0, 2] + m[2, 0], m[1, 2] + m[2, 1]])
    q /= np.linalg.norm(q)
    return q if q[0] >= 0 else -q


def quaternion_to_rotation(q: np.ndarray) -> np.ndarray:
    """A unit quaternion (w, x, y, z) -> its 3x3 rotation matrix."""
    w, x, y, z = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def camera_line(camera_id: int, camera, d: Distortion, model: str, size: tuple[int, int]) -> str:
    """One line of cameras.txt for a ``scene.cameras.Camera`` recorded at ``size`` (w, h)."""
    if model == "OPENCV":
        params = [camera.fx, camera.fy, camera.cx, camera.cy, d.k1, d.k2, d.p1, d.p2]
    elif model == "RADIAL":
        if abs(camera.fx - camera.fy) > 1e-9 * abs(camera.fx) or not d.radial_only:
            raise ValueError(
                f"camera {camera.id!r}: COLMAP's RADIAL model needs fx = fy and no tangential "
                f"terms (fx={camera.fx}, fy={camera.fy}, p1={d.p1}, p2={d.p2}); use OPENCV"
            )
        params = [camera.fx, camera.cx, camera.cy, d.k1, d.k2]
    else:
        raise ValueError(f"camera model {model!r}: choose one of {CAMERA_MODELS}")
    return f"{camera_id} {model} {size[0]} {size[1]} " + " ".join(repr(float(p)) for p in params)


def write_colmap_text(
    folder: Path,
    cameras: list,
    *,
    names: list[str],
    sizes: list[tuple[int, int]],
    distortion: Distortion,
    model: str,
    rig: RigFrame,
) -> Path:
    """cameras.txt, images.txt and an empty points3D.txt for ``cameras`` into ``folder``.

    Camera i (1-based ids in file order) is image i named ``names[i]``, recorded at
    ``sizes[i]`` = (width, height)."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    cam_lines = ["# Camera list with one line of data per camera:"]
    cam_lines.append("#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]")
    img_lines = ["# Image list with two lines of data per image:"]
    img_lines.append("#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME")
    img_lines.append("#   POINTS2D[] as (X, Y, POINT3D_ID)")
    for i, (camera, name, size) in enumerate(zip(cameras, names, sizes), start=1):
        cam_lines.append(camera_line(i, camera, distortion, model, size))
        w2c = rig.world_to_camera(camera.world_to_camera.numpy())
        q = rotation_to_quaternion(w2c[:3, :3])
        numbers = " ".join(repr(float(v)) for v in (*q, *w2c[:3, 3]))
        img_lines += [f"{i} {numbers} {i} {name}", ""]
    (folder / "cameras.txt").write_text("\n".join(cam_lines) + "\n")
    (folder / "images.txt").write_text("\n".join(img_lines) + "\n")
    (folder / "points3D.txt").write_text(
        "# 3D point list with one line of data per point: none (cameras only)\n"
    )
    return folder
