"""The physics a diagnosis may add: one ``Candidate`` per registered PhysicsTerm plus the
friction coefficients the run kept fixed.

A candidate turns a small coefficient vector theta (zero = "absent", the model the run fitted)
into SimulationParams. Body-force terms come from the registry (kind ``physics_term``), so a
third-party term is screened exactly like the built-in ones, provided the run's simulator lists
it in ``supported_terms``. A term parameter whose ParamSpec description begins with ``[3]`` is
a 3-vector (the convention of ``mosiv_framework.terms``); others are scalars.

Plasticity missing from an elastic fit is a candidate per body the run fitted as ``elastic``: it
turns the body into ``plasticine`` with the same E and nu and a von Mises yield stress
yield_stress = Y_max 10^(-theta) (theta in decades below the law's upper bound Y_max, which no
collision of the generator's bodies reaches, so theta = 0 means "does not yield"). Unlike the
others it is not zero-neutral to the bit (the plasticine law's elasticity is StVK-Hencky, the
elastic law's neo-Hookean; they agree to first order in the strain) and its loss is flat at
theta = 0 (nothing yields), so the screening probes it on a ladder instead of by its gradient
(``ladder``).

Two built-in terms get a narrower parametrisation, because their full form is indistinguishable
from another candidate: ``gravity`` replaces the declared gravity vector, and a change of its
direction is exactly a steady ``wind``; so the gravity candidate changes only the magnitude
along the declared direction (one coefficient, m/s^2), and ``wind`` covers the rest. That
magnitude change is still a wind along g, a special case the decision step prefers when the
wind's extra coefficients add little (``SPECIAL_CASES``, ``decide.prefer_special_cases``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch

from mosiv_framework.diagnose.context import RunContext
from mosiv_framework.expression import NAME as EXPRESSION
from mosiv_framework.interfaces import PhysicsTerm
from mosiv_framework.laws import get_law
from mosiv_framework.laws.base import OBJECT_PARAMS
from mosiv_framework.pipeline.params import GROUND_FRICTION
from mosiv_framework.recipes.terms import param_size
from mosiv_framework.registry import get_registry
from mosiv_framework.types import ObjectParams, SimulationParams

GROUND_REGIMES = frozenset({"ground_contact", "rest"})
CONTACT_REGIMES = frozenset({"object_contact"})
FRICTION = next(spec for spec in OBJECT_PARAMS if spec.name == "friction")
YIELD_STRESS = get_law("plasticine").param("yield_stress")
#: plasticity acts where bodies are stressed: contacts, landings and resting under weight
PLASTIC_REGIMES = frozenset({"object_contact", "ground_contact", "rest"})
#: theta (decades below the bound) at which the screening probes a plasticity candidate
PLASTICITY_LADDER = (1.0, 1.75, 2.5, 3.25)
#: candidate -> the candidates that contain it as a special case (same predictions at some of
#: their coefficients): a gravity magnitude change d is the wind d g/|g|
SPECIAL_CASES: dict[str, tuple[str, ...]] = {"gravity": ("wind",)}


@dataclass
class Candidate:
    """One hypothesis: a named effect with coefficients theta (zero means absent).

    ``lower``/``upper`` bound theta (sign constraints: drag >= 0); ``step`` is a natural size
    of theta used to probe the loss and scale the optimiser; ``units`` per coefficient.
    """

    name: str
    # "term", "gravity", "ground_friction", "object_friction", "plasticity" or "expression"
    # (a discovered law, ``formula``)
    kind: str
    coefficient_names: list[str]
    units: list[str]
    lower: torch.Tensor
    upper: torch.Tensor
    step: torch.Tensor
    regimes: frozenset[str]
    description: str
    term: PhysicsTerm | None = None
    base: dict = field(default_factory=dict)
    #: coefficients the screen probes instead of taking a gradient at zero, for effects whose
    #: loss is flat there (None: screen by gradient)
    ladder: tuple[float, ...] | None = None

    @property
    def special_case_of(self) -> tuple[str, ...]:
        """The candidates that contain this one as a special case (``SPECIAL_CASES``)."""
        return SPECIAL_CASES.get(self.name, ())

    @property
    def dim(self) -> int:
        return len(self.coefficient_names)

    def zero(self) -> torch.Tensor:
        return torch.zeros(self.dim, dtype=torch.float32)

    def clamp(self, theta: torch.Tensor) -> torch.Tensor:
        return torch.maximum(torch.minimum(theta, self.upper), self.lower)

    def apply(self, params: SimulationParams, theta: torch.Tensor) -> SimulationParams:
        """``params`` with this effect switched on at ``theta`` (differentiable in theta).

        theta is used as given (a clamp would halve gradients at a bound such as zero drag);
        callers keep it inside [lower, upper] with ``clamp``.
        """
        terms = dict(params.terms)
        objects = params.objects
        ground = params.ground_friction
        if self.kind == "gravity":
            g = torch.tensor(self.base["gravity"], dtype=torch.float32)
            terms["gravity"] = {"acceleration": g + theta[0] * g / g.norm()}
        elif self.kind == "ground_friction":
            ground = params.ground_friction + theta[0]
        elif self.kind == "object_friction":
            objects = {
                k: ObjectParams(p.family, {**p.values, "friction": p.values["friction"] + theta[0]})
                for k, p in params.objects.items()
            }
        elif self.kind == "plasticity":
            k = self.base["object"]
            values = {**params.objects[k].values, "yield_stress": self.yield_stress(theta)}
            objects = {**params.objects, k: ObjectParams("plasticine", values)}
        elif self.kind == "expression":  # a sparse term: only the discovered coefficients
            terms[self.name] = {n: theta[i] for i, n in enumerate(self.coefficient_names)}
        else:
            values, i = {}, 0
            for spec in self.term.params:
                size = 3 if _is_vector(spec) else 1
                values[spec.name] = theta[i : i + size] if size == 3 else theta[i]
                i += size
            terms[self.name] = values
        return SimulationParams(objects, dict(params.initial_velocity), ground, terms)

    def without(self, params: SimulationParams, theta: torch.Tensor) -> SimulationParams:
        """``params`` (which include this effect at ``theta``) with the effect taken out."""
        if self.kind in ("term", "gravity", "expression"):
            terms = {k: v for k, v in params.terms.items() if k != self.term.name}
            return SimulationParams(
                params.objects, params.initial_velocity, params.ground_friction, terms
            )
        if self.kind == "plasticity":
            k = self.base["object"]
            values = {n: v for n, v in params.objects[k].values.items() if n != "yield_stress"}
            objects = {**params.objects, k: ObjectParams("elastic", values)}
            return SimulationParams(
                objects, params.initial_velocity, params.ground_friction, params.terms
            )
        return self.apply(params, -theta)  # friction candidates shift a coefficient: undo it

    def yield_stress(self, theta: torch.Tensor) -> torch.Tensor:
        """Von Mises yield stress (Pa) of a plasticity candidate at ``theta`` (decades)."""
        return YIELD_STRESS.upper * torch.pow(10.0, -theta[0])

    def acceleration(self, velocity: torch.Tensor, theta: torch.Tensor) -> torch.Tensor | None:
        """Extra acceleration [N, 3] (m/s^2) at ``velocity`` for body-force candidates."""
        if self.kind == "gravity":
            g = torch.tensor(self.base["gravity"], dtype=torch.float32)
            return (theta[0] * g / g.norm()).expand_as(velocity)
        if self.kind != "term":
            return None
        values, i = {}, 0
        for spec in self.term.params:
            size = 3 if _is_vector(spec) else 1
            values[spec.name] = theta[i : i + size] if size == 3 else theta[i]
            i += size
        return self.term.reference_acceleration(velocity, values)

    def physical(self, theta: torch.Tensor) -> dict[str, float | list[float]]:
        """Coefficient values as the recipe would write them."""
        theta = self.clamp(theta.detach().float())
        if self.kind == "gravity":
            g = torch.tensor(self.base["gravity"], dtype=torch.float32)
            return {"acceleration": (g + theta[0] * g / g.norm()).tolist()}
        if self.kind == "ground_friction":
            return {"ground_friction": float(self.base["ground_friction"] + theta[0])}
        if self.kind == "object_friction":
            mus = self.base.get("friction", [])
            out = {"friction_change": float(theta[0])}
            if mus and max(mus) == min(mus):  # one assumed coefficient: the new one in full
                out["coefficient"] = float(mus[0] + theta[0])
            return out
        if self.kind == "plasticity":
            return {"object": self.base["object"], "yield_stress": float(self.yield_stress(theta))}
        if self.kind == "expression":
            return {n: float(c) for n, c in zip(self.coefficient_names, theta)}
        out, i = {}, 0
        for spec in self.term.params:
            if _is_vector(spec):
                out[spec.name] = theta[i : i + 3].tolist()
                i += 3
            else:
                out[spec.name] = float(theta[i])
                i += 1
        return out


def _is_vector(spec) -> bool:
    return param_size(spec) == 3


def build_candidates(ctx: RunContext) -> tuple[list[Candidate], list[str]]:
    """Every effect the run's simulator can add; returns (candidates, reasons for skipped ones).

    The registered physics terms the simulator implements and the model does not hold yet,
    then a change of table friction, of body-body friction and of a body's plasticity where
    the run did not identify them.
    """
    skipped: list[str] = []
    out = _term_candidates(ctx, skipped)
    free = set(ctx.parameter_vector().normalized)
    if ctx.world.ground_height is not None:
        if "ground_friction" in free:
            skipped.append("ground_friction: already identified by the run")
        else:
            out.append(_ground_friction_candidate(ctx))
    if len(ctx.object_ids) > 1:
        if any(key.endswith(".friction") for key in free):
            skipped.append("object_friction: already identified by the run")
        else:
            out.append(_object_friction_candidate(ctx))
    out += _plasticity_candidates(ctx, skipped)
    return out, skipped


def _term_candidates(ctx: RunContext, skipped: list[str]) -> list[Candidate]:
    """A candidate per registered physics term the run's simulator implements and its model
    lacks; the reason for each other one is appended to ``skipped``."""
    supported = set(getattr(ctx.simulator, "supported_terms", frozenset()))
    gravity = tuple(float(x) for x in ctx.world.gravity)
    out = []
    for component in get_registry().components("physics_term"):
        term = component.factory()
        if term.name == EXPRESSION:  # not a library term: built from the discovered law
            continue
        if term.name not in supported:
            skipped.append(f"{term.name}: simulator {ctx.simulator_name!r} does not implement it")
        elif term.name in ctx.identified.terms:
            skipped.append(f"{term.name}: already part of the fitted model")
        elif term.name != "gravity":
            out.append(_term_candidate(term))
        elif sum(g * g for g in gravity) == 0.0:
            skipped.append("gravity: the scene declares none, so no direction to rescale")
        else:
            out.append(_gravity_candidate(term, gravity))
    return out


def _gravity_candidate(term, gravity: tuple[float, ...]) -> Candidate:
    """A change of gravity's magnitude along its declared direction."""
    spec = term.params[0]
    g_norm = sum(g * g for g in gravity) ** 0.5
    return Candidate(
        "gravity",
        "gravity",
        ["magnitude_change"],
        [spec.unit],
        # |g| may range over [0, the spec's bound]
        torch.tensor([-g_norm]),
        torch.tensor([spec.upper - g_norm]),
        torch.tensor([0.01 * (spec.upper - spec.lower)]),
        term.regimes,
        "gravity magnitude other than declared",
        term,
        {"gravity": gravity},
    )


