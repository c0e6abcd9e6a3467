"""Snow (Stomakhin et al. 2013): fixed-corotated elasticity hardened by plastic compaction.

Parameters: E (Pa), nu, critical_compression theta_c, critical_stretch theta_s, hardening xi.
The per-particle plastic volume ratio plastic_J stiffens compacted snow and softens loosened snow.
"""

from __future__ import annotations

import torch

from mosiv_framework.laws.base import ConstitutiveLaw, ParamSpec, lame_parameters
from mosiv_framework.laws.elastic import YOUNGS_MODULUS
from mosiv_framework.laws.elastic_corotated import corotated_kirchhoff
from mosiv_framework.laws.linalg import (
    gather_params,
    plastic_j_or_ones,
)
from mosiv_framework.laws.plasticine import isotropic_return

Tensor = torch.Tensor


def _clamp_singular(s: Tensor, lo: Tensor, hi: Tensor) -> tuple[Tensor, Tensor]:
    # Stomakhin 2013 eq. 7: singular values beyond [1 - theta_c, 1 + theta_s] are plastic.
    s_new = torch.minimum(torch.maximum(s, lo[:, None]), hi[:, None])
    return s_new, (s_new != s).any(dim=-1)


class Snow(ConstitutiveLaw):
    """Fixed-corotated stress with hardening exp(xi (1 - plastic_J)); clamped singular values."""

    name = "snow"
    params = (
        YOUNGS_MODULUS,
        ParamSpec("nu", "1", 0.0, 0.45, 0.25, description="Poisson ratio"),
        ParamSpec("critical_compression", "1", 1e-3, 0.2, 2.5e-2, description="theta_c"),
        ParamSpec("critical_stretch", "1", 1e-3, 0.1, 7.5e-3, description="theta_s"),
        ParamSpec("hardening", "1", 0.0, 30.0, 10.0, description="xi"),
    )
    description = "Stomakhin 2013 snow (E, nu, critical_compression/stretch, hardening)"

    def derived(
        self, values: dict[str, Tensor], *, like: Tensor | None = None
    ) -> dict[str, Tensor]:
        """Unhardened mu0, lam0 (Pa), theta_c, theta_s and xi; [N] when like=F."""
        names = ("E", "nu", "critical_compression", "critical_stretch", "hardening")
        E, nu, theta_c, theta_s, xi = gather_params(values, names, like=like, law=self.name)
        mu0, lam0 = lame_parameters(E, nu)
        return {"mu0": mu0, "lam0": lam0, "theta_c": theta_c, "theta_s": theta_s, "xi": xi}

    def kirchhoff_stress(
        self,
        F: Tensor,
        values: dict[str, Tensor],
        *,
        plastic_J: Tensor | None = None,
        velocity_gradient: Tensor | None = None,
    ) -> Tensor:
        d = self.derived(values, like=F)
        pj = plastic_j_or_ones(plastic_J, like=F)
        # Stomakhin 2013 eq. 3: Lame constants scale with exp(xi (1 - J_p)).
        hardening = torch.exp(d["xi"] * (1.0 - pj))
        # the fixed-corotated Kirchhoff stress 2 mu (F - R) F^T + lam (J - 1) J I, hardened
        return corotated_kirchhoff(F, d["mu0"] * hardening, d["lam0"] * hardening)

    def return_map(
        self,
        F: Tensor,
        values: dict[str, Tensor],
        *,
        plastic_J: Tensor | None = None,
        dt: float = 0.0,
    ) -> tuple[Tensor, Tensor]:
        d = self.derived(values, like=F)
        pj = plastic_j_or_ones(plastic_J, like=F)
        lo, hi = 1.0 - d["theta_c"], 1.0 + d["theta_s"]
        F_new = isotropic_return(F, _clamp_singular, lo, hi)
        # The plastic part absorbs the volume the elastic part lost: J_e J_p is preserved.
        pj_new = pj * torch.linalg.det(F) / torch.linalg.det(F_new)
        return F_new, pj_new
