"""Unit tests of the lifting steps on analytic shapes (no scene, no renderer)."""

from __future__ import annotations

import math

import numpy as np
import pytest
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


def test_an_object_emptied_by_another_objects_claims_is_named_with_the_counts():
    cell = 0.005
    big, surf_big = _sphere_grid((0.20, 0.2, 0.2), 0.05, cell)
    small, surf_small = _sphere_grid((0.20, 0.2, 0.2), 0.02, cell, seed=1)
    # object 1's Gaussians reach inside object 2 (as when Stage I mislabels some), so every
    # cell of object 2 is contested and object 1's surface is as near as object 2's
    with pytest.raises(ValueError) as error:
        emit_particles(
            {1: big, 2: small},
            {1: torch.cat([surf_big, surf_small]).float(), 2: surf_small.float()},
            domain_lower=(0, 0, 0),
            domain_upper=(1, 1, 1),
            cell=cell,
            sub_lattice=1,
            densities={1: 1000.0, 2: 1000.0},
        )
    n = int(small.occupied.sum())
    assert (
        f"object 2 has no occupied cell inside the domain after lifting: its density grid held {n} cells, {n} went to other objects"
        in str(error.value)
    )


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


def _sheet(z: float, opacity: float) -> GaussianFrames:
    """Gaussians of radius 2 mm every 2 mm over a 10 cm square in the plane at height z (m)."""
    axis = torch.arange(-0.05, 0.0501, 0.002)
    x, y = torch.meshgrid(axis, axis, indexing="ij")
    means = torch.stack([x.reshape(-1), y.reshape(-1), torch.full((x.numel(),), z)], dim=-1)
    g = means.shape[0]
    return GaussianFrames(
        means[None],
        torch.full((1, g), 0.002),
        torch.full((g, 3), 0.5),
        torch.full((g,), opacity),
        torch.ones(g, dtype=torch.int64),
    )


def test_depth_test_puts_the_surface_at_the_half_density_front_of_the_first_layer():
    from mosiv_lift.carve import HALF_DENSITY_RADII, depth_consistent

    from mosiv_framework.registry import get_registry
    from mosiv_framework.scene.cameras import Camera

    renderer = get_registry().create("renderer", "gauss-torch", {"tile_size": 8})
    camera = Camera.look_at((0, 0, 0.5), (0, 0, 0), (0, 1, 0), width=48, height=48, fov_deg=20)
    front = 0.002 * HALF_DENSITY_RADII  # m above the sheet's centre plane
    heights = torch.tensor([0.02, front + 0.002, front - 0.001, 0.0, -0.01])
    samples = torch.stack([torch.zeros(5), torch.zeros(5), heights], dim=-1).double()
    opaque = _sheet(0.0, 1.0)
    votes = depth_consistent(
        samples,
        opaque,
        renderer,
        [camera],
        alpha_threshold=0.5,
        depth_tolerance=0.0,
        layer=0.0005,
        surface_fraction=0.5,
    )
    assert votes.tolist() == [0, 0, 1, 1, 1]  # free space in front of the surface, solid behind
    # a tolerance moves the surface towards the camera by that much
    votes = depth_consistent(
        samples,
        opaque,
        renderer,
        [camera],
        alpha_threshold=0.5,
        depth_tolerance=0.004,
        layer=0.0005,
        surface_fraction=0.5,
    )
    assert votes.tolist() == [0, 1, 1, 1, 1]
    # a faint sheet 2 cm above an opaque one: the median surface is the opaque sheet; asking
    # for half the faint sheet's opacity finds the faint one
    faint, solid = _sheet(0.0, 0.05), _sheet(-0.02, 1.0)
    stack = GaussianFrames(
        torch.cat([faint.means, solid.means], dim=1),
        torch.cat([faint.radii, solid.radii], dim=1),
        torch.cat([faint.colors, solid.colors]),
        torch.cat([faint.opacities, solid.opacities]),
        torch.cat([faint.object_ids, solid.object_ids]),
    )
    faint_alpha = float(renderer.render(faint, camera, frame=0, n_objects=1).alpha[24, 24])
    assert 0.05 < faint_alpha < 0.5
    mid = torch.tensor([[0.0, 0.0, -0.01]], dtype=torch.float64)  # between the sheets
    kwargs = dict(alpha_threshold=0.3, depth_tolerance=0.0, layer=0.0005)
    median = depth_consistent(mid, stack, renderer, [camera], surface_fraction=0.5, **kwargs)
    first = depth_consistent(
        mid, stack, renderer, [camera], surface_fraction=0.5 * faint_alpha, **kwargs
    )
    assert median.tolist() == [0] and first.tolist() == [1]


