"""Plasticine with the fixed-corotated stress: parameters E, nu, yield_stress.

Genesis's ``ElastoPlastic`` material with von Mises yield: plasticine's return map (the
deviatoric Hencky strain kept within yield_stress / 2 mu) under the fixed-corotated stress of
``elastic_corotated`` instead of StVK-Hencky (docs/PHYSICS.md, Genesis's laws).
"""

from __future__ import annotations

import torch

from mosiv_framework.laws.elastic_corotated import corotated_kirchhoff
from mosiv_framework.laws.plasticine import Plasticine

Tensor = torch.Tensor


class PlasticineCorotated(Plasticine):
    """Fixed-corotated stress + von Mises: plastic flow keeps 2 mu ||dev eps|| <= yield_stress."""

    name = "plasticine_corotated"
    description = (
        "elasto-plastic solid with the fixed-corotated stress and von Mises yield, as Genesis's "
        "ElastoPlastic (E, nu, yield_stress)"
    )

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
