"""PhysicsTerms declared by the core: schema plus, for body forces, a torch reference acceleration.

Simulator backends implement these natively (see ``Simulator.supported_terms``); the core keeps
their parameter schemas so recipes, the concealed-physics generator and diagnosis all agree on
names, units and bounds. Vector parameters (``acceleration``) are [3] tensors.

Body-force terms (drag, wind, gravity) add an acceleration at every grid node. The material and
contact terms (``material_damping``, ``ground_restitution``) change the stress or the ground
boundary condition instead, so they have no reference acceleration. Every term at its zero
value is the model without it. ``expression`` (``mosiv_framework.expression``) applies a
discovered force law, a sparse sum of state features with differentiable coefficients.
"""

from __future__ import annotations

import torch

from mosiv_framework.expression import ExpressionTerm
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


class MaterialDamping(PhysicsTerm):
    """Kelvin-Voigt viscosity added to every object's constitutive stress.

    Kirchhoff form, as the Newtonian law writes its viscous stress:
    tau_visc = eta J (L + L^T) (Pa), with L the APIC affine matrix C (1/s) as the velocity
    gradient and J = det F. Only the symmetric part of L enters, so rigid translation and
    rotation (L antisymmetric) are not damped. For a body of Young's modulus E vibrating at
    angular frequency omega the damping ratio is about eta omega / (2 E).
    """

    name = "material_damping"
    params = (
        ParamSpec(
            "viscosity",
            "Pa s",
            0.0,
            200.0,
            0.0,
            description="eta in tau_visc = eta J (L + L^T)",
        ),
    )
    regimes = frozenset({"object_contact", "ground_contact", "rest"})
    description = "Kelvin-Voigt material damping tau = eta J (L + L^T)"


class GroundRestitution(PhysicsTerm):
    """A bouncing table: material arriving at the ground leaves it with e times its normal speed.

    At grid nodes of the ground layer moving into the table (v_z < 0) the normal velocity is set
    to e max(-v_in, 0) instead of 0, where v_in (m/s) is the node's arriving normal velocity:
    its momentum before this substep's stress and body-force impulse. The Coulomb limit then
    uses the whole normal change, so the tangential speed drops by at most
    mu (|v_z| + e max(-v_in, 0)) (= mu (1 + e)|v_z| for free-falling material).

    Why the arriving velocity and not v_z itself: grid contact is applied every substep, and a
    body pressed onto the table keeps being pushed down by its own stress; reflecting that push
    re-launched the contact layer every substep and pumped energy into the body (a stiff ball
    dropped at 1.5 J ended with 47 J at e = 1). Reflecting only what arrives keeps e = 1 nearly
    lossless and e = 0 the plain inelastic contact, bit for bit.
    """

    name = "ground_restitution"
    params = (
        ParamSpec(
            "coefficient",
            "1",
            0.0,
            1.0,
            0.0,
            description="e in v_z <- -e v_z at the ground",
        ),
    )
    regimes = frozenset({"ground_contact"})
    description = "restitution of the ground contact v_z <- -e v_z"


BUILTIN_TERMS: tuple[PhysicsTerm, ...] = (
    LinearDrag(),
    QuadraticDrag(),
    Wind(),
    Gravity(),
    MaterialDamping(),
    GroundRestitution(),
    ExpressionTerm(),
)
