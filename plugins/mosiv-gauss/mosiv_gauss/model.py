"""Object-aware dynamic Gaussians: canonical kernels warped by a low-rank deformation (paper
eq. 1, section 3.2 "Dynamic Gaussian reconstruction"; design after DynMF, Kratimenos et al.).

For canonical centre ``mu`` (m) and log-radius ``log r`` of a Gaussian of object ``k``, at the
normalised time ``t`` in [0, 1] (frame / (T - 1)):

    mu_t     = mu + sum_b alpha_b(mu, k) psi^mu_b(t)          (psi^mu_b in R^3, metres)
    log r_t  = log r + sum_b alpha_b(mu, k) psi^r_b(t)

``psi(t)`` comes from the *basis network* (a small MLP of time, B bases, 3 + 1 outputs each) and
``alpha(mu, k)`` from the *coefficient network* (an MLP of the positionally encoded canonical
centre and the one-hot object id). The paper adds the radius residual to r directly; it is added
to log r here so the radius stays positive whatever the networks output. Feeding the object id
to the coefficient network lets two touching objects move differently even where their
canonical centres are close. The coefficient network's output layer starts at zero, so a fresh
model is the identity deformation (the static hull) and the bases still receive gradients.
"""

from __future__ import annotations

import math

import torch
from torch import nn

from mosiv_framework.types import GaussianFrames

Tensor = torch.Tensor


def _mlp(n_in: int, width: int, layers: int, n_out: int) -> nn.Sequential:
    """``layers`` hidden layers of ``width`` units with SiLU, then a linear output layer."""
    mods: list[nn.Module] = []
    for i in range(layers):
        mods += [nn.Linear(n_in if i == 0 else width, width), nn.SiLU()]
    mods.append(nn.Linear(width if layers else n_in, n_out))
    return nn.Sequential(*mods)


def positional_encoding(x: Tensor, n_frequencies: int) -> Tensor:
    """[..., D] -> [..., D (1 + 2L)]: x, sin(2^l pi x), cos(2^l pi x) for l < L (NeRF-style)."""
    if n_frequencies == 0:
        return x
    scales = (2.0 ** torch.arange(n_frequencies, device=x.device, dtype=x.dtype)) * math.pi
    angles = x.unsqueeze(-1) * scales  # [..., D, L]
    return torch.cat([x, angles.sin().flatten(-2), angles.cos().flatten(-2)], dim=-1)


class BasisNetwork(nn.Module):
    """psi(t): normalised time [F] -> per-basis residuals [F, B, 4] (centre m, log-radius)."""

    def __init__(
        self, *, n_bases: int, width: int, layers: int, scale: float, time_frequencies: int = 4
    ) -> None:
        super().__init__()
        self.n_bases = n_bases
        # the highest octave's period is 2 / 2^(L-1) of the clip: it bounds how abrupt a
        # change of motion (an impact) the bases can follow
        self.time_frequencies = time_frequencies
        self.net = _mlp(1 + 2 * self.time_frequencies, width, layers, 4 * n_bases)
        # centre residuals are produced in units of the scene extent, so the weights stay O(1)
        self.register_buffer("scale", torch.tensor([scale, scale, scale, 1.0]))

    def forward(self, t: Tensor) -> Tensor:
        feats = positional_encoding(t.reshape(-1, 1), self.time_frequencies)
        return self.net(feats).reshape(-1, self.n_bases, 4) * self.scale


class CoefficientNetwork(nn.Module):
    """alpha(mu, k): canonical centres [G, 3] (m) and object ids [G] -> coefficients [G, B]."""

    def __init__(
        self,
        *,
        n_bases: int,
        n_objects: int,
        width: int,
        layers: int,
        pe_frequencies: int,
        lower: Tensor,
        upper: Tensor,
    ) -> None:
        super().__init__()
        self.n_objects = n_objects
        self.pe_frequencies = pe_frequencies
        self.register_buffer("centre", (lower + upper) / 2)
        self.register_buffer("half_extent", (upper - lower).max() / 2)
        n_in = 3 * (1 + 2 * pe_frequencies) + n_objects
        self.net = _mlp(n_in, width, layers, n_bases)
        nn.init.zeros_(self.net[-1].weight)
        nn.init.zeros_(self.net[-1].bias)

    def forward(self, mu: Tensor, object_ids: Tensor) -> Tensor:
        x = (mu - self.centre) / self.half_extent  # the domain maps into [-1, 1]^3
        one_hot = nn.functional.one_hot(object_ids - 1, self.n_objects).to(mu.dtype)
        return self.net(torch.cat([positional_encoding(x, self.pe_frequencies), one_hot], -1))


def inverse_sigmoid(p: Tensor) -> Tensor:
    p = p.clamp(1e-4, 1 - 1e-4)
    return torch.log(p / (1 - p))


