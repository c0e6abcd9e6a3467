"""The discrete-library baseline: pick each object's material from fixed prototypes.

The OmniPhysGS-style comparison (docs/ARCHITECTURE.md, Stage III): instead of refining continuous
parameters, every object gets one entry of a small, fixed table of material prototypes, chosen
by the observed-frame loss of a full rollout. No parameter is ever adjusted continuously, so the
baseline is exactly as good as its table's nearest entry.

The table spans each family with a stiffness (or viscosity) ladder a decade apart, the
resolution of the hand-tuned presets such libraries ship with; all other parameters stay at the
law's defaults (``mosiv_framework.laws``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import torch

from mosiv_framework.errors import ConfigError, SimulationDiverged
from mosiv_framework.laws import get_law
from mosiv_framework.losses import WeightedSum
from mosiv_framework.pipeline.identify import geometry
from mosiv_framework.types import ObjectParams, ParticleSet, SimulationParams, World


@dataclass(frozen=True)
class Prototype:
    """One library entry: a name, its material family and the parameters it sets (SI units);
    parameters it does not name take the law's default."""

    name: str
    family: str
    params: dict[str, float]

    def values(self) -> dict[str, float]:
        law = get_law(self.family)
        values = {**law.defaults(), **self.params}
        law.validate(values, where=f"prototype {self.name}: ")
        return values


PROTOTYPES: tuple[Prototype, ...] = (
    # rubbers and foams: soft foam, rubber, hard rubber
    Prototype("elastic-soft", "elastic", {"E": 1.0e4}),
    Prototype("elastic-medium", "elastic", {"E": 1.0e5}),
    Prototype("elastic-stiff", "elastic", {"E": 1.0e6}),
    # doughs and clays: yield stress a decade below, or near, the stiffness scale
    Prototype("plasticine-soft", "plasticine", {"E": 1.0e4, "yield_stress": 1.0e3}),
    Prototype("plasticine-medium", "plasticine", {"E": 1.0e5, "yield_stress": 1.0e3}),
    Prototype("plasticine-firm", "plasticine", {"E": 1.0e5, "yield_stress": 1.0e4}),
    # granular media: loose, medium and dense packing
    Prototype("sand-loose", "sand", {"friction_angle": 20.0, "E": 1.0e5}),
    Prototype("sand-medium", "sand", {"friction_angle": 35.0, "E": 1.0e5}),
    Prototype("sand-dense", "sand", {"friction_angle": 45.0, "E": 1.0e5}),
    # liquids: thin syrup, syrup, honey
    Prototype("newtonian-thin", "newtonian", {"viscosity": 0.1, "bulk_modulus": 1.0e5}),
    Prototype("newtonian-medium", "newtonian", {"viscosity": 1.0, "bulk_modulus": 1.0e5}),
    Prototype("newtonian-thick", "newtonian", {"viscosity": 10.0, "bulk_modulus": 1.0e5}),
    # pastes and gels
    Prototype(
        "non_newtonian-soft",
        "non_newtonian",
        {"shear_modulus": 1.0e3, "bulk_modulus": 1.0e4, "yield_stress": 100.0},
    ),
    Prototype(
        "non_newtonian-medium",
        "non_newtonian",
        {"shear_modulus": 1.0e4, "bulk_modulus": 1.0e5, "yield_stress": 1.0e3},
    ),
    # snow: powder and packed
    Prototype("snow-powder", "snow", {"E": 1.0e4}),
    Prototype("snow-packed", "snow", {"E": 1.0e5}),
)


def candidates(family: str, *, scope: str, table=PROTOTYPES) -> list[Prototype]:
    """Prototypes an object of ``family`` may take: its family's, or every entry."""
    if scope == "all":
        return list(table)
    if scope != "family":
        raise ConfigError(f"identify.library_scope={scope!r}: valid values are family, all")
    found = [p for p in table if p.family == family]
    if not found:
        families = sorted({p.family for p in table})
        raise ConfigError(
            f"the prototype library has no entry of family {family!r} (it has {families}); "
            f"set identify.library_scope=all to choose among every family"
        )
    return found


