"""Scene I/O for ``mosiv-scene/1``: cameras, reading, writing and validation.

Light on purpose: numpy and torch only at import; imageio loads when pixels are first read or
written. No simulator backend is imported here.
"""

from mosiv_framework.scene.cameras import Camera, is_rigid, rigidity_problems
from mosiv_framework.scene.check import (
    FORMAT,
    MATERIAL_FAMILIES,
    Problem,
    check_layout,
    check_scene,
    require_valid_scene,
    run_check,
    summary,
    validate_scene,
)
from mosiv_framework.scene.example import write_example_scene
from mosiv_framework.scene.io import (
    Scene,
    SceneObject,
    SceneWriter,
    atomic_write_bytes,
    atomic_write_json,
    encode_png,
    read_scene,
    write_scene,
)

__all__ = [
    "FORMAT",
    "MATERIAL_FAMILIES",
    "Camera",
    "Problem",
    "Scene",
    "SceneObject",
    "SceneWriter",
    "atomic_write_bytes",
    "atomic_write_json",
    "check_layout",
    "check_scene",
    "encode_png",
    "is_rigid",
    "read_scene",
    "require_valid_scene",
    "rigidity_problems",
    "run_check",
    "summary",
    "validate_scene",
    "write_example_scene",
    "write_scene",
]
