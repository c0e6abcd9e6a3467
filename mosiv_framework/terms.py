"""Body-force PhysicsTerms declared by the core: schema plus torch reference acceleration.

Simulator backends implement these natively (see ``Simulator.supported_terms``); the core keeps
their parameter schemas so recipes, the concealed-physics generator and diagnosis all agree on
names, units and bounds. Vector parameters (``acceleration``) are [3] tensors.
"""

from __future__ import annotations

import torch

from mosiv_framework.interfaces import PhysicsTerm
from mosiv_framework.laws.base import ParamSpec

Tensor = torch.Tensor
_ALL_REGIMES = frozenset({"free_flight", "object_contact", "ground_contact", "rest"})


class LinearDrag(PhysicsTerm):
    """Stokes-like air drag, a = -c v."""

    name = "linear_drag"
    params = (ParamSpec("coefficient", "1/s", 0.0, 50.0, 0.0, description="c in a = -c v"),)
    regimes = frozenset({"free_flight", "object_contact"})
    description = "linear air drag a = -c v"

    def reference_acceleration(self, velocity: Tensor, values: dict[str, Tensor]) -> Tensor:
        return -values["coefficient"] * velocity


class QuadraticDrag(PhysicsTerm):
    """Turbulent air drag, a = -c |v| v."""

    name = "quadratic_drag"
    params = (ParamSpec("coefficient", "1/m", 0.0, 50.0, 0.0, description="c in a = -c |v| v"),)
    regimes = frozenset({"free_flight", "object_contact"})
    description = "quadratic air drag a = -c |v| v"

    def reference_acceleration(self, velocity: Tensor, values: dict[str, Tensor]) -> Tensor:
        return -values["coefficient"] * velocity.norm(dim=-1, keepdim=True) * velocity


class Wind(PhysicsTerm):
    """A steady extra body acceleration (wind, a tilted table, a mis-declared force)."""

    name = "wind"
    params = (ParamSpec("acceleration", "m/s^2", -50.0, 50.0, 0.0, description="[3] vector"),)
    regimes = _ALL_REGIMES
    description = "steady extra acceleration a = const"

    def reference_acceleration(self, velocity: Tensor, values: dict[str, Tensor]) -> Tensor:
        return values["acceleration"].to(velocity).expand_as(velocity)


class Gravity(PhysicsTerm):
    """Gravity other than scene.json declares: the [3] acceleration replaces the declared one."""

    name = "gravity"
    params = (ParamSpec("acceleration", "m/s^2", -50.0, 50.0, 0.0, description="[3] vector"),)
    regimes = _ALL_REGIMES
    description = "gravity vector replacing the declared one"

    def reference_acceleration(self, velocity: Tensor, values: dict[str, Tensor]) -> Tensor:
        return values["acceleration"].to(velocity).expand_as(velocity)


BUILTIN_TERMS: tuple[PhysicsTerm, ...] = (LinearDrag(), QuadraticDrag(), Wind(), Gravity())
