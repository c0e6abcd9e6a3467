"""Coarse-to-fine density grid of one object's interior from its carving samples.

Paper section 3.3: a density grid is refined from coarse to fine by upsampling, mean filtering,
re-marking the voxels that hold samples, and thresholding. Here, at every level, a voxel's
*measured* occupancy is the fraction of the uniform samples inside it that survived carving
(an unbiased estimate of the fraction of the voxel inside the object). Level by level:
1. coarsest level: density = measured fraction;
2. finer level: the previous level's thresholded occupancy is upsampled x2 (nearest) and mean
   filtered over 3x3x3 voxels, giving a smooth prior in [0, 1];
3. re-mark: voxels that hold samples blend their measured fraction with the prior,
   ``d = (n f + w prior) / (n + w)`` with ``n`` samples in the voxel and ``w = prior_weight``;
   voxels without samples keep the prior (this fills holes left by sparse sampling);
4. threshold: occupied where ``d >= 1/2`` (the voxel is more inside than outside).
The result is on the finest level, whose voxels are the cells of the shared emission grid.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from mosiv_lift.carve import Box

Tensor = torch.Tensor


@dataclass
class DensityGrid:
    """One object's finest-level grid over ``box``: density [X, Y, Z] in [0, 1] and the
    thresholded occupancy [X, Y, Z] bool."""

    box: Box
    density: Tensor
    occupied: Tensor


def _counts(samples: Tensor, kept: Tensor, box: Box, factor: int) -> tuple[Tensor, Tensor]:
    """Samples and kept samples per voxel of a level whose voxels are ``factor`` cells wide."""
    shape = [s // factor for s in box.shape]
    local = (samples - box.world_lower) / (box.cell * factor)
    idx = torch.floor(local).long()
    for d in range(3):  # a sample exactly on the upper face belongs to the last voxel
        idx[:, d] = idx[:, d].clamp(0, shape[d] - 1)
    flat = (idx[:, 0] * shape[1] + idx[:, 1]) * shape[2] + idx[:, 2]
    n = shape[0] * shape[1] * shape[2]
    total = torch.bincount(flat, minlength=n).reshape(shape).double()
    hits = torch.bincount(flat[kept], minlength=n).reshape(shape).double()
    return total, hits


def _mean_filter(grid: Tensor) -> Tensor:
    """3x3x3 box mean with zero padding (space outside the box is outside the object)."""
    x = grid[None, None]
    return torch.nn.functional.avg_pool3d(x, 3, stride=1, padding=1, count_include_pad=True)[0, 0]


def refine_density(
    samples: Tensor, kept: Tensor, box: Box, *, levels: int, prior_weight: float
) -> DensityGrid:
    """Run the coarse-to-fine refinement on carving ``samples`` [S, 3] (m) with ``kept`` [S]."""
    occupied = None
    density = None
    for level in range(levels):
        factor = 2 ** (levels - 1 - level)
        total, hits = _counts(samples, kept, box, factor)
        measured = hits / total.clamp_min(1.0)
        if occupied is None:
            density = measured
        else:
            up = occupied.double().repeat_interleave(2, 0).repeat_interleave(2, 1)
            prior = _mean_filter(up.repeat_interleave(2, 2))
            density = (total * measured + prior_weight * prior) / (total + prior_weight)
            density = torch.where(total > 0, density, prior)
        occupied = density >= 0.5
    return DensityGrid(box, density, occupied)
