"""Real recordings in: ``mosiv data import`` turns what a capture rig delivers (one video or
image folder per camera, a COLMAP model or a nerfstudio ``transforms.json``) into a
``mosiv-scene/1`` folder (docs/SCENE_FORMAT.md, "Importing a recording").

One module per job: ``video`` (frames), ``colmap`` and ``nerfstudio`` (cameras),
``distortion`` (undistortion to pinhole), ``offsets`` (time offsets), ``align`` (units, up axis,
ground), ``domain`` (visual hull, domain), ``materials`` (objects) and ``importer`` (the steps
in order).
"""

from mosiv_framework.capture.common import CaptureError, SourceCamera
from mosiv_framework.capture.importer import ImportSettings, find_inputs, import_recording

__all__ = ["CaptureError", "ImportSettings", "SourceCamera", "find_inputs", "import_recording"]
