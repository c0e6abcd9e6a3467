"""Real recordings in and out.

``mosiv data import`` turns what a capture rig delivers (one video or image folder per camera, a
COLMAP model or a nerfstudio ``transforms.json``) into a ``mosiv-scene/1`` folder
(docs/SCENE_FORMAT.md, "Importing a recording"); ``mosiv data capture`` writes a scene the way
such a rig delivers it (``write``), so that the import can be benchmarked against ground truth.

One module per job, shared by both directions: ``video`` (frames), ``colmap`` (COLMAP models,
read and written through pycolmap) and ``nerfstudio`` (cameras), ``lens`` (distortion and its
inverse, frames remapped through it), ``rotations`` (up axis to +z), ``offsets`` (time offsets),
``align`` (units, up axis, ground; the rig frame a capture is written in), ``domain`` (visual
hull, domain), ``materials`` (objects), ``importer`` and ``write`` (the steps in order).
"""

from mosiv_framework.capture.align import RigFrame
from mosiv_framework.capture.common import CaptureError, SourceCamera
from mosiv_framework.capture.importer import ImportSettings, find_inputs, import_recording
from mosiv_framework.capture.lens import Distortion
from mosiv_framework.capture.write import CAPTURE_FORMAT, write_capture

__all__ = [
    "CAPTURE_FORMAT",
    "CaptureError",
    "Distortion",
    "ImportSettings",
    "RigFrame",
    "SourceCamera",
    "find_inputs",
    "import_recording",
    "write_capture",
]
