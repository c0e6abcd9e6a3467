"""Plasticine: StVK-Hencky elasticity + von Mises yield surface; parameters E, nu, yield_stress.

Also defines the StVK-Hencky stress and the deviatoric return map that sand and non_newtonian
reuse.
"""

from __future__ import annotations

from collections.abc import Callable

import torch

from mosiv_framework.laws.base import ConstitutiveLaw, ParamSpec, lame_parameters
from mosiv_framework.laws.elastic import POISSON_RATIO, YOUNGS_MODULUS
from mosiv_framework.laws.linalg import (
    deviatoric,
    gather_params,
    hencky_strain,
    plastic_j_or_ones,
    safe_norm,
    svd_map,
)

Tensor = torch.Tensor


def _hencky_principal_stress(s: Tensor, mu: Tensor, lam: Tensor) -> Tensor:
    # Principal Kirchhoff stresses of StVK-Hencky: 2 mu eps + lam tr(eps), eps = log(s).
    eps = hencky_strain(s)
    return 2.0 * mu[:, None] * eps + (lam * eps.sum(dim=-1))[:, None]


def hencky_kirchhoff(F: Tensor, mu: Tensor, lam: Tensor) -> Tensor:
    """StVK-Hencky Kirchhoff stress tau = U diag(2 mu eps + lam tr(eps)) U^T (Pa), [N, 3, 3]."""
    G, R, _ = svd_map(F, _hencky_principal_stress, mu, lam)
    return G @ R.transpose(-1, -2)  # U diag(.) V^T V U^T


def deviatoric_flow(s: Tensor, excess: Tensor) -> tuple[Tensor, Tensor]:
    """New singular values after removing ``excess`` [N] of deviatoric Hencky strain where > 0.

    eps <- eps - dg e / ||e|| with e = dev(eps) (tr eps unchanged); returns (s_new, flowed).
    """
    eps = hencky_strain(s)
    e = deviatoric(eps)
    step = torch.clamp(excess, min=0.0)  # also keeps the unused branch finite for torch.where
    eps_new = eps - step[:, None] * e / safe_norm(e)[:, None]
    flowed = excess > 0
    return torch.where(flowed[:, None], torch.exp(eps_new), s), flowed


def isotropic_return(
    F: Tensor, flow: Callable[..., tuple[Tensor, Tensor]], *params: Tensor
) -> Tensor:
    """F_new = U diag(s_new) V^T with (s_new, flowed) = flow(s, *params); F kept exactly where
    nothing flowed (so elastic states are untouched and their gradient is the identity)."""
    G, _, s = svd_map(F, lambda s_, *p: flow(s_, *p)[0], *params)
    _, flowed = flow(s, *(p.detach() for p in params))
    return torch.where(flowed[:, None, None], G, F)


def _von_mises(s: Tensor, radius: Tensor) -> tuple[Tensor, Tensor]:
    # von Mises: dg = ||dev eps|| - yield_stress / (2 mu)
    return deviatoric_flow(s, safe_norm(deviatoric(hencky_strain(s))) - radius)


class HenckyElastic(ConstitutiveLaw):
    """Laws whose elastic part is StVK-Hencky (plasticine, sand, non_newtonian): the stress
    comes from the Lame constants ``mu``, ``lam`` that each law's ``derived`` provides."""

    def kirchhoff_stress(
        self,
        F: Tensor,
        values: dict[str, Tensor],
        *,
        plastic_J: Tensor | None = None,
        velocity_gradient: Tensor | None = None,
    ) -> Tensor:
        d = self.derived(values, like=F)
        return hencky_kirchhoff(F, d["mu"], d["lam"])


class Plasticine(HenckyElastic):
    """StVK-Hencky + von Mises: plastic flow keeps 2 mu ||dev eps|| <= yield_stress."""

    name = "plasticine"
    params = (
        YOUNGS_MODULUS,
        POISSON_RATIO,
        ParamSpec(
            "yield_stress", "Pa", 10.0, 1e6, 2e3, log_scale=True, description="von Mises yield"
        ),
    )
    description = "StVK-Hencky elasto-plastic solid with von Mises yield (E, nu, yield_stress)"

    def derived(
        self, values: dict[str, Tensor], *, like: Tensor | None = None
    ) -> dict[str, Tensor]:
        """Lame constants mu, lam (Pa) and the yield stress (Pa); [N] when like=F."""
        E, nu, ys = gather_params(values, ("E", "nu", "yield_stress"), like=like, law=self.name)
        mu, lam = lame_parameters(E, nu)
        return {"mu": mu, "lam": lam, "yield_stress": ys}

    def return_map(
        self,
        F: Tensor,
        values: dict[str, Tensor],
        *,
        plastic_J: Tensor | None = None,
        dt: float = 0.0,
    ) -> tuple[Tensor, Tensor]:
        d = self.derived(values, like=F)
        radius = d["yield_stress"] / (2.0 * d["mu"])  # von Mises radius in strain space
        return isotropic_return(F, _von_mises, radius), plastic_j_or_ones(plastic_J, like=F)
