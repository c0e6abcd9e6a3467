"""Elastic solid with the fixed-corotated stress (Stomakhin et al. 2012), parameters E and nu.

The same parameters as ``elastic`` and the same small-strain behaviour, but the stress the
Genesis engine's ``Elastic`` material uses by default, so that scenes Genesis made can be fitted
with the law that made them (docs/PHYSICS.md, Genesis's laws). Snow is this stress hardened by
compaction and reuses ``corotated_kirchhoff``.
"""

from __future__ import annotations

import torch

from mosiv_framework.laws.base import ConstitutiveLaw, lame_parameters
from mosiv_framework.laws.elastic import POISSON_RATIO, YOUNGS_MODULUS
from mosiv_framework.laws.linalg import (
    gather_params,
    identity_like,
    plastic_j_or_ones,
    polar_rotation,
)

Tensor = torch.Tensor


def corotated_kirchhoff(F: Tensor, mu: Tensor, lam: Tensor) -> Tensor:
    """Fixed-corotated Kirchhoff stress tau = 2 mu (F - R) F^T + lam (J - 1) J I (Pa), [N, 3, 3],
    with R the rotation of the polar decomposition F = R S (proper even where det F < 0)."""
    R = polar_rotation(F)
    J = torch.linalg.det(F)
    shear = 2.0 * mu[:, None, None] * (F - R) @ F.transpose(-1, -2)
    return shear + (lam * (J - 1.0) * J)[:, None, None] * identity_like(F)


class ElasticCorotated(ConstitutiveLaw):
    """Fixed-corotated: tau = 2 mu (F - R) F^T + lam (J - 1) J I; no plasticity."""

    name = "elastic_corotated"
    params = (YOUNGS_MODULUS, POISSON_RATIO)
    description = "elastic solid with the fixed-corotated stress, as Genesis's Elastic (E, nu)"

    def derived(
        self, values: dict[str, Tensor], *, like: Tensor | None = None
    ) -> dict[str, Tensor]:
        """Lame constants mu, lam (Pa) from E (Pa) and nu; [N] when like=F."""
        E, nu = gather_params(values, ("E", "nu"), like=like, law=self.name)
        mu, lam = lame_parameters(E, nu)
        return {"mu": mu, "lam": lam}

    def kirchhoff_stress(
        self,
        F: Tensor,
        values: dict[str, Tensor],
        *,
        plastic_J: Tensor | None = None,
        velocity_gradient: Tensor | None = None,
    ) -> Tensor:
        d = self.derived(values, like=F)
        return corotated_kirchhoff(F, d["mu"], d["lam"])

    def return_map(
        self,
        F: Tensor,
        values: dict[str, Tensor],
        *,
        plastic_J: Tensor | None = None,
        dt: float = 0.0,
    ) -> tuple[Tensor, Tensor]:
        # Purely elastic: every F is admissible.
        return F, plastic_j_or_ones(plastic_J, like=F)