def test_widened_trained_gaussians_close_their_gaps_without_moving_the_surface():
    # a trained-like sheet: tiny Gaussians (0.3 mm) every 4 mm, far sparser than the ~3.6 mm
    # pixels of the view, so most pixel rays pass between them and the solid behind the sheet
    # is voted out; widened by half their spacing they overlap into a closed sheet
    from mosiv_lift.carve import depth_consistent, widened_radii
    from mosiv_lift.seed import default_point_radius

    from mosiv_framework.registry import get_registry
    from mosiv_framework.scene.cameras import Camera

    renderer = get_registry().create("renderer", "gauss-torch", {"tile_size": 8})
    camera = Camera.look_at((0, 0, 0.5), (0, 0, 0), (0, 1, 0), width=48, height=48, fov_deg=20)
    axis = torch.arange(-0.04, 0.0401, 0.004)
    x, y = torch.meshgrid(axis, axis, indexing="ij")
    means = torch.stack([x.reshape(-1), y.reshape(-1), torch.zeros(x.numel())], dim=-1)
    g = means.shape[0]
    radii = torch.full((g,), 0.0003)
    widen = default_point_radius({1: means})
    assert abs(widen - 0.002) < 1e-6  # half the 4 mm spacing
    torch.testing.assert_close(
        widened_radii(radii, widen), torch.full((g,), math.hypot(3e-4, widen))
    )

    def sheet(r):
        return GaussianFrames(
            means[None],
            r[None],
            torch.full((g, 3), 0.5),
            torch.ones(g),
            torch.ones(g, dtype=torch.int64),
        )

    grid = torch.linspace(-0.02, 0.02, 9)
    gx, gy = torch.meshgrid(grid, grid, indexing="ij")
    plane = torch.stack([gx.reshape(-1), gy.reshape(-1)], dim=-1).double()

    def at(z):
        return torch.cat([plane, torch.full((plane.shape[0], 1), z, dtype=torch.float64)], 1)

    kwargs = dict(alpha_threshold=0.5, depth_tolerance=0.0, layer=0.0005, surface_fraction=0.5)
    behind = at(-0.003)  # 3 mm inside the solid below the sheet
    sparse = depth_consistent(behind, sheet(radii), renderer, [camera], **kwargs)
    closed = depth_consistent(
        behind, sheet(widened_radii(radii, widen)), renderer, [camera], front_radii=radii, **kwargs
    )
    assert float(sparse.double().mean()) < 0.5  # the gaps vote most of the interior out
    assert bool((closed == 1).all())
    # the widening blurs but does not move the surface: 1.5 mm in front of it is still free
    in_front = at(0.0015)
    votes = depth_consistent(
        in_front,
        sheet(widened_radii(radii, widen)),
        renderer,
        [camera],
        front_radii=radii,
        **kwargs,
    )
    assert bool((votes == 0).all())
    # counted from the widened radius instead, the front would move out by 1.18 * 2 mm
    moved = depth_consistent(
        in_front, sheet(widened_radii(radii, widen)), renderer, [camera], **kwargs
    )
    assert bool((moved == 1).all())


def _share_inside(box: Box, centre, radius: float, sub: int = 4) -> torch.Tensor:
    """Exact-enough fraction of each cell of ``box`` inside a ball (sub^3 regular points)."""
    axes = [(torch.arange(n * sub, dtype=torch.float64) + 0.5) / sub * box.cell for n in box.shape]
    points = torch.stack(torch.meshgrid(*axes, indexing="ij"), dim=-1) + box.world_lower
    inside = (points - torch.tensor(centre, dtype=torch.float64)).norm(dim=-1) <= radius
    x, y, z = box.shape
    return inside.double().reshape(x, sub, y, sub, z, sub).mean(dim=(1, 3, 5))


def test_default_sampling_classifies_boundary_cells_beyond_sampling_noise():
    # a cell three quarters inside (or outside) must land on its side of the 1/2 threshold;
    # with 8 samples per cell binomial noise flips some of them (options.py, samples_per_cell)
    from mosiv_lift.options import GaussiansLifterOptions

    centre, radius, cell = (0.2, 0.2, 0.2), 0.05, 0.005
    default = GaussiansLifterOptions().samples_per_cell
    wrong = {}
    for per_cell in (8.0, default):
        grid, _ = _sphere_grid(centre, radius, cell, per_cell=per_cell)
        share = _share_inside(grid.box, centre, radius)
        boundary = (share > 0) & (share < 1)
        clear = boundary & ((share - 0.5).abs() >= 0.25)
        flipped = grid.occupied != (share >= 0.5)
        wrong[per_cell] = (int((flipped & clear).sum()), int(flipped.sum()), int(boundary.sum()))
    clear_wrong, all_wrong, n_boundary = wrong[default]
    assert clear_wrong == 0
    assert all_wrong < 0.06 * n_boundary
    assert wrong[8.0][0] > 0 and all_wrong < 0.7 * wrong[8.0][1]
