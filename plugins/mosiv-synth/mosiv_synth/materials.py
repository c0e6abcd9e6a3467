"""Parameter ranges of the six material families and sampling from them.

Two presets: ``paper`` (``MATERIAL_RANGES``, the paper's benchmark) and ``wide``
(``WIDE_RANGES``, two decades of stiffness and a decade or more of every yield stress and
viscosity, for identification that must hold away from the paper's narrow band).

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
from dataclasses import dataclass

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


@dataclass(frozen=True)
class BulkFromPoisson:
    """The bulk modulus K = 2 G (1 + nu) / (3 (1 - 2 nu)) of an isotropic solid with the shear
    modulus G drawn before it and a Poisson ratio nu drawn uniformly in [nu_lo, nu_hi].

    Drawing K and G independently over decades would pair a soft K with a stiff G (negative
    Poisson ratio, lambda = K - 2 G / 3 < 0), a material no gel is; tying K to G keeps
    nu in the wide preset's 0.15-0.4. ``lower`` / ``upper`` bound the result (Pa)."""

    shear: Range
    nu_lo: float
    nu_hi: float

    @staticmethod
    def ratio(nu: float) -> float:
        return 2.0 * (1.0 + nu) / (3.0 * (1.0 - 2.0 * nu))

    @property
    def lower(self) -> float:
        return self.shear[0] * self.ratio(self.nu_lo)

    @property
    def upper(self) -> float:
        return self.shear[1] * self.ratio(self.nu_hi)

    def draw(self, rng: np.random.Generator, values: dict[str, float]) -> float:
        return values["shear_modulus"] * self.ratio(float(rng.uniform(self.nu_lo, self.nu_hi)))


# ---------------------------------------------------------------------------- wide preset
# Two decades of Young's modulus, log-uniform: 1e4 Pa (soft gel, jelly) to 1e6 Pa (rubber).
# The stiff end needs ~550 substeps per frame on the 64-cell grid (P-wave speed up to 65 m/s);
# ``stability.required_substeps`` raises the simulator's substeps for such draws.
_W_E: Range = (1.0e4, 1.0e6, True)
# Poisson ratio 0.15 (foams, cork-like) to 0.4 (nearly incompressible rubber); the law allows
# 0.45, but nu -> 0.5 makes the P-wave modulus E (1 - nu) / ((1 + nu)(1 - 2 nu)) blow up.
_W_NU: Range = (0.15, 0.4, False)
# density of wood and foams (500) to wet clay and rubber (2000), log-uniform over a factor 4
_W_RHO: Range = (500.0, 2000.0, True)
# inter-body Coulomb friction 0.1 (wet, slippery) to 0.6 (rubbery); above it multi-field
# contact glues the colliding bodies
_W_FRICTION: Range = (0.1, 0.6, False)
# the gel's shear modulus: E / (2 (1 + nu)) of the wide E and nu, 3.5e3-4.4e5 Pa
_W_SHEAR: Range = (3.5e3, 4.4e5, True)

WIDE_RANGES: dict[str, dict[str, Range | BulkFromPoisson]] = {
    "elastic": {"E": _W_E, "nu": _W_NU, "rho": _W_RHO, "friction": _W_FRICTION},
    "plasticine": {
        "E": _W_E,
        "nu": _W_NU,
        # 1-30 kPa (1.5 decades): the soft end slumps under its own weight (rho g h ~ 1-3 kPa
        # at the base of a 0.1-0.15 m object), the hard end yields only under the impact
        # stresses of the stiffer draws (E x 3 % strain ~ 3e4 Pa at E = 1e6 Pa)
        "yield_stress": (1.0e3, 3.0e4, True),
        "rho": _W_RHO,
        "friction": _W_FRICTION,
    },
    "sand": {
        # 20 deg (rounded glass beads, wet loose grains) to 45 deg (angular crushed rock)
        "friction_angle": (20.0, 45.0, False),
        "E": _W_E,
        "nu": _W_NU,
        "rho": _W_RHO,
        "friction": _W_FRICTION,
    },
    "newtonian": {
        # 0.1 Pa s (olive oil x 1.5) to 10 Pa s (thick honey), two decades; the explicit
        # viscous stress needs nu_k dt / dx^2 below ~1/6, which ``stability`` checks (at
        # 10 Pa s and 500 kg/m^3 the 64-cell grid keeps it at 0.05 with 100 substeps)
        "viscosity": (0.1, 10.0, True),
        # 1e4-1e6 Pa, the E decades: sound speed 2-45 m/s, from a slow squishy liquid to one
        # compressed by < 1 % in 1-2 m/s impacts
        "bulk_modulus": (1.0e4, 1.0e6, True),
        "rho": _W_RHO,
        "friction": _W_FRICTION,
    },
    "non_newtonian": {
        "shear_modulus": _W_SHEAR,
        "bulk_modulus": BulkFromPoisson(_W_SHEAR, _W_NU[0], _W_NU[1]),
        # Bingham yield stress 50 Pa (ketchup) to 5 kPa (stiff dough), two decades
        "yield_stress": (50.0, 5.0e3, True),
        # plastic viscosity 0.1-10 Pa s (two decades); relaxation eta / (2 G dt) stays from
        # ~1e-4 (a plastic) to ~3 (a slow viscous creep) over the shear-modulus range
        "plastic_viscosity": (0.1, 10.0, True),
        "rho": _W_RHO,
        "friction": _W_FRICTION,
    },
    "snow": {
        "E": _W_E,
        "nu": _W_NU,
        # around Stomakhin et al.'s 2.5e-2 / 7.5e-3 over a factor ~3 each; hardening stays
        # at 4-12, as e^(xi (1 - J_p)) multiplies the stiffness the substeps were chosen for
        "critical_compression": (0.015, 0.045, False),
        "critical_stretch": (0.004, 0.012, False),
        "hardening": (4.0, 12.0, False),
        "rho": _W_RHO,
        "friction": _W_FRICTION,
    },
}
# table friction 0.2 (polished, wet) to 0.8 (rubber mat)
WIDE_GROUND_FRICTION_RANGE: Range = (0.2, 0.8, False)

