"""Sand: StVK-Hencky elasticity with a Drucker-Prager cone (Klar et al. 2016).

Parameters: friction_angle (deg), E, nu. Expansion loses all elastic strain (cohesionless);
compression is projected back onto the cone ||dev eps|| + alpha (3 lam + 2 mu) tr(eps) / (2 mu) = 0.
"""

from __future__ import annotations

import math

import torch

from mosiv_framework.laws.base import ParamSpec, lame_parameters
from mosiv_framework.laws.elastic import YOUNGS_MODULUS
from mosiv_framework.laws.linalg import (
    deviatoric,
    gather_params,
    hencky_strain,
    plastic_j_or_ones,
    safe_norm,
)
from mosiv_framework.laws.plasticine import HenckyElastic, deviatoric_flow, isotropic_return

Tensor = torch.Tensor


def _drucker_prager(s: Tensor, slope: Tensor) -> tuple[Tensor, Tensor]:
    eps = hencky_strain(s)
    tr_eps = eps.sum(dim=-1)
    # Klar 2016: dg = ||dev eps|| + alpha (3 lam + 2 mu) tr(eps) / (2 mu); slope = the factor of tr
    s_cone, on_cone = deviatoric_flow(s, safe_norm(deviatoric(eps)) + slope * tr_eps)
    # Tension: a cohesionless material carries none, so all stretch is plastic (s <- 1).
    expanded = tr_eps > 0
    return torch.where(expanded[:, None], torch.ones_like(s), s_cone), expanded | on_cone


class Sand(HenckyElastic):
    """Drucker-Prager sand: no tension, shear bounded by the friction cone."""

    name = "sand"
    params = (
        ParamSpec("friction_angle", "deg", 5.0, 60.0, 30.0, description="internal friction angle"),
        YOUNGS_MODULUS,
        ParamSpec("nu", "1", 0.0, 0.45, 0.3, description="Poisson ratio"),
    )
    description = "Drucker-Prager granular material (friction_angle, E, nu)"

    def derived(
        self, values: dict[str, Tensor], *, like: Tensor | None = None
    ) -> dict[str, Tensor]:
        """mu, lam (Pa) and cone slope alpha = sqrt(2/3) 2 sin(phi) / (3 - sin(phi)); [N] if like=F."""
        phi_deg, E, nu = gather_params(
            values, ("friction_angle", "E", "nu"), like=like, law=self.name
        )
        mu, lam = lame_parameters(E, nu)
        sin_phi = torch.sin(phi_deg * (math.pi / 180.0))
        alpha = math.sqrt(2.0 / 3.0) * 2.0 * sin_phi / (3.0 - sin_phi)
        return {"mu": mu, "lam": lam, "alpha": alpha}

    def return_map(
        self,
        F: Tensor,
        values: dict[str, Tensor],
        *,
        plastic_J: Tensor | None = None,
        dt: float = 0.0,
    ) -> tuple[Tensor, Tensor]:
        d = self.derived(values, like=F)
        slope = d["alpha"] * (3.0 * d["lam"] + 2.0 * d["mu"]) / (2.0 * d["mu"])
        return isotropic_return(F, _drucker_prager, slope), plastic_j_or_ones(plastic_J, like=F)