def _term_candidate(term) -> Candidate:
    """A physics term's parameters as coefficients (a vector parameter as three)."""
    names, units, lower, upper, step = [], [], [], [], []
    for spec in term.params:
        size = 3 if _is_vector(spec) else 1
        for axis in range(size):
            names.append(f"{spec.name}.{'xyz'[axis]}" if size == 3 else spec.name)
            units.append(spec.unit)
            lower.append(spec.lower)
            upper.append(spec.upper)
            # probe 1 % of the admissible range: visible in the loss, small enough for
            # the quadratic model of the probe to hold
            step.append(0.01 * (spec.upper - spec.lower))
    return Candidate(
        term.name,
        "term",
        names,
        units,
        torch.tensor(lower),
        torch.tensor(upper),
        torch.tensor(step),
        term.regimes,
        term.description or term.name,
        term,
    )


def _ground_friction_candidate(ctx: RunContext) -> Candidate:
    """A change of the table's Coulomb friction from the run's value, within its bounds."""
    mu = float(ctx.identified.ground_friction)
    return Candidate(
        "ground_friction",
        "ground_friction",
        ["ground_friction_change"],
        ["1"],
        torch.tensor([GROUND_FRICTION.lower - mu]),
        torch.tensor([GROUND_FRICTION.upper - mu]),
        torch.tensor([0.01 * (GROUND_FRICTION.upper - GROUND_FRICTION.lower)]),
        GROUND_REGIMES,
        "table Coulomb friction other than assumed",
        base={"ground_friction": mu},
    )


