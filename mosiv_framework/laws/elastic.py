"""Elastic solid: compressible neo-Hookean (paper appendix), parameters E and nu."""

from __future__ import annotations

import torch

from mosiv_framework.laws.base import ConstitutiveLaw, ParamSpec, lame_parameters
from mosiv_framework.laws.linalg import gather_params, identity_like, plastic_j_or_ones, safe_det

Tensor = torch.Tensor

YOUNGS_MODULUS = ParamSpec("E", "Pa", 1e3, 1e7, 5e4, log_scale=True, description="Young's modulus")
POISSON_RATIO = ParamSpec("nu", "1", 0.0, 0.45, 0.25, description="Poisson ratio")


class Elastic(ConstitutiveLaw):
    """Neo-Hookean: tau = mu (F F^T - I) + lam ln(J) I; no plasticity."""

    name = "elastic"
    params = (YOUNGS_MODULUS, POISSON_RATIO)
    description = "neo-Hookean elastic solid (E, nu)"

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
        eye = identity_like(F)
        # Neo-Hookean Kirchhoff stress; J is clamped so crushed/inverted elements stay finite.
        log_j = torch.log(safe_det(F))
        left_cauchy_green = F @ F.transpose(-1, -2)
        return (
            d["mu"][:, None, None] * (left_cauchy_green - eye)
            + (d["lam"] * log_j)[:, None, None] * eye
        )

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
