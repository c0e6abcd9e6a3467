"""Lifting from points: each object's frame-0 points become its particles.

Used with the oracle reconstructor (ground-truth points, optionally noisy), for ablations and
tests. Each particle's rest volume is the object's occupied volume divided by its particle count;
the occupied volume is measured on a voxel grid of ``voxel_size`` shared by all objects.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from mosiv_framework.interfaces import Lifter
from mosiv_framework.types import ParticleSet, Reconstruction


@dataclass
class PointsLifterOptions:
    """max_particles_per_object: random subsample above this; voxel_size (m): resolution of the
    occupancy used for particle volumes; seed: subsampling seed."""

    max_particles_per_object: int = 4000
    voxel_size: float = 0.01
    seed: int = 0

    def __post_init__(self) -> None:
        if self.max_particles_per_object < 1:
            raise ValueError(
                f"max_particles_per_object must be >= 1, got {self.max_particles_per_object}"
            )
        if not self.voxel_size > 0:
            raise ValueError(
                f"voxel_size must be a positive length in metres, got {self.voxel_size}"
            )


def occupied_volume(points: torch.Tensor, voxel_size: float) -> float:
    """Volume (m^3) of the voxels of side ``voxel_size`` that hold at least one point."""
    cells = torch.floor(points / voxel_size).to(torch.int64)
    return torch.unique(cells, dim=0).shape[0] * voxel_size**3


class PointsLifter(Lifter):
    def __init__(self, **options):
        self.options = PointsLifterOptions(**options)

    def lift(self, reconstruction: Reconstruction, scene) -> ParticleSet:
        generator = torch.Generator().manual_seed(self.options.seed)
        materials = {obj.id: obj.material for obj in scene.objects}
        positions, volumes, ids = [], [], []
        for k in reconstruction.object_list:
            if k not in materials:
                raise ValueError(f"reconstruction has object {k} that scene.json does not declare")
            pts = reconstruction.points[k][0].to(torch.float32)
            if pts.shape[0] > self.options.max_particles_per_object:
                keep = torch.randperm(pts.shape[0], generator=generator)
                pts = pts[keep[: self.options.max_particles_per_object]]
            volume = occupied_volume(pts, self.options.voxel_size)
            positions.append(pts)
            volumes.append(torch.full((pts.shape[0],), volume / pts.shape[0]))
            ids.append(torch.full((pts.shape[0],), k, dtype=torch.int64))
        return ParticleSet(
            torch.cat(positions),
            torch.cat(volumes),
            torch.cat(ids),
            {k: materials[k] for k in reconstruction.object_list},
        )
