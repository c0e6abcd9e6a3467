"""Appearance carried to simulation: Gaussians bound to the particles of their object.

Each Gaussian g of object k is bound to its ``k_nn`` nearest rest-state particles of the same
object with normalised inverse-distance weights ``w_gi = (d_gi + eps)^-p / sum_j (d_gj + eps)^-p``.
A simulated particle state moves it by the weighted particle displacement:

    mu_g(x) = mu_g(rest) + sum_i w_gi (x_i - x_i(rest))

Because the weights sum to one, a rigid translation of the particles moves every Gaussian by
exactly that translation; radii, colours and opacities stay those of frame 0. The map is linear
in the particle positions, so silhouettes rendered from it are differentiable with respect to
the simulated state.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from scipy.spatial import cKDTree

from mosiv_framework.types import GaussianFrames

Tensor = torch.Tensor


@dataclass
class GaussianBinding:
    """Frame-0 Gaussians and the particles they follow.

    rest_means [G, 3] m, radii [G] m, colors [G, 3], opacities [G], object_ids [G] int64: the
    frame-0 Gaussians; rest_positions [N, 3] m: the particles at rest; neighbors [G, k] int64:
    indices into the particles; weights [G, k]: interpolation weights (rows sum to 1).
    """

    rest_means: Tensor
    radii: Tensor
    colors: Tensor
    opacities: Tensor
    object_ids: Tensor
    rest_positions: Tensor
    neighbors: Tensor
    weights: Tensor

    @property
    def n_objects(self) -> int:
        return int(self.object_ids.max())

    def means(self, positions: Tensor) -> Tensor:
        """Gaussian centres (m) for particle positions [N, 3] -> [G, 3], or [T, N, 3] ->
        [T, G, 3]; differentiable with respect to ``positions``."""
        if positions.shape[-2:] != self.rest_positions.shape:
            raise ValueError(
                f"positions must be [..., {self.rest_positions.shape[0]}, 3] (the lifted "
                f"particles), got {list(positions.shape)}"
            )
        rest = self.rest_positions.to(positions)
        displacement = positions - rest
        moved = displacement[..., self.neighbors.to(positions.device), :]  # [..., G, k, 3]
        shift = (self.weights.to(positions)[..., None] * moved).sum(dim=-2)
        return self.rest_means.to(positions) + shift

    def gaussian_frames(self, positions: Tensor) -> GaussianFrames:
        """The bound Gaussians at particle states [T, N, 3] (or one state [N, 3])."""
        if positions.ndim == 2:
            positions = positions[None]
        means = self.means(positions)
        t = means.shape[0]
        dev = means.device
        return GaussianFrames(
            means=means,
            radii=self.radii.to(dev, means.dtype).expand(t, -1),
            colors=self.colors.to(dev, means.dtype),
            opacities=self.opacities.to(dev, means.dtype),
            object_ids=self.object_ids.to(dev),
        )

    def render(self, positions: Tensor, camera, renderer, *, n_objects: int, background=None):
        """Render one particle state [N, 3] through ``camera`` with a Renderer component."""
        frames = self.gaussian_frames(positions)
        if background is None:
            return renderer.render(frames, camera, frame=0, n_objects=n_objects)
        return renderer.render(frames, camera, frame=0, n_objects=n_objects, background=background)


def bind_gaussians(
    gaussians: GaussianFrames,
    positions: Tensor,
    object_ids: Tensor,
    *,
    neighbors: int,
    power: float,
) -> GaussianBinding:
    """Bind frame 0 of ``gaussians`` to particles (positions [N, 3] m, object_ids [N]) of the
    same object; ``neighbors`` particles per Gaussian, weights (d + eps)^-power."""
    rest_means = gaussians.means[0].detach().float()
    g_ids = gaussians.object_ids
    pos = positions.detach().double().numpy()
    p_ids = object_ids.numpy()
    g = rest_means.shape[0]
    nbr = np.zeros((g, neighbors), dtype=np.int64)
    w = np.zeros((g, neighbors), dtype=np.float64)
    for k in torch.unique(g_ids).tolist():
        members = np.nonzero(p_ids == k)[0]
        if not len(members):
            raise ValueError(
                f"Gaussians of object {k} cannot be bound: the particles have no object {k} "
                f"(particle objects: {sorted(set(p_ids.tolist()))})"
            )
        rows = torch.nonzero(g_ids == k).squeeze(1).numpy()
        kk = min(neighbors, len(members))
        d, j = cKDTree(pos[members]).query(rest_means[rows].double().numpy(), k=kk)
        d, j = d.reshape(len(rows), kk), j.reshape(len(rows), kk)
        # eps: a fraction of the particle spacing scale keeps coincident points finite
        eps = 1e-6 + 1e-3 * float(np.median(d[:, 0])) if len(d) else 1e-6
        raw = (d + eps) ** (-power)
        # pad to ``neighbors`` columns with zero weight when an object has too few particles
        nbr[rows, :kk] = members[j]
        nbr[rows, kk:] = members[j[:, :1]]
        w[rows, :kk] = raw / raw.sum(axis=1, keepdims=True)
    return GaussianBinding(
        rest_means=rest_means,
        radii=gaussians.radii[0].detach().float(),
        colors=gaussians.colors.detach().float(),
        opacities=gaussians.opacities.detach().float(),
        object_ids=g_ids.clone(),
        rest_positions=positions.detach().float().clone(),
        neighbors=torch.from_numpy(nbr),
        weights=torch.from_numpy(w).float(),
    )
