"""What the capture steps share: the error they raise, a camera as the recording gives it, how a
camera model's image name finds its frames, and the refusal of a non-empty output folder."""

from __future__ import annotations

import math
import re
from dataclasses import astuple, dataclass, field
from pathlib import Path

import numpy as np

from mosiv_framework.capture.lens import Distortion, Intrinsics
from mosiv_framework.errors import ConfigError, OutputError


class CaptureError(ConfigError):
    """A recording cannot be imported; the message names the file and the field at fault."""


@dataclass
class SourceCamera:
    """One camera of a recording, in the recording's own world frame and units.

    ``world_to_camera`` is a 4x4 rigid transform in the OpenCV convention (x right, y down, z
    forward) whose translation is in the recording's units. ``origin`` says where the pose was
    read (file and entry), so that errors can point at it.
    """

    id: str
    intrinsics: Intrinsics
    distortion: Distortion
    world_to_camera: np.ndarray
    origin: str
    model: str = "PINHOLE"
    extra: dict = field(default_factory=dict)

    @property
    def rotation(self) -> np.ndarray:
        return self.world_to_camera[:3, :3]

    @property
    def center(self) -> np.ndarray:
        """Optical centre in recording coordinates: -R^T t."""
        return -self.rotation.T @ self.world_to_camera[:3, 3]


def natural_key(name: str) -> list:
    """Sort key that reads digit runs as numbers: frame_9 before frame_10, 2.png before
    10.png (tools that number frames without leading zeros would otherwise be read out of
    order); with zero-padded numbers it is the plain order."""
    return [(0, int(t), t) if t.isdigit() else (1, 0, t) for t in re.split(r"(\d+)", name)]


def camera_key(name: str, known: set[str]) -> str | None:
    """The camera id an image path of a camera model refers to (docs/SCENE_FORMAT.md,
    "Importing a recording"): the file's stem if a video or frame folder has that name, else its
    parent folder's name if one has that name; None when neither does."""
    parts = name.replace("\\", "/").split("/")
    stem = parts[-1].rsplit(".", 1)[0]
    if stem in known:
        return stem
    if len(parts) >= 2 and parts[-2] in known:
        return parts[-2]
    return None


def no_frames_message(where: str, name: str) -> str:
    """The error for a camera of a model that no video or frame folder belongs to."""
    parts = name.replace("\\", "/").split("/")
    stem = parts[-1].rsplit(".", 1)[0]
    names = repr(stem) + (f" or {parts[-2]!r}" if len(parts) >= 2 else "")
    return (
        f"{where}: this camera has no frames: no video or frame folder named {names} "
        "in the frames folder"
    )


def refuse_non_empty(out: Path, what: str) -> None:
    """OutputError unless ``out`` is absent or an empty folder: nothing is ever overwritten."""
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        state = "is a file" if not out.is_dir() else "is a non-empty folder"
        raise OutputError(
            f"{what} {str(out)!r} {state}; give a new or empty folder (nothing is overwritten)"
        )


#: how far the frames of one camera may disagree and still be one fixed camera: registered
#: one by one (COLMAP, nerfstudio), a fixed camera's frames differ by the solver's noise
STATIC_ROTATION_DEG = 1.0
#: of the median distance between the cameras (from the origin, for a single camera)
STATIC_CENTRE_FRACTION = 0.02
#: relative, of focal lengths, principal point and size; distortion coefficients absolute
STATIC_INTRINSICS_FRACTION, STATIC_DISTORTION_ATOL = 0.01, 1e-3


def one_pose_per_camera(frames: dict[str, list[SourceCamera]]) -> list[SourceCamera]:
    """Each camera's first frame, once its other frames are found to agree with it.

    A capture rig's cameras are fixed and ``mosiv-scene/1`` has one pose per camera; a camera
    whose frames turn or move it further than registration noise (``STATIC_*``) is refused,
    naming both frames, rather than one pose silently kept."""
    firsts = {key: views[0] for key, views in frames.items()}
    if not firsts:
        return []
    centres = np.array([c.center for c in firsts.values()])
    if len(centres) > 1:
        gaps = np.linalg.norm(centres[:, None] - centres[None], axis=-1)
        scale = float(np.median(gaps[np.triu_indices(len(centres), 1)]))
    else:  # one camera: no spacing to measure a move against, only its turning is checked
        scale = math.inf
    for views in frames.values():
        for other in views[1:]:
            _same_camera(views[0], other, scale)
    return list(firsts.values())


def _same_camera(first: SourceCamera, other: SourceCamera, scale: float) -> None:
    cos = (float(np.trace(first.rotation.T @ other.rotation)) - 1.0) / 2.0
    angle = math.degrees(math.acos(min(1.0, max(-1.0, cos))))
    shift = float(np.linalg.norm(first.center - other.center))
    if angle > STATIC_ROTATION_DEG or shift > STATIC_CENTRE_FRACTION * scale:
        raise CaptureError(
            f"{other.origin}: camera {first.id!r} is turned {angle:.3g} deg and moved "
            f"{shift:.3g} (the recording's units) from its pose in {first.origin}: a capture "
            f"rig's cameras must stay fixed (at most {STATIC_ROTATION_DEG:g} deg and "
            f"{STATIC_CENTRE_FRACTION:g} of the distance between cameras, {scale:.3g})"
        )
    a, b = np.array(astuple(first.intrinsics)), np.array(astuple(other.intrinsics))
    da, db = np.array(first.distortion.coefficients), np.array(other.distortion.coefficients)
    same_lens = first.distortion.model == other.distortion.model and np.allclose(
        da, db, rtol=0.0, atol=STATIC_DISTORTION_ATOL
    )
    if not np.allclose(a, b, rtol=STATIC_INTRINSICS_FRACTION, atol=0.0) or not same_lens:
        raise CaptureError(
            f"{other.origin}: camera {first.id!r} has other intrinsics or distortion here "
            f"({first.intrinsics}, {first.distortion} in {first.origin}; here "
            f"{other.intrinsics}, {other.distortion})"
        )
