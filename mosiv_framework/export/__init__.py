"""``mosiv export``: a finished run as PLY point clouds, 3DGS splats, glTF meshes and JSON."""

from mosiv_framework.export.meshes import object_mesh, write_frame_glb
from mosiv_framework.export.ply import (
    GAUSSIAN_PROPERTIES,
    PARTICLE_PROPERTIES,
    read_gaussians_ply,
    write_gaussians_ply,
    write_particles_ply,
)
from mosiv_framework.export.run_data import RunData, load_run
from mosiv_framework.export.writer import MARKER, export_run, select_frames

__all__ = [
    "GAUSSIAN_PROPERTIES",
    "MARKER",
    "PARTICLE_PROPERTIES",
    "RunData",
    "export_run",
    "load_run",
    "object_mesh",
    "read_gaussians_ply",
    "select_frames",
    "write_frame_glb",
    "write_gaussians_ply",
    "write_particles_ply",
]
