"""What the capture steps share: the error they raise, a camera as the recording gives it, how a
camera model's image name finds its frames, and the refusal of a non-empty output folder."""

from __future__ import annotations

from dataclasses import dataclass, field
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
