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

from __future__ import annotations

import importlib

#: the package's names and the module each comes from, imported on first use: the CLI reads
#: ``capture.options`` to build its parser, which must not load pycolmap, imageio or torch
_EXPORTS = {
    "CAPTURE_FORMAT": "write",
    "CaptureError": "common",
    "Distortion": "lens",
    "ImportSettings": "importer",
    "RigFrame": "align",
    "SourceCamera": "common",
    "find_inputs": "importer",
    "import_recording": "importer",
    "write_capture": "write",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    if name not in _EXPORTS:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(importlib.import_module(f"{__name__}.{_EXPORTS[name]}"), name)