def library_params(
    choice: dict[int, Prototype],
    velocities: dict[int, torch.Tensor],
    *,
    ground_friction: float,
    terms: dict[str, dict[str, torch.Tensor]] | None = None,
) -> SimulationParams:
    """SimulationParams with every object's values taken from its chosen prototype (and the
    recipe's physics ``terms``, unchanged)."""
    objects = {
        k: ObjectParams(
            p.family, {n: torch.tensor(v, dtype=torch.float32) for n, v in p.values().items()}
        )
        for k, p in choice.items()
    }
    v0 = {k: v.detach().clone().float() for k, v in velocities.items()}
    terms = {n: {p: v.detach() for p, v in ps.items()} for n, ps in (terms or {}).items()}
    return SimulationParams(objects, v0, torch.tensor(float(ground_friction)), terms)


def pick_prototypes(
    *,
    simulator,
    particles: ParticleSet,
    world: World,
    targets: dict[int, torch.Tensor],
    observed_frames: int,
    objective: WeightedSum,
    velocities: dict[int, torch.Tensor],
    ground_friction: float,
    terms: dict[str, dict[str, torch.Tensor]] | None = None,
    scope: str = "family",
    sweeps: int = 2,
    table=PROTOTYPES,
) -> tuple[dict[int, Prototype], list[dict]]:
    """Choose a prototype per object by coordinate descent on the observed-frame loss.

    Objects interact, so a joint search would try every combination; instead each sweep visits
    the objects in turn and tries every candidate of one object with the others held at their
    current choice (K * P rollouts per sweep instead of P^K). A candidate the simulator cannot
    follow (it diverges) scores infinity. Returns the choice and one record per rollout tried.
    """
    last = observed_frames - 1
    frames = list(range(1, last + 1))
    pool = {k: candidates(fam, scope=scope, table=table) for k, fam in particles.materials.items()}
    # start from each family's middle entry: the library's "typical" material of that kind
    choice = {
        k: c[len(c) // 2] if scope == "family" else _middle_of(c, particles.materials[k])
        for k, c in pool.items()
    }
    records: list[dict] = []
    cache: dict[tuple[str, ...], float] = {}

    def loss_of(trial: dict[int, Prototype]) -> float:
        key = tuple(trial[k].name for k in sorted(trial))
        if key in cache:
            return cache[key]
        params = library_params(trial, velocities, ground_friction=ground_friction, terms=terms)
        parts = replace(particles, materials={k: p.family for k, p in trial.items()})
        try:
            with torch.no_grad():
                traj = simulator.rollout(parts, params, world=world, frames=last)
            device = traj.positions.device
            target = geometry({k: t.to(device) for k, t in targets.items()}, frames)
            value = float(objective(geometry(traj, frames), target))
        except SimulationDiverged as exc:
            value, diverged = math.inf, str(exc)
        else:
            diverged = None
        cache[key] = value
        records.append(
            {"choice": dict(zip(map(str, sorted(trial)), key)), "loss": value}
            | ({"diverged": diverged} if diverged else {})
        )
        return value

    best = loss_of(choice)
    for _ in range(max(1, sweeps)):
        changed = False
        for k in sorted(pool):
            for proto in pool[k]:
                trial = {**choice, k: proto}
                value = loss_of(trial)
                if value < best:
                    best, choice, changed = value, trial, True
        if not changed:  # a sweep that changes nothing has converged
            break
    if not math.isfinite(best):
        raise SimulationDiverged(
            object_id=min(choice),
            frame=0,
            substep=0,
            reason="every prototype combination tried by the library baseline diverged",
            advice="Raise simulator.substeps or simulator.grid, or use identify.method=gradient.",
        )
    return choice, records


def _middle_of(pool: list[Prototype], family: str) -> Prototype:
    """The middle entry of ``family`` within ``pool`` (or of the pool if it has none)."""
    own = [p for p in pool if p.family == family] or pool
    return own[len(own) // 2]
