"""Newtonian fluid: weakly compressible (Tait-like pressure) with linear viscosity.

Parameters: viscosity (Pa s) and bulk_modulus (Pa). Only the volume change of F is remembered.
"""

from __future__ import annotations

import torch

from mosiv_framework.laws.base import ConstitutiveLaw, ParamSpec
from mosiv_framework.laws.linalg import gather_params, identity_like, plastic_j_or_ones, safe_det

Tensor = torch.Tensor


class Newtonian(ConstitutiveLaw):
    """tau = J viscosity (L + L^T) + (bulk_modulus / 7) (J - J^-6) I; F <- J^(1/3) I."""

    name = "newtonian"
    params = (
        ParamSpec("viscosity", "Pa*s", 1e-3, 1e4, 10.0, log_scale=True, description="dynamic"),
        ParamSpec(
            "bulk_modulus", "Pa", 1e3, 1e7, 5e4, log_scale=True, description="small-strain bulk"
        ),
    )
    description = "weakly compressible Newtonian fluid (viscosity, bulk_modulus)"
    uses_velocity_gradient = True

    def derived(
        self, values: dict[str, Tensor], *, like: Tensor | None = None
    ) -> dict[str, Tensor]:
        """Viscosity (Pa s) and bulk modulus (Pa); [N] when like=F."""
        visc, kappa = gather_params(values, ("viscosity", "bulk_modulus"), like=like, law=self.name)
        return {"viscosity": visc, "bulk_modulus": kappa}

    def kirchhoff_stress(
        self,
        F: Tensor,
        values: dict[str, Tensor],
        *,
        plastic_J: Tensor | None = None,
        velocity_gradient: Tensor | None = None,
    ) -> Tensor:
        if velocity_gradient is None:
            raise ValueError(
                "law 'newtonian' needs velocity_gradient (the particle's affine matrix C, 1/s, "
                "[N, 3, 3]) because its viscous stress depends on the strain rate"
            )
        d = self.derived(values, like=F)
        J = safe_det(F)
        L = velocity_gradient
        viscous = (J * d["viscosity"])[:, None, None] * (L + L.transpose(-1, -2))
        # Tait equation with exponent 7, scaled by 1/7 so d(pressure)/dJ = -bulk_modulus at J = 1.
        pressure_term = d["bulk_modulus"] / 7.0 * (J - J.pow(-6))
        return viscous + pressure_term[:, None, None] * identity_like(F)

    def return_map(
        self,
        F: Tensor,
        values: dict[str, Tensor],
        *,
        plastic_J: Tensor | None = None,
        dt: float = 0.0,
    ) -> tuple[Tensor, Tensor]:
        # A fluid forgets its shape: keep only the volume ratio J of F.
        J = safe_det(F)
        F_new = J.pow(1.0 / 3.0)[:, None, None] * identity_like(F)
        return F_new, plastic_j_or_ones(plastic_J, like=F)
