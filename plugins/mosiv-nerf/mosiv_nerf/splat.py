"""Particle-to-grid transfer (P2G) of particle quantities onto a voxel lattice, differentiable in
the particle positions and values.

Each particle p at x_p spreads a value v_p onto nearby nodes i with weights w_ip that sum to one
(partition of unity), like the MPM's particle-to-grid step:

- ``bspline``: the quadratic B-spline of MLS-MPM, 3 nodes per axis, C1 in x_p, so the
  gradient of a render with respect to particle positions is continuous;
- ``trilinear``: linear hat functions, 2 nodes per axis, continuous but with kinks at nodes.

``splat`` returns sum_p w_ip v_p per node. The grid renderer turns particle densities into node
densities with v_p = sigma_p V_p / cell^3, so a uniform block of particles of density sigma and
volume cell^3 each gives nodes of density sigma in its interior.
"""

from __future__ import annotations

import itertools

import torch

from mosiv_framework.errors import ConfigError
from mosiv_nerf.volume import GridBox

Tensor = torch.Tensor

KERNELS = ("bspline", "trilinear")


def _axis_weights(xi: Tensor, kernel: str) -> tuple[Tensor, Tensor]:
    """Per-axis (first node index [N, 3] int64, weights [N, 3, n] over n consecutive nodes)
    for positions ``xi`` in grid units."""
    if kernel == "bspline":
        base = torch.floor(xi - 0.5).detach()
        fx = xi - base  # in [0.5, 1.5)
        w = torch.stack(
            [0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1.0) ** 2, 0.5 * (fx - 0.5) ** 2], dim=-1
        )
    elif kernel == "trilinear":
        base = torch.floor(xi).detach()
        fx = xi - base
        w = torch.stack([1.0 - fx, fx], dim=-1)
    else:
        raise ConfigError(f"splat kernel must be one of {list(KERNELS)}, got {kernel!r}")
    return base.long(), w


def kernel_reach(kernel: str) -> int:
    """Nodes past a particle's cell that its kernel touches (margin a grid needs)."""
    return 2 if kernel == "bspline" else 1


def splat(positions: Tensor, values: Tensor, box: GridBox, *, kernel: str = "bspline") -> Tensor:
    """P2G of ``values`` [N, C] at ``positions`` [N, 3] (m) onto ``box``: [C, Nz, Ny, Nx].

    Contributions that fall on nodes outside the box are dropped; build the box with
    ``GridBox.around`` and a margin of ``kernel_reach(kernel)`` so none do.
    """
    nx, ny, nz = box.shape
    xi = (positions - box.lo.to(positions)) / box.cell
    base, w = _axis_weights(xi, kernel)
    n_off = w.shape[-1]
    flat = values.new_zeros(nz * ny * nx, values.shape[1])
    for a, b, c in itertools.product(range(n_off), repeat=3):
        ix, iy, iz = base[:, 0] + a, base[:, 1] + b, base[:, 2] + c
        inside = (ix >= 0) & (ix < nx) & (iy >= 0) & (iy < ny) & (iz >= 0) & (iz < nz)
        weight = w[:, 0, a] * w[:, 1, b] * w[:, 2, c] * inside.to(w.dtype)
        index = ((iz.clamp(0, nz - 1) * ny + iy.clamp(0, ny - 1)) * nx) + ix.clamp(0, nx - 1)
        flat = flat.index_add(0, index, values * weight[:, None])
    return flat.T.reshape(values.shape[1], nz, ny, nx)
