"""How many MPM substeps a scene's materials need, so the generating simulation stays stable.

Explicit MPM is stable while (1) a pressure wave crosses less than about half a grid cell per
substep, c dt / dx < 0.5 with the P-wave speed c = sqrt(M / rho) (M = lambda + 2 mu, the P-wave
modulus), and (2) for the Newtonian fluid's explicit viscous stress, the momentum diffusion
number nu_k dt / dx^2 (nu_k = viscosity / rho) stays below 1/6 in three dimensions.

The paper's ranges keep both at the protocol's 100 substeps on the 64-cell grid (P-wave speeds
below 12.3 m/s: c dt / dx <= 0.41). The wide preset reaches P-wave speeds of 65 m/s (E = 1e6 Pa,
nu = 0.4, rho = 500 kg/m^3), which needs ~550 substeps there: ``required_substeps`` gives the
fewest substeps at or above the requested ones that keep both numbers below their targets.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

#: the stability bounds, and the targets (10 % below them) the chosen substeps aim for
CFL_BOUND = 0.5
CFL_TARGET = 0.45
VISCOUS_BOUND = 1.0 / 6.0
VISCOUS_TARGET = 0.15

_E_FAMILIES = ("elastic", "plasticine", "sand", "snow", "elastic_corotated", "plasticine_corotated")


def p_wave_modulus(family: str, p: dict[str, float]) -> float:
    """M = lambda + 2 mu (Pa) of one object's parameters ``p`` at rest.

    E and nu: M = E (1 - nu) / ((1 + nu)(1 - 2 nu)); the Newtonian fluid has no shear
    stiffness (M = bulk_modulus); the viscoplastic gel M = K + 4 G / 3. Snow's hardening
    e^(xi (1 - J_p)) stiffens compacted snow beyond this value; the margin of ``CFL_TARGET``
    covers compaction of a few percent."""
    if family in _E_FAMILIES:
        e, nu = p["E"], p["nu"]
        return e * (1.0 - nu) / ((1.0 + nu) * (1.0 - 2.0 * nu))
    if family == "newtonian":
        return p["bulk_modulus"]
    if family == "non_newtonian":
        return p["bulk_modulus"] + 4.0 * p["shear_modulus"] / 3.0
    raise ValueError(f"no P-wave modulus for material family {family!r}")


def kinematic_viscosity(family: str, p: dict[str, float]) -> float:
    """viscosity / rho (m^2/s) of a material whose viscous stress is explicit; 0 otherwise
    (the gel's plastic viscosity relaxes implicitly and sets no step limit)."""
    return p["viscosity"] / p["rho"] if family == "newtonian" else 0.0


def stability_numbers(
    families: Sequence[str], params: Sequence[dict[str, float]], *, dx: float, dt: float
) -> dict[str, float]:
    """The largest CFL number c dt / dx and viscous number nu_k dt / dx^2 over the objects.

    Args:
        families, params: each object's family and parameters (``rho`` included).
        dx: grid cell (m); dt: substep (s).
    """
    speeds = [math.sqrt(p_wave_modulus(f, p) / p["rho"]) for f, p in zip(families, params)]
    diffusion = [kinematic_viscosity(f, p) for f, p in zip(families, params)]
    return {"cfl": max(speeds) * dt / dx, "viscous": max(diffusion) * dt / dx**2}


def required_substeps(
    families: Sequence[str],
    params: Sequence[dict[str, float]],
    *,
    dx: float,
    fps: float,
    requested: int,
) -> int:
    """The fewest substeps per frame, at least ``requested``, that keep the CFL number below
    ``CFL_TARGET`` and the viscous number below ``VISCOUS_TARGET`` for every object."""
    worst = stability_numbers(families, params, dx=dx, dt=1.0 / fps)  # the numbers at 1 substep
    need = max(worst["cfl"] / CFL_TARGET, worst["viscous"] / VISCOUS_TARGET)
    return max(int(requested), math.ceil(need))
