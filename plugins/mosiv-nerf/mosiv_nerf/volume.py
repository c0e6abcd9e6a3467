"""Differentiable volume rendering through an axis-aligned voxel box (torch, CPU or GPU).

A ray r(t) = o + t d (unit d) is clipped to the box [lo, hi] by the slab method and sampled at
S points t_i = t_near + (i + u_i) delta, delta = (t_far - t_near) / S, so the samples of every
ray cover exactly its chord through the box. With per-object densities sigma_k (1/m) and a
colour c at each sample, the emission-absorption quadrature is

    a_i = 1 - exp(-sigma_i delta),  sigma_i = sum_k sigma_k,i,
    T_i = exp(-sum_{j<i} sigma_j delta),  w_i = T_i a_i,
    C = sum_i w_i c_i,  alpha = sum_i w_i = 1 - exp(-sum_i sigma_i delta),
    alpha_k = sum_i w_i sigma_k,i / sigma_i  (the share of the absorbed light due to object k).

For a constant density the quadrature is exact: alpha = 1 - exp(-sigma L) over a chord of
length L. Grids are stored as [C, Nz, Ny, Nx] with node (i, j, l) at lo + (l, j, i) * cell, the
layout ``torch.nn.functional.grid_sample`` reads trilinearly with ``align_corners=True``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch
import torch.nn.functional as F

Tensor = torch.Tensor

#: a sampler maps points [R, S, 3] (m) to (per-object density [K, R, S] in 1/m, rgb [R, S, 3])
Sampler = Callable[[Tensor], tuple[Tensor, Tensor]]


@dataclass
class GridBox:
    """An axis-aligned lattice: ``lo`` [3] (m) is node 0, ``cell`` the spacing (m), ``shape``
    the node counts (nx, ny, nz)."""

    lo: Tensor
    cell: float
    shape: tuple[int, int, int]

    @property
    def hi(self) -> Tensor:
        n = torch.tensor(self.shape, dtype=self.lo.dtype, device=self.lo.device)
        return self.lo + (n - 1) * self.cell

    def nodes(self) -> Tensor:
        """Node positions [Nz, Ny, Nx, 3] (m)."""
        axes = [
            self.lo[d] + self.cell * torch.arange(n, dtype=self.lo.dtype, device=self.lo.device)
            for d, n in enumerate(self.shape)
        ]
        z, y, x = torch.meshgrid(axes[2], axes[1], axes[0], indexing="ij")
        return torch.stack([x, y, z], dim=-1)

    @classmethod
    def around(cls, lower: Tensor, upper: Tensor, cell: float, margin: int = 2) -> GridBox:
        """The lattice of spacing ``cell`` covering [lower, upper] with ``margin`` extra nodes
        on every side."""
        lo = lower - margin * cell
        n = torch.ceil((upper - lower) / cell).long() + 2 * margin + 1
        return cls(lo, float(cell), tuple(int(v) for v in n.clamp(min=2)))


def trilinear(volume: Tensor, box: GridBox, points: Tensor) -> Tensor:
    """Trilinear samples of ``volume`` [C, Nz, Ny, Nx] at ``points`` [..., 3] -> [C, ...];
    differentiable in both. Points outside the box read the border nodes."""
    lead = points.shape[:-1]
    norm = 2.0 * (points - box.lo.to(points)) / (box.hi - box.lo).to(points) - 1.0
    grid = norm.reshape(1, -1, 1, 1, 3).to(volume.dtype)
    out = F.grid_sample(
        volume[None], grid, mode="bilinear", padding_mode="border", align_corners=True
    )
    return out.reshape(volume.shape[0], *lead)


def ray_box(origins: Tensor, dirs: Tensor, lo: Tensor, hi: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Slab intersection of rays [R, 3] with the box [lo, hi]: (t_near [R], t_far [R], hit [R]).

    t_near is clamped at 0 (cameras inside the box start at their centre)."""
    safe = torch.where(dirs.abs() < 1e-12, torch.full_like(dirs, 1e-12), dirs)
    t0 = (lo.to(origins) - origins) / safe
    t1 = (hi.to(origins) - origins) / safe
    near = torch.minimum(t0, t1).amax(dim=-1).clamp(min=0.0)
    far = torch.maximum(t0, t1).amin(dim=-1)
    return near, far, far > near


@dataclass
class RayImage:
    """Rendered rays: rgb [R, 3], alpha [R], depth [R] (m along the ray), object_alpha [K, R]."""

    rgb: Tensor
    alpha: Tensor
    depth: Tensor
    object_alpha: Tensor


def march(
    sampler: Sampler,
    box: GridBox,
    origins: Tensor,
    dirs: Tensor,
    *,
    n_objects: int,
    step: float,
    generator: torch.Generator | None = None,
    max_samples: int = 1024,
) -> RayImage:
    """Render rays [R, 3] through the field ``sampler`` defined inside ``box``.

    Args:
        step: nominal sample spacing (m); the sample count S = ceil(box diagonal / step) is
            shared by all rays, each spreading its S samples over its own chord.
        generator: with a generator, samples are jittered inside their interval (training);
            without one they sit at interval centres (deterministic renders).
        max_samples: upper bound on S (memory).
    Returns:
        RayImage; rays that miss the box are empty (alpha 0, rgb 0, depth 0).
    """
    r = origins.shape[0]
    near, far, hit = ray_box(origins, dirs, box.lo, box.hi)
    diag = float((box.hi - box.lo).norm())
    s = int(max(1, min(max_samples, -(-diag // step))))
    length = torch.where(hit, far - near, torch.zeros_like(far))
    delta = length / s  # [R]
    if generator is None:
        u = torch.full((r, s), 0.5, dtype=origins.dtype, device=origins.device)
    else:
        u = torch.rand((r, s), generator=generator, device=generator.device).to(origins)
    idx = torch.arange(s, dtype=origins.dtype, device=origins.device)
    t = near[:, None] + (idx[None] + u) * delta[:, None]  # [R, S]
    points = origins[:, None, :] + t[..., None] * dirs[:, None, :]
    sigma_k, rgb = sampler(points)  # [K, R, S], [R, S, 3]
    if sigma_k.shape[0] != n_objects:
        raise ValueError(f"sampler gave {sigma_k.shape[0]} density channels for {n_objects}")
    return composite(sigma_k, rgb, t, delta)


def composite(sigma_k: Tensor, rgb: Tensor, t: Tensor, delta: Tensor) -> RayImage:
    """Emission-absorption quadrature of densities [K, R, S] and colours [R, S, 3] at ray
    parameters t [R, S] with per-ray spacing delta [R] (module docstring)."""
    sigma = sigma_k.sum(dim=0)  # [R, S]
    tau = sigma * delta[:, None]
    # exclusive cumulative optical depth: light reaching sample i
    before = torch.cumsum(tau, dim=1) - tau
    weights = torch.exp(-before) * (1.0 - torch.exp(-tau))  # [R, S]
    alpha = weights.sum(dim=1)
    out_rgb = (weights[..., None] * rgb).sum(dim=1)
    depth = (weights * t).sum(dim=1) / alpha.clamp(min=1e-8)
    share = sigma_k / sigma.clamp(min=1e-12)[None]
    object_alpha = (weights[None] * share).sum(dim=2)
    return RayImage(
        out_rgb, alpha, torch.where(alpha > 1e-6, depth, torch.zeros_like(depth)), object_alpha
    )
