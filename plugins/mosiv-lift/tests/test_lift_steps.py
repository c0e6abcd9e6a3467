"""Unit tests of the lifting steps on analytic shapes (no scene, no renderer)."""

from __future__ import annotations

import math

import numpy as np
import torch
from mosiv_lift.bind import bind_gaussians
from mosiv_lift.carve import Box, draw_samples, fibonacci_directions, object_box
from mosiv_lift.density import refine_density
from mosiv_lift.emit import emit_particles

from mosiv_framework.types import GaussianFrames


def _sphere_grid(centre, radius, cell, seed=0, per_cell=8.0, levels=3):
    """Density grid of a ball carved exactly (kept = inside the analytic sphere)."""
    # Gaussians filling the ball (like the oracle's points): shells of Fibonacci points
    shells = [
        r * fibonacci_directions(max(8, int(400 * r * r / radius**2)))
        for r in np.linspace(0.1 * radius, radius, 8)
    ]
    means = torch.tensor([centre], dtype=torch.float64) + torch.cat(shells)
    box = object_box(
        means,
        torch.full((means.shape[0],), 1e-3),
        origin=(0.0, 0.0, 0.0),
        cell=cell,
        levels=levels,
        padding=None,
    )
    samples = draw_samples(
        box, per_cell=per_cell, generator=torch.Generator().manual_seed(seed), limit=10**7
    )
    kept = (samples - torch.tensor(centre, dtype=torch.float64)).norm(dim=1) <= radius
    return refine_density(samples, kept, box, levels=levels, prior_weight=2.0), means


def test_box_is_whole_coarse_cells_around_the_gaussians():
    means = torch.tensor([[0.1, 0.2, 0.3], [0.15, 0.27, 0.31]])
    box = object_box(
        means, torch.tensor([0.002, 0.002]), origin=(0, 0, 0), cell=0.01, levels=3, padding=0.0
    )
    lo = box.world_lower
    hi = lo + torch.tensor(box.shape, dtype=torch.float64) * box.cell
    assert torch.all(lo <= means.double().min(0).values) and torch.all(
        hi >= means.double().max(0).values
    )
    assert all(s % 4 == 0 for s in box.shape)


def test_density_grid_recovers_the_volume_of_a_ball():
    radius, cell = 0.05, 0.005
    grid, _ = _sphere_grid((0.2, 0.2, 0.2), radius, cell)
    volume = float(grid.occupied.sum()) * cell**3
    exact = 4.0 / 3.0 * math.pi * radius**3
    assert abs(volume - exact) / exact < 0.03


def test_coarse_to_fine_fills_cells_that_hold_no_sample():
    # with 0.5 samples per fine cell most interior cells are empty; the coarse prior fills them
    radius, cell = 0.05, 0.005
    grid, _ = _sphere_grid((0.2, 0.2, 0.2), radius, cell, per_cell=0.5)
    volume = float(grid.occupied.sum()) * cell**3
    exact = 4.0 / 3.0 * math.pi * radius**3
    assert abs(volume - exact) / exact < 0.1
    single, _ = _sphere_grid((0.2, 0.2, 0.2), radius, cell, per_cell=0.5, levels=1)
    assert float(single.occupied.sum()) * cell**3 < 0.8 * exact  # one level leaves holes


def test_overlapping_claims_go_to_the_nearest_surface_and_sub_lattices_keep_apart():
    cell = 0.005
    a, surf_a = _sphere_grid((0.20, 0.2, 0.2), 0.04, cell)
    b, surf_b = _sphere_grid((0.26, 0.2, 0.2), 0.04, cell, seed=1)  # balls overlap by 2 cm
    em = emit_particles(
        {1: a, 2: b},
        {1: surf_a.float(), 2: surf_b.float()},
        domain_lower=(0, 0, 0),
        domain_upper=(1, 1, 1),
        cell=cell,
        sub_lattice=2,
        densities={1: 1000.0, 2: 500.0},
    )
    assert em.contested_cells > 0
    pos, ids = em.positions.double().numpy(), em.object_ids.numpy()
    # the lens both balls claim goes to the nearest Gaussians: split at the bisector x = 0.23
    # (up to the spacing of the discrete shells)
    lens = np.linalg.norm(pos - [0.20, 0.2, 0.2], axis=1) < 0.04
    lens &= np.linalg.norm(pos - [0.26, 0.2, 0.2], axis=1) < 0.04
    assert np.all(pos[lens & (ids == 1), 0] < 0.23 + 2 * cell)
    assert np.all(pos[lens & (ids == 2), 0] > 0.23 - 2 * cell)
    from scipy.spatial import cKDTree

    gap = cKDTree(pos[ids == 2]).query(pos[ids == 1])[0].min()
    assert gap >= 0.5 * cell * (1 - 1e-4)
    torch.testing.assert_close(em.volumes, torch.full_like(em.volumes, cell**3 / 8))
    rho = torch.where(em.object_ids == 1, 1000.0, 500.0)
    torch.testing.assert_close(em.masses, rho * em.volumes)


def test_binding_interpolates_displacements_with_weights_summing_to_one():
    gen = torch.Generator().manual_seed(0)
    particles = torch.rand(300, 3, generator=gen)
    ids = torch.where(particles[:, 0] < 0.5, 1, 2)
    centres = torch.rand(50, 3, generator=gen)
    g_ids = torch.where(centres[:, 0] < 0.5, 1, 2)
    gaussians = GaussianFrames(
        centres[None],
        torch.full((1, 50), 0.01),
        torch.rand(50, 3, generator=gen),
        torch.ones(50),
        g_ids,
    )
    binding = bind_gaussians(gaussians, particles, ids, neighbors=4, power=2.0)
    torch.testing.assert_close(binding.weights.sum(1), torch.ones(50))
    # neighbours belong to the Gaussian's own object
    assert torch.all(ids[binding.neighbors] == g_ids[:, None])
    # moving only object 2's particles leaves object 1's Gaussians in place
    moved = particles + (ids == 2)[:, None] * torch.tensor([0.0, 0.0, 0.1])
    means = binding.means(moved)
    torch.testing.assert_close(means[g_ids == 1], centres[g_ids == 1])
    torch.testing.assert_close(means[g_ids == 2], centres[g_ids == 2] + torch.tensor([0, 0, 0.1]))
    # differentiable in the particle state (silhouette losses need it)
    state = particles.clone().requires_grad_(True)
    binding.means(state).sum().backward()
    assert state.grad is not None and torch.isfinite(state.grad).all()


def test_box_type_is_plain_data():
    box = Box((0.0, 0.0, 0.0), 0.01, (1, 2, 3), (4, 4, 4))
    assert box.n_cells == 64
    torch.testing.assert_close(
        box.world_lower, torch.tensor([0.01, 0.02, 0.03], dtype=torch.float64)
    )
