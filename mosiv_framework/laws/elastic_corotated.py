"""Elastic solid with the fixed-corotated stress (Stomakhin et al. 2012), parameters E and nu.

The same parameters as ``elastic`` and the same small-strain behaviour, but the stress the
Genesis engine's ``Elastic`` material uses by default, so that scenes Genesis made can be fitted
with the law that made them (docs/PHYSICS.md, Genesis's laws). Snow is this stress hardened by
compaction and reuses ``corotated_kirchhoff``.
"""

from __future__ import annotations

import torch

from mosiv_framework.laws.elastic import Elastic
from mosiv_framework.laws.linalg import identity_like, polar_rotation

Tensor = torch.Tensor


def corotated_kirchhoff(F: Tensor, mu: Tensor, lam: Tensor) -> Tensor:
    """Fixed-corotated Kirchhoff stress tau = 2 mu (F - R) F^T + lam (J - 1) J I (Pa), [N, 3, 3],
    with R the rotation of the polar decomposition F = R S (proper even where det F < 0)."""
    R = polar_rotation(F)
    J = torch.linalg.det(F)
    shear = 2.0 * mu[:, None, None] * (F - R) @ F.transpose(-1, -2)
    return shear + (lam * (J - 1.0) * J)[:, None, None] * identity_like(F)


class ElasticCorotated(Elastic):
    """Fixed-corotated: tau = 2 mu (F - R) F^T + lam (J - 1) J I; no plasticity (the elastic
    law's parameters, Lame constants and return map, another stress)."""

    name = "elastic_corotated"
    description = "elastic solid with the fixed-corotated stress, as Genesis's Elastic (E, nu)"

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
