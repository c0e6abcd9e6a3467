"""Which world axis points up in the exported files.

MOSIV's world is z up (metres). Tools disagree: glTF fixes +y up (and Blender's, three.js's
importers rely on it), and splat viewers made for COLMAP captures expect OpenCV's y down. A
proper rotation (no mirror) takes MOSIV's world into each; isotropic Gaussians need no change
of their rotation, only of their means.
"""

from __future__ import annotations

import numpy as np

from mosiv_framework.capture.align import parse_up
from mosiv_framework.capture.rotations import rotation_to_z

#: the up axis of the written files -> rotation applied to MOSIV's (x, y, z) points: the
#: inverse of the import's rotation of that up axis to +z (as ``align.RigFrame`` writes a
#: capture's cameras): "y" takes (x, y, z) to (x, z, -y), glTF's convention; "-y" to
#: (x, -z, y), OpenCV's and COLMAP's
ROTATIONS = {up: rotation_to_z(parse_up(up)).T for up in ("z", "y", "-y")}
#: how the README names each choice
DESCRIPTION = {
    "z": "z up (MOSIV's world)",
    "y": "y up: the file's (x, y, z) is MOSIV's (x, z, -y)",
    "-y": "y down, as OpenCV and COLMAP captures are: the file's (x, y, z) is MOSIV's (x, -z, y)",
}


def rotate(points: np.ndarray, up: str) -> np.ndarray:
    """``points`` [..., 3] (positions or velocities) in the files' world with ``up`` up."""
    if up not in ROTATIONS:
        raise ValueError(f"up axis {up!r}: choose one of {', '.join(ROTATIONS)}")
    return np.asarray(points) @ ROTATIONS[up].T


def srgb_to_linear(rgb: np.ndarray) -> np.ndarray:
    """sRGB colours in [0, 1] as linear RGB, which glTF's vertex colours are."""
    rgb = np.clip(np.asarray(rgb, dtype=np.float64), 0.0, 1.0)
    return np.where(rgb <= 0.04045, rgb / 12.92, ((rgb + 0.055) / 1.055) ** 2.4)