def _object_friction_candidate(ctx: RunContext) -> Candidate:
    """One change of every body's friction, keeping each within the parameter's bounds."""
    mus = [float(p.values["friction"]) for p in ctx.identified.objects.values()]
    return Candidate(
        "object_friction",
        "object_friction",
        ["friction_change"],
        ["1"],
        torch.tensor([FRICTION.lower - min(mus)]),
        torch.tensor([FRICTION.upper - max(mus)]),
        torch.tensor([0.01 * (FRICTION.upper - FRICTION.lower)]),
        CONTACT_REGIMES,
        "object-object Coulomb friction other than assumed",
        base={"friction": mus},
    )


def _plasticity_candidates(ctx: RunContext, skipped: list[str]) -> list[Candidate]:
    """One candidate per body the run fitted as elastic (named ``plasticity`` when there is
    one such body, ``plasticity@K`` for body K when there are several)."""
    supported = set(getattr(ctx.simulator, "supported_laws", ()))
    elastic = sorted(k for k, p in ctx.identified.objects.items() if p.family == "elastic")
    if not elastic:
        return []
    if "plasticine" not in supported:
        skipped.append(f"plasticity: simulator {ctx.simulator_name!r} has no plasticine law")
        return []
    decades = float(torch.log10(torch.tensor(YIELD_STRESS.upper / YIELD_STRESS.lower)))
    return [
        Candidate(
            "plasticity" if len(elastic) == 1 else f"plasticity@{k}",
            "plasticity",
            ["yield_decades_below_bound"],
            ["decade"],
            torch.tensor([0.0]),
            torch.tensor([decades]),
            torch.tensor([0.25]),
            PLASTIC_REGIMES,
            f"object {k} yields plastically (von Mises) though fitted as elastic",
            base={"object": k},
            ladder=PLASTICITY_LADDER,
        )
        for k in elastic
    ]
