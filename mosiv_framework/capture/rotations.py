"""The rotation the capture modules share: the smallest one taking an up direction to +z."""

from __future__ import annotations

import numpy as np


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
