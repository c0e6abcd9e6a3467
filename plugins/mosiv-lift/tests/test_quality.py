"""The lift's voxel IoU voxelises the ground truth exactly, whatever the phase of the grids.

A generated body is the set of lattice-cell centres inside its surface (``particle_spacing``
apart, at a random sub-cell offset), so each ground-truth particle is one voxel of its own
lattice. The IoU is taken on that lattice (``quality.lattice_origin``), not on the simulation
domain's grid, whose phase against the lattice is arbitrary: there, a cell holding one
ground-truth particle counted as full though the particle's voxel covers only part of it.

- A lift that fills exactly the ground truth's voxels scores 1. (On the domain's grid it
  scored 0.67-1.0 for this body, depending on the phase.)
- A perfect lift emitted on a grid of another phase (the exact more-than-half-inside occupancy
  of the body on that grid) still differs from the ground truth by its own voxelisation. For
  this slender body, 5 cells thick, that alone leaves IoU 0.72-0.86 over the six phases below
  (0.61-0.86 on the domain's grid): the ceiling of any lift at this cell size.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from mosiv_lift.quality import lift_geometry, scoring_cell

from mosiv_framework.types import ParticleSet

SPACING = 0.006  # m: the ground-truth lattice and the lift's cell
SEMI_AXES = np.array([0.06, 0.016, 0.014])  # m: a slender ellipsoid, 5 cells thick, as a banana


def inside(points: np.ndarray) -> np.ndarray:
    return np.sum((points / SEMI_AXES) ** 2, axis=1) <= 1.0


def lattice(phase: np.ndarray, spacing: float) -> np.ndarray:
    """Cell centres at (i + phase) * spacing covering the body's bounding box."""
    n = np.ceil(SEMI_AXES / spacing).astype(int) + 2
    axes = [(np.arange(-n[d], n[d] + 1) + phase[d]) * spacing for d in range(3)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)


def perfect_lift(phase: np.ndarray, *, samples: int = 6, per_axis: int = 2) -> np.ndarray:
    """Particles (``per_axis``^3 per cell) in the cells of the lift's grid that the body fills
    more than half of, measured with ``samples``^3 points per cell."""
    centres = lattice(phase, SPACING)
    f = (np.arange(samples) + 0.5) / samples - 0.5
    sub = np.stack(np.meshgrid(f, f, f, indexing="ij"), axis=-1).reshape(-1, 3) * SPACING
    share = inside((centres[:, None, :] + sub[None]).reshape(-1, 3)).reshape(len(centres), -1)
    full = centres[share.mean(axis=1) > 0.5]
    g = (np.arange(per_axis) + 0.5) / per_axis - 0.5
    emit = np.stack(np.meshgrid(g, g, g, indexing="ij"), axis=-1).reshape(-1, 3) * SPACING
    return (full[:, None, :] + emit[None]).reshape(-1, 3)


def particle_set(positions: np.ndarray, per_axis: int) -> ParticleSet:
    """One object's particles, each of volume spacing^3 / per_axis^3."""
    n = len(positions)
    return ParticleSet(
        positions=torch.from_numpy(positions),
        volumes=torch.full((n,), SPACING**3 / per_axis**3, dtype=torch.float64),
        object_ids=torch.ones(n, dtype=torch.int64),
        materials={1: "elastic"},
    )


def ground_truth(rng: np.random.Generator) -> np.ndarray:
    centres = lattice(rng.uniform(0.0, 1.0, 3), SPACING)
    return centres[inside(centres)]


@pytest.mark.parametrize("seed", range(4))
def test_a_lift_filling_the_ground_truth_voxels_scores_one(seed):
    gt = ground_truth(np.random.default_rng(seed))
    g = (np.arange(2) + 0.5) / 2 - 0.5  # 8 particles per voxel, as the lifter emits them
    emit = np.stack(np.meshgrid(g, g, g, indexing="ij"), axis=-1).reshape(-1, 3) * SPACING
    lift = (gt[:, None, :] + emit[None]).reshape(-1, 3)
    score = lift_geometry(
        particle_set(lift, 2), {1: torch.from_numpy(gt)}, gt_spacing=SPACING, cell=SPACING
    )[1]
    assert score["iou"] == 1.0 and abs(score["volume_error"]) < 1e-9, score


@pytest.mark.parametrize("seed", range(6))
def test_a_perfect_lift_on_another_grid_scores_near_its_voxelisation_ceiling(seed):
    rng = np.random.default_rng(seed)
    gt = ground_truth(rng)
    lift = perfect_lift(rng.uniform(0.0, 1.0, 3))
    score = lift_geometry(
        particle_set(lift, 2), {1: torch.from_numpy(gt)}, gt_spacing=SPACING, cell=SPACING
    )[1]
    assert abs(score["volume_error"]) < 0.06, score
    assert score["iou"] >= 0.7, score


@pytest.mark.parametrize("lift_cell", [SPACING / 2, SPACING / 3])
def test_a_lift_on_a_finer_grid_is_scored_on_the_lattice(lift_cell):
    """A lift on cells finer than the lattice fills each ground-truth voxel with sub-cells;
    scored on ``scoring_cell`` it counts as exact, while the finer grid itself would count
    every ground-truth particle as one mostly empty cell."""
    gt = ground_truth(np.random.default_rng(7))
    n = round(SPACING / lift_cell)
    g = (np.arange(n) + 0.5) / n - 0.5  # the lifter's cell centres inside each lattice voxel
    emit = np.stack(np.meshgrid(g, g, g, indexing="ij"), axis=-1).reshape(-1, 3) * SPACING
    lift = particle_set((gt[:, None, :] + emit[None]).reshape(-1, 3), n)
    assert scoring_cell(lift_cell, SPACING) == SPACING
    assert scoring_cell(2 * SPACING, SPACING) == 2 * SPACING
    truth = {1: torch.from_numpy(gt)}
    on_lattice = lift_geometry(
        lift, truth, gt_spacing=SPACING, cell=scoring_cell(lift_cell, SPACING)
    )
    assert on_lattice[1]["iou"] == 1.0, on_lattice
    too_fine = lift_geometry(lift, truth, gt_spacing=SPACING, cell=lift_cell)
    assert too_fine[1]["iou"] < 0.5, too_fine