#: preset name -> (material ranges, ground friction range)
RANGE_PRESETS: dict[str, tuple[dict, Range]] = {
    "paper": (MATERIAL_RANGES, GROUND_FRICTION_RANGE),
    "wide": (WIDE_RANGES, WIDE_GROUND_FRICTION_RANGE),
}


def range_bounds(spec: Range | BulkFromPoisson) -> tuple[float, float]:
    """(lower, upper) of one range entry."""
    if isinstance(spec, BulkFromPoisson):
        return spec.lower, spec.upper
    return spec[0], spec[1]


def range_table(preset: str) -> dict:
    """The preset's ranges as JSON (gt/params.json records them): family -> parameter ->
    {lower, upper, log} (or the bulk modulus' rule), plus ``ground_friction``."""
    materials, ground = RANGE_PRESETS[preset]

    def entry(spec) -> dict:
        if isinstance(spec, BulkFromPoisson):
            return {
                "rule": "2 shear_modulus (1 + nu) / (3 (1 - 2 nu))",
                "nu": [spec.nu_lo, spec.nu_hi],
                "lower": spec.lower,
                "upper": spec.upper,
            }
        return {"lower": spec[0], "upper": spec[1], "log": spec[2]}

    table = {fam: {n: entry(s) for n, s in r.items()} for fam, r in materials.items()}
    return {"materials": table, "ground_friction": entry(ground)}


def draw(rng: np.random.Generator, spec: Range) -> float:
    """One value uniformly (or log-uniformly) from ``spec``."""
    lo, hi, log = spec
    if log:
        return float(math.exp(rng.uniform(math.log(lo), math.log(hi))))
    return float(rng.uniform(lo, hi))


def sample_params(family: str, rng: np.random.Generator, preset: str = "paper") -> dict[str, float]:
    """True parameter values of one object of ``family``, keyed by the law's parameter names
    (plus ``rho`` and ``friction``), each inside the law's ParamSpec bounds.

    Args:
        family: material family (a key of ``MATERIAL_RANGES``).
        rng: drawn in the law's parameter order (the same seed gives the same values).
        preset: "paper" or "wide" (``RANGE_PRESETS``).
    """
    if preset not in RANGE_PRESETS:
        raise ValueError(f"unknown range preset {preset!r}; valid: {', '.join(RANGE_PRESETS)}")
    table = RANGE_PRESETS[preset][0]
    if family not in table:
        raise ValueError(f"unknown material family {family!r}; valid: {', '.join(table)}")
    law = get_law(family)
    ranges = table[family]
    missing = sorted(set(law.param_names()) - set(ranges))
    if missing:
        raise RuntimeError(f"materials.py gives no range for {family} parameter(s) {missing}")
    values: dict[str, float] = {}
    for name in law.param_names():
        spec = ranges[name]
        derived = isinstance(spec, BulkFromPoisson)
        values[name] = spec.draw(rng, values) if derived else draw(rng, spec)
    law.validate(values, where=f"sampled {family} parameters: ")
    return values
