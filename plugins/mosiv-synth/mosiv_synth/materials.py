"""Parameter ranges of the six material families and sampling from them.

The paper's benchmark (appendix, "Genesis Multi-Object Dataset Physical Parameters") draws
E in [4.75e4, 5.25e4] Pa, Poisson ratio in [0.2, 0.3] and density in [800, 1200] kg/m^3
uniformly for every family; we keep those. Its yield-stress and shear-modulus columns are in
Genesis' internal units, so for the remaining parameters we choose physically sensible ranges
for 0.08-0.15 m objects colliding at ~1-2 m/s, with the reasoning beside each range. Every range
lies inside the law's ParamSpec bounds (``mosiv_framework.laws``), which ``sample_params``
checks.
"""

from __future__ import annotations

import math

import numpy as np

from mosiv_framework.laws import get_law

# (lower, upper, log_uniform) per parameter name
Range = tuple[float, float, bool]

# The paper's common ranges (appendix table): E ~ 5e4 Pa +-5 %, nu 0.2-0.3, rho 800-1200.
_E: Range = (4.75e4, 5.25e4, False)
_NU: Range = (0.2, 0.3, False)
_RHO: Range = (800.0, 1200.0, False)
# Coulomb friction between bodies: 0.2-0.5 spans soft rubber-on-food to wet-food contacts; higher
# values would glue the colliding objects together in multi-field MPM contact.
_FRICTION: Range = (0.2, 0.5, False)

MATERIAL_RANGES: dict[str, dict[str, Range]] = {
    "elastic": {"E": _E, "nu": _NU, "rho": _RHO, "friction": _FRICTION},
    "plasticine": {
        "E": _E,
        "nu": _NU,
        # von Mises yields at 2 mu |dev eps| = tau_Y, mu ~ 2e4 Pa: 2-5 kPa means permanent set
        # beyond 5-12 % deviatoric strain. A 1-2 m/s impact strains ~v/c ~ 15-25 % (c ~ 8 m/s),
        # so collisions dent it, while the self-weight stress rho g h ~ 1 kPa of a 0.1 m object
        # stays below yield and it keeps its shape at rest.
        "yield_stress": (2.0e3, 5.0e3, True),
        "rho": _RHO,
        "friction": _FRICTION,
    },
    "sand": {
        # internal friction angles of dry sands are 30-40 deg (their angle of repose); 25 deg
        # reaches loose, rounded grains.
        "friction_angle": (25.0, 40.0, False),
        "E": _E,
        "nu": _NU,
        "rho": _RHO,
        "friction": _FRICTION,
    },
    "newtonian": {
        # syrup to honey (0.5-5 Pa s): a liquid that visibly flows and spreads within the 1.25 s
        # clip, yet viscous enough that a 0.1 m blob is not shredded into droplets the particle
        # resolution cannot represent (water, 1e-3 Pa s, would be).
        "viscosity": (0.5, 5.0, True),
        # weakly compressible: sound speed sqrt(K / rho) = 6.5-11 m/s is several times the
        # 1-2 m/s flow speeds (density changes < ~10 %) and keeps c dt / dx < 0.5 at the default
        # 100 substeps on a 64-cell grid.
        "bulk_modulus": (5.0e4, 1.2e5, True),
        "rho": _RHO,
        "friction": _FRICTION,
    },
    "non_newtonian": {
        # shear and bulk moduli of the paper's E ~ 5e4 Pa, nu 0.2-0.3 solid: mu = E / (2 (1 + nu))
        # and K = E / (3 (1 - 2 nu)), so the gel is as stiff as the other families before it yields.
        "shear_modulus": (1.8e4, 2.2e4, False),
        "bulk_modulus": (2.8e4, 4.4e4, False),
        # Bingham yield stress of pastes and gels (mayonnaise, toothpaste: 0.1-1 kPa): the impact
        # makes it flow, its own weight (~1 kPa at the base) makes it slump slowly.
        "yield_stress": (150.0, 800.0, True),
        # plastic viscosity 0.5-5 Pa s: with 2 mu dt ~ 16-40 Pa s at 100-200 substeps the rate
        # term eta / (2 mu dt) ~ 0.01-0.3 is noticeable but does not freeze the flow.
        "plastic_viscosity": (0.5, 5.0, True),
        "rho": _RHO,
        "friction": _FRICTION,
    },
    "snow": {
        "E": _E,
        "nu": _NU,
        # Stomakhin et al. (2013) use theta_c = 2.5e-2, theta_s = 7.5e-3, xi = 10; we vary around
        # them: smaller thresholds crumble the snowball on impact, larger ones keep it elastic.
        "critical_compression": (0.019, 0.03, False),
        "critical_stretch": (0.005, 0.0095, False),
        "hardening": (5.0, 10.0, False),
        "rho": _RHO,
        "friction": _FRICTION,
    },
}

# Table friction drawn per scene: a smooth lacquered or cloth-covered tabletop, 0.3-0.6.
GROUND_FRICTION_RANGE: Range = (0.3, 0.6, False)


def draw(rng: np.random.Generator, spec: Range) -> float:
    """One value uniformly (or log-uniformly) from ``spec``."""
    lo, hi, log = spec
    if log:
        return float(math.exp(rng.uniform(math.log(lo), math.log(hi))))
    return float(rng.uniform(lo, hi))


def sample_params(family: str, rng: np.random.Generator) -> dict[str, float]:
    """True parameter values of one object of ``family``, keyed by the law's parameter names
    (plus ``rho`` and ``friction``), each inside the law's ParamSpec bounds."""
    if family not in MATERIAL_RANGES:
        raise ValueError(f"unknown material family {family!r}; valid: {', '.join(MATERIAL_RANGES)}")
    law = get_law(family)
    ranges = MATERIAL_RANGES[family]
    missing = sorted(set(law.param_names()) - set(ranges))
    if missing:
        raise RuntimeError(f"materials.py gives no range for {family} parameter(s) {missing}")
    values = {name: draw(rng, ranges[name]) for name in law.param_names()}
    law.validate(values, where=f"sampled {family} parameters: ")
    return values
