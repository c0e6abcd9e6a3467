"""Lifting from points: each object's frame-0 points become its particles.

Used with the oracle reconstructor (ground-truth points, optionally noisy), for ablations and
tests. Each particle's rest volume is the object's occupied volume divided by its particle count;
the occupied volume is measured on a voxel grid of ``voxel_size`` shared by all objects.

``split`` k replaces each point by k^3 particles on a k x k x k lattice centred on it, spaced
by the points' own spacing over k, each with 1 / k^3 of its volume: the same body, sampled
finely enough for a simulator grid finer than the points (MPM wants a few particles per cell;
a body sampled coarser than the grid's cells is represented by too few quadrature points and
tears apart numerically).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from mosiv_framework.interfaces import Lifter
from mosiv_framework.types import ParticleSet, Reconstruction


@dataclass
class PointsLifterOptions:
    """max_particles_per_object: random subsample above this (before any split); voxel_size
    (m): resolution of the occupancy used for particle volumes; seed: subsampling seed;
    split: each point becomes split^3 particles (see the module docstring)."""

    max_particles_per_object: int = 4000
    voxel_size: float = 0.01
    seed: int = 0
    split: int = 1

    def __post_init__(self) -> None:
        if self.max_particles_per_object < 1:
            raise ValueError(
                f"max_particles_per_object must be >= 1, got {self.max_particles_per_object}"
            )
        if isinstance(self.split, bool) or not isinstance(self.split, int) or self.split < 1:
            raise ValueError(f"split must be a whole number >= 1, got {self.split!r}")
        if not self.voxel_size > 0:
            raise ValueError(
                f"voxel_size must be a positive length in metres, got {self.voxel_size}"
            )


def occupied_volume(points: torch.Tensor, voxel_size: float) -> float:
    """Volume (m^3) of the voxels of side ``voxel_size`` that hold at least one point."""
    cells = torch.floor(points / voxel_size).to(torch.int64)
    return torch.unique(cells, dim=0).shape[0] * voxel_size**3


def split_points(points: torch.Tensor, k: int, volume: float) -> torch.Tensor:
    """Each of ``points`` [N, 3] replaced by k^3 points on a lattice centred on it with pitch
    s / k, where s = (volume / N)^(1/3) is the points' own spacing (``volume``: the body's)."""
    if k == 1:
        return points
    spacing = (volume / points.shape[0]) ** (1.0 / 3.0)
    steps = (torch.arange(k, dtype=points.dtype) + 0.5) / k - 0.5
    lattice = torch.stack(torch.meshgrid(steps, steps, steps, indexing="ij"), -1).reshape(-1, 3)
    return (points[:, None, :] + spacing * lattice[None]).reshape(-1, 3)


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
            pts = split_points(pts, self.options.split, volume)
            positions.append(pts)
            volumes.append(torch.full((pts.shape[0],), volume / pts.shape[0]))
            ids.append(torch.full((pts.shape[0],), k, dtype=torch.int64))
        return ParticleSet(
            torch.cat(positions),
            torch.cat(volumes),
            torch.cat(ids),
            {k: materials[k] for k in reconstruction.object_list},
        )
