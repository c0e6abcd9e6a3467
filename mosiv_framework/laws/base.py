"""What a constitutive law is: a parameter schema plus a pure-torch reference of its physics.

Each law lives in its own module of this package (one file per law). Backends implement the same
equations natively and are checked against these references by ``mosiv_framework.testing``.

Conventions shared by every law:
- ``F`` is the elastic deformation gradient, a [N, 3, 3] tensor.
- ``values`` maps parameter names to tensors broadcastable to [N] (0-d or [N]).
- ``plastic_J`` is a [N] per-particle plastic volume ratio; only laws with hardening use it
  (snow); the others pass it through unchanged.
- ``kirchhoff_stress`` returns tau = J * sigma, [N, 3, 3] in Pa.
- ``return_map`` projects a trial ``F`` back into the elastic region and returns the new
  ``(F, plastic_J)``; ``dt`` (s) matters only for rate-dependent laws.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from dataclasses import dataclass

import torch

Tensor = torch.Tensor


@dataclass(frozen=True)
class ParamSpec:
    """One identifiable parameter: name, SI unit, admissible bounds, log-scale flag, default.

    ``log_scale`` says the optimiser should work on log(value) (stiffnesses, viscosities).
    """

    name: str
    unit: str
    lower: float
    upper: float
    default: float
    log_scale: bool = False
    description: str = ""

    def __post_init__(self) -> None:
        if not self.lower <= self.default <= self.upper:
            raise ValueError(
                f"{self.name}: default {self.default} outside [{self.lower}, {self.upper}]"
            )
        if self.log_scale and self.lower <= 0:
            raise ValueError(f"{self.name}: log-scale parameters need a positive lower bound")

    def check(self, value: float, *, where: str = "") -> None:
        """Raise ValueError naming the parameter and the valid range if ``value`` is outside it."""
        if not (math.isfinite(value) and self.lower <= value <= self.upper):
            at = f" ({where})" if where else ""
            raise ValueError(
                f"parameter {self.name}={value!r}{at} is outside its valid range "
                f"[{self.lower:g}, {self.upper:g}] {self.unit}"
            )

    def to_normalized(self, value: Tensor) -> Tensor:
        """Map a value to [0, 1] over the bounds (in log space for log-scale parameters)."""
        lo, hi = self.lower, self.upper
        if self.log_scale:
            return (torch.log(value) - math.log(lo)) / (math.log(hi) - math.log(lo))
        return (value - lo) / (hi - lo)

    def from_normalized(self, u: Tensor) -> Tensor:
        """Inverse of ``to_normalized``; ``u`` is clamped to [0, 1] so bounds always hold."""
        u = u.clamp(0.0, 1.0)
        lo, hi = self.lower, self.upper
        if self.log_scale:
            return torch.exp(math.log(lo) + u * (math.log(hi) - math.log(lo)))
        return lo + u * (hi - lo)


# Parameters every object carries whatever its law: density and Coulomb friction coefficient.
OBJECT_PARAMS: tuple[ParamSpec, ...] = (
    ParamSpec("rho", "kg/m^3", 50.0, 5000.0, 1000.0, log_scale=True, description="density"),
    ParamSpec(
        "friction", "1", 0.0, 2.0, 0.3, description="Coulomb coefficient against other bodies"
    ),
)


def lame_parameters(E: Tensor, nu: Tensor) -> tuple[Tensor, Tensor]:
    """Lame constants (mu, lambda) in Pa from Young's modulus E (Pa) and Poisson ratio nu.

    mu = E / (2 (1 + nu)) (the paper's appendix has a typo here), lambda = E nu / ((1 + nu)(1 - 2 nu)).
    """
    mu = E / (2.0 * (1.0 + nu))
    lam = E * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))
    return mu, lam


class ConstitutiveLaw(ABC):
    """A material family: parameter schema and torch reference of stress and return map."""

    #: family name as written in scene.json (``elastic``, ``plasticine``, ...)
    name: str
    #: the law's own parameters (the common ``rho`` and ``friction`` are in OBJECT_PARAMS)
    params: tuple[ParamSpec, ...]
    #: one-line description for ``mosiv plugins``
    description: str = ""
    #: True when the stress depends on the velocity gradient (fluids)
    uses_velocity_gradient: bool = False

    @property
    def all_params(self) -> tuple[ParamSpec, ...]:
        return self.params + OBJECT_PARAMS

    def param(self, name: str) -> ParamSpec:
        for spec in self.all_params:
            if spec.name == name:
                return spec
        raise KeyError(f"law {self.name!r} has no parameter {name!r}; it has {self.param_names()}")

    def param_names(self) -> list[str]:
        return [p.name for p in self.all_params]

    def defaults(self) -> dict[str, float]:
        return {p.name: p.default for p in self.all_params}

    def validate(self, values: dict[str, float], *, where: str = "") -> None:
        """Raise ValueError for an unknown, missing or out-of-range parameter, naming it."""
        unknown = sorted(set(values) - set(self.param_names()))
        if unknown:
            raise ValueError(
                f"{where}law {self.name!r} has no parameter(s) {unknown}; valid: {self.param_names()}"
            )
        for spec in self.all_params:
            if spec.name in values:
                spec.check(float(values[spec.name]), where=where or self.name)

    @abstractmethod
    def kirchhoff_stress(
        self,
        F: Tensor,
        values: dict[str, Tensor],
        *,
        plastic_J: Tensor | None = None,
        velocity_gradient: Tensor | None = None,
    ) -> Tensor:
        """Kirchhoff stress tau = J sigma (Pa), [N, 3, 3]."""

    @abstractmethod
    def return_map(
        self,
        F: Tensor,
        values: dict[str, Tensor],
        *,
        plastic_J: Tensor | None = None,
        dt: float = 0.0,
    ) -> tuple[Tensor, Tensor]:
        """Project a trial elastic F onto the admissible set; returns (F, plastic_J)."""
