"""A scene written as a capture rig delivers it: videos, COLMAP cameras, lens distortion.

``distortion`` holds the lens model (forward ``distort_*`` and inverse ``undistort_*``) that an
importer of such captures uses to undo what ``writer.write_capture`` applied.
"""

from mosiv_framework.capture_out.colmap import (
    RigFrame,
    quaternion_to_rotation,
    rotation_to_quaternion,
    write_colmap_text,
)
from mosiv_framework.capture_out.distortion import (
    Distortion,
    distort_image,
    distort_normalized,
    distort_pixels,
    undistort_normalized,
    undistort_pixels,
)
from mosiv_framework.capture_out.writer import CAPTURE_FORMAT, write_capture

__all__ = [
    "CAPTURE_FORMAT",
    "Distortion",
    "RigFrame",
    "distort_image",
    "distort_normalized",
    "distort_pixels",
    "quaternion_to_rotation",
    "rotation_to_quaternion",
    "undistort_normalized",
    "undistort_pixels",
    "write_capture",
    "write_colmap_text",
]