class DynamicGaussians(nn.Module):
    """Canonical Gaussians plus the two networks of eq. 1; one object id per Gaussian.

    Parameters: means [G, 3] (m), log_radii [G] (log m), color_logits [G, 3] (sigmoid gives
    RGB in [0, 1]), opacity_logits [G] (sigmoid gives opacity); buffer object_ids [G] int64.
    ``n_frames`` T sets the time normalisation t = frame / (T - 1).
    """

    canonical_names = ("means", "log_radii", "color_logits", "opacity_logits")

    def __init__(
        self,
        *,
        means: Tensor,
        radii: Tensor,
        colors: Tensor,
        opacities: Tensor,
        object_ids: Tensor,
        n_objects: int,
        n_frames: int,
        lower,
        upper,
        n_bases: int = 10,
        basis_width: int = 64,
        basis_layers: int = 4,
        coef_width: int = 64,
        coef_layers: int = 4,
        pe_frequencies: int = 4,
        time_frequencies: int = 4,
    ) -> None:
        super().__init__()
        if n_frames < 1:
            raise ValueError(f"n_frames={n_frames}: a dynamic model needs at least one frame")
        device = means.device
        self.n_objects = n_objects
        self.n_frames = n_frames
        self.means = nn.Parameter(means.detach().clone().float())
        self.log_radii = nn.Parameter(radii.detach().float().log())
        self.color_logits = nn.Parameter(inverse_sigmoid(colors.detach().float()))
        self.opacity_logits = nn.Parameter(inverse_sigmoid(opacities.detach().float()))
        self.register_buffer("object_ids", object_ids.detach().long().clone())
        lo = torch.as_tensor(lower, dtype=torch.float32, device=device)
        hi = torch.as_tensor(upper, dtype=torch.float32, device=device)
        self.basis = BasisNetwork(
            n_bases=n_bases,
            width=basis_width,
            layers=basis_layers,
            scale=float((hi - lo).max()),
            time_frequencies=time_frequencies,
        ).to(device)
        self.coefficients = CoefficientNetwork(
            n_bases=n_bases,
            n_objects=n_objects,
            width=coef_width,
            layers=coef_layers,
            pe_frequencies=pe_frequencies,
            lower=lo,
            upper=hi,
        ).to(device)

    # ------------------------------------------------------------------ canonical attributes
    @property
    def n_gaussians(self) -> int:
        return self.means.shape[0]

    def colors(self) -> Tensor:
        return torch.sigmoid(self.color_logits)

    def opacities(self) -> Tensor:
        return torch.sigmoid(self.opacity_logits)

    def network_parameters(self) -> list[nn.Parameter]:
        return [*self.basis.parameters(), *self.coefficients.parameters()]

    def canonical_parameters(self) -> list[nn.Parameter]:
        return [getattr(self, name) for name in self.canonical_names]

    # -------------------------------------------------------------------------- deformation
    def normalised_time(self, frames: Tensor) -> Tensor:
        frames = torch.as_tensor(frames, dtype=self.means.dtype, device=self.means.device)
        return frames / max(1, self.n_frames - 1)

    def residuals(self, frames) -> Tensor:
        """sum_b alpha_b(mu, k) psi_b(t) for each frame: [F, G, 4] (centre m, log-radius)."""
        psi = self.basis(self.normalised_time(frames))  # [F, B, 4]
        alpha = self.coefficients(self.means, self.object_ids)  # [G, B]
        return torch.einsum("gb,fbc->fgc", alpha, psi)  # eq. 1, both sums at once

    def at(self, frames) -> tuple[Tensor, Tensor]:
        """Deformed centres [F, G, 3] (m) and radii [F, G] (m) at the given frame indices."""
        res = self.residuals(frames)
        means = self.means.unsqueeze(0) + res[..., :3]
        radii = torch.exp(self.log_radii.unsqueeze(0) + res[..., 3])
        return means, radii

    def frames(self, frames=None) -> GaussianFrames:
        """The model as GaussianFrames (differentiable) at ``frames`` (default: every frame)."""
        if frames is None:
            frames = list(range(self.n_frames))
        means, radii = self.at(frames)
        return GaussianFrames(
            means=means,
            radii=radii,
            colors=self.colors(),
            opacities=self.opacities(),
            object_ids=self.object_ids,
        )

    # ------------------------------------------------------------------ densify / prune
    @torch.no_grad()
    def reindex(self, index: Tensor, *, means: Tensor | None = None, log_radii=None) -> None:
        """Keep Gaussian ``index[i]`` as the new Gaussian i (duplicates allowed, for cloning),
        optionally with new centres/log-radii [len(index)]; parameters are replaced."""
        for name in self.canonical_names:
            old = getattr(self, name)
            new = old.data[index].clone()
            if name == "means" and means is not None:
                new = means.detach().clone()
            if name == "log_radii" and log_radii is not None:
                new = log_radii.detach().clone()
            setattr(self, name, nn.Parameter(new))
        self.object_ids = self.object_ids[index].clone()
