"""Non-Newtonian viscoplastic material (Bingham / Herschel-Bulkley-like, as in PAC-NeRF).

Parameters: shear_modulus mu (Pa), bulk_modulus kappa (Pa), yield_stress (Pa) and
plastic_viscosity eta (Pa s). Beyond the von Mises surface the strain relaxes at a finite rate
set by eta; eta -> 0 recovers plasticine's instantaneous projection.
"""

from __future__ import annotations

import torch

from mosiv_framework.laws.base import ParamSpec
from mosiv_framework.laws.linalg import (
    deviatoric,
    gather_params,
    hencky_strain,
    plastic_j_or_ones,
    safe_norm,
)
from mosiv_framework.laws.plasticine import HenckyElastic, deviatoric_flow, isotropic_return

Tensor = torch.Tensor


def _viscoplastic(s: Tensor, radius: Tensor, relax: Tensor) -> tuple[Tensor, Tensor]:
    # dg = (||dev eps|| - yield_stress / (2 mu)) / (1 + eta / (2 mu dt))
    return deviatoric_flow(s, (safe_norm(deviatoric(hencky_strain(s))) - radius) * relax)


class NonNewtonian(HenckyElastic):
    """StVK-Hencky with viscoplastic (rate-dependent) von Mises flow."""

    name = "non_newtonian"
    params = (
        ParamSpec("shear_modulus", "Pa", 1e2, 1e6, 1e4, log_scale=True, description="mu"),
        ParamSpec("bulk_modulus", "Pa", 1e3, 1e7, 5e4, log_scale=True, description="kappa"),
        ParamSpec("yield_stress", "Pa", 10.0, 1e5, 500.0, log_scale=True, description="yield"),
        ParamSpec("plastic_viscosity", "Pa*s", 1e-3, 1e3, 1.0, log_scale=True, description="eta"),
    )
    description = (
        "viscoplastic fluid (shear_modulus, bulk_modulus, yield_stress, plastic_viscosity)"
    )

    def derived(
        self, values: dict[str, Tensor], *, like: Tensor | None = None
    ) -> dict[str, Tensor]:
        """mu = shear_modulus, lam = kappa - 2 mu / 3 (Pa), yield_stress (Pa), eta (Pa s)."""
        names = ("shear_modulus", "bulk_modulus", "yield_stress", "plastic_viscosity")
        mu, kappa, ys, eta = gather_params(values, names, like=like, law=self.name)
        return {"mu": mu, "lam": kappa - 2.0 * mu / 3.0, "yield_stress": ys, "eta": eta}

    def return_map(
        self,
        F: Tensor,
        values: dict[str, Tensor],
        *,
        plastic_J: Tensor | None = None,
        dt: float = 0.0,
    ) -> tuple[Tensor, Tensor]:
        if not dt > 0.0:
            raise ValueError(
                f"law 'non_newtonian' needs the substep dt > 0 (s) in return_map, got dt={dt!r}: "
                "its plastic flow is rate-dependent"
            )
        d = self.derived(values, like=F)
        two_mu = 2.0 * d["mu"]
        radius = d["yield_stress"] / two_mu
        # 1 / (1 + eta / (2 mu dt)), written so that eta = 0 gives exactly 1 (von Mises).
        relax = two_mu * dt / (two_mu * dt + d["eta"])

        return isotropic_return(F, _viscoplastic, radius, relax), plastic_j_or_ones(
            plastic_J, like=F
        )
