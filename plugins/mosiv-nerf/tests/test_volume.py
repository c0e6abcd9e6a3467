"""Volume rendering against analytic cases, and the grid renderer's gradients."""

from __future__ import annotations

import math

import torch
from mosiv_nerf.renderer import particle_grid
from mosiv_nerf.splat import splat
from mosiv_nerf.volume import GridBox, march, trilinear


def uniform_sampler(box: GridBox, sigmas: list[float], colour=(0.2, 0.5, 0.9)):
    """A field of constant per-object densities on ``box`` (trilinear of constant nodes)."""
    nx, ny, nz = box.shape
    nodes = torch.stack([torch.full((nz, ny, nx), s, dtype=torch.float64) for s in sigmas])
    rgb = torch.tensor(colour, dtype=torch.float64)

    def sample(points):
        sigma = trilinear(nodes, box, points)
        return sigma, rgb.expand(*points.shape[:-1], 3)

    return sample


def test_uniform_box_transmittance_is_exp_minus_sigma_length():
    box = GridBox(
        torch.tensor([0.0, 0.0, 0.0], dtype=torch.float64), 0.1, (11, 6, 4)
    )  # 1 x .5 x .3
    sigma = [3.0, 1.5]
    origins = torch.tensor(
        [[-1.0, 0.25, 0.15], [0.5, -2.0, 0.1], [-1.0, -1.0, -1.0], [0.3, 0.2, 5.0]],
        dtype=torch.float64,
    )
    target = torch.tensor([0.8, 0.4, 0.2], dtype=torch.float64)  # a point inside the box
    dirs = torch.nn.functional.normalize(target - origins, dim=1)
    dirs[3] = torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64)  # straight down: chord 0.3
    out = march(uniform_sampler(box, sigma), box, origins, dirs, n_objects=2, step=0.05)
    # chord lengths by the slab method computed independently, in closed form
    lengths = []
    for o, d in zip(origins, dirs):
        t0 = (box.lo - o) / d
        t1 = (box.hi - o) / d
        near, far = float(torch.minimum(t0, t1).max()), float(torch.maximum(t0, t1).min())
        lengths.append(max(0.0, far - max(near, 0.0)))
    expected = torch.tensor([1.0 - math.exp(-sum(sigma) * L) for L in lengths], dtype=torch.float64)
    assert abs(lengths[3] - 0.3) < 1e-12
    torch.testing.assert_close(out.alpha, expected, rtol=1e-10, atol=1e-12)
    # each object's share of the absorbed light is its share of the density
    torch.testing.assert_close(out.object_alpha[0], expected * 2.0 / 3.0, rtol=1e-10, atol=1e-12)
    # a constant colour comes out premultiplied by alpha
    torch.testing.assert_close(out.rgb[:, 1], 0.5 * expected, rtol=1e-10, atol=1e-12)


def test_ray_missing_the_box_is_empty():
    box = GridBox(torch.zeros(3, dtype=torch.float64), 0.1, (5, 5, 5))
    o = torch.tensor([[2.0, 2.0, 2.0]], dtype=torch.float64)
    d = torch.tensor([[1.0, 0.0, 0.0]], dtype=torch.float64)
    out = march(uniform_sampler(box, [5.0]), box, o, d, n_objects=1, step=0.05)
    assert float(out.alpha[0]) == 0.0 and float(out.depth[0]) == 0.0


def test_splat_of_a_lattice_block_reproduces_its_density_inside():
    cell = 0.1
    g = torch.arange(10, dtype=torch.float64) * cell
    x, y, z = torch.meshgrid(g, g, g, indexing="ij")
    pos = torch.stack([x, y, z], -1).reshape(-1, 3) + 0.5 * cell
    box = GridBox.around(pos.min(0).values, pos.max(0).values, cell, margin=3)
    grid = splat(pos, torch.full((pos.shape[0], 1), 7.0, dtype=torch.float64), box)
    # total splatted mass is conserved (partition of unity)
    assert abs(float(grid.sum()) - 7.0 * pos.shape[0]) < 1e-8
    nodes = box.nodes()
    interior = ((nodes > 0.25) & (nodes < 0.75)).all(-1)
    torch.testing.assert_close(grid[0][interior], torch.full_like(grid[0][interior], 7.0))


def grid_loss(positions, camera_rays, colors, ids, target):
    sigma = torch.full((positions.shape[0],), 20.0, dtype=positions.dtype)
    volumes = torch.full_like(sigma, 0.05**3)
    grid = particle_grid(positions, sigma, colors, ids, n_objects=2, cell=0.05, volumes=volumes)
    origins, dirs = camera_rays
    out = march(grid.sample, grid.box, origins, dirs, n_objects=2, step=0.02)
    return ((out.rgb - target) ** 2).sum() + ((out.object_alpha[0] - 0.5) ** 2).sum()


def test_grid_render_gradient_matches_finite_differences():
    gen = torch.Generator().manual_seed(3)
    n = 12
    pos = (torch.rand(n, 3, generator=gen, dtype=torch.float64) * 0.15).requires_grad_(True)
    colors = torch.rand(n, 3, generator=gen, dtype=torch.float64)
    ids = torch.tensor([1] * 6 + [2] * 6)
    ys, zs = torch.meshgrid(
        torch.linspace(0.0, 0.15, 6, dtype=torch.float64),
        torch.linspace(0.0, 0.15, 6, dtype=torch.float64),
        indexing="ij",
    )
    origins = torch.stack([torch.full_like(ys, -1.0), ys, zs], -1).reshape(-1, 3)
    dirs = torch.nn.functional.normalize(
        torch.tensor([1.0, 0.05, 0.03], dtype=torch.float64).expand_as(origins), dim=1
    )
    target = torch.full((origins.shape[0], 3), 0.3, dtype=torch.float64)
    rays = (origins, dirs)
    loss = grid_loss(pos, rays, colors, ids, target)
    (grad,) = torch.autograd.grad(loss, pos)
    eps = 1e-6
    numeric = torch.zeros_like(pos)
    with torch.no_grad():
        for i in range(n):
            for d in range(3):
                p = pos.detach().clone()
                p[i, d] += eps
                up = grid_loss(p, rays, colors, ids, target)
                p[i, d] -= 2 * eps
                down = grid_loss(p, rays, colors, ids, target)
                numeric[i, d] = (up - down) / (2 * eps)
    assert float(grad.abs().max()) > 1e-3  # the positions do move the image
    torch.testing.assert_close(grad, numeric, rtol=1e-4, atol=1e-6)
