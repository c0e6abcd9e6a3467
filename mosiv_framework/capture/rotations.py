"""Rotations and rigid transforms the capture modules share: unit quaternions (w, x, y, z, as
COLMAP stores them) to and from matrices, 4x4 rigid transforms, and the smallest rotation taking
an up direction to +z."""

from __future__ import annotations

import numpy as np


def rigid(rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """[[R, t], [0, 1]] as a float64 4x4 array."""
    m = np.eye(4)
    m[:3, :3] = rotation
    m[:3, 3] = translation
    return m


def quaternion_to_rotation(q: np.ndarray) -> np.ndarray:
    """Quaternion (w, x, y, z) -> 3x3 rotation matrix (normalised first)."""
    w, x, y, z = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


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


def rotation_to_z(up: np.ndarray) -> np.ndarray:
    """The smallest rotation Q with Q up = +z (Rodrigues; 180 degrees about x for up = -z)."""
    u = np.asarray(up, float) / np.linalg.norm(up)
    z = np.array([0.0, 0.0, 1.0])
    c = float(u @ z)
    if c < -1.0 + 1e-12:
        return np.diag([1.0, -1.0, -1.0])
    v = np.cross(u, z)
    vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + vx + vx @ vx / (1.0 + c)
