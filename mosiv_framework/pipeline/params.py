"""Building simulation parameters and the optimiser's view of them.

The optimiser works on a vector of unconstrained leaves: initial velocities in m/s, and every
identified physical parameter through its ParamSpec's normalised coordinate in [0, 1] (log space
for stiffnesses and viscosities), so one learning rate suits parameters that differ by orders of
magnitude and bounds always hold.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch

from mosiv_framework.laws import get_law
from mosiv_framework.laws.base import ParamSpec
from mosiv_framework.types import ObjectParams, SimulationParams

GROUND_FRICTION = ParamSpec(
    "ground_friction", "1", 0.0, 2.0, 0.3, description="table Coulomb coefficient"
)

#: Scaling every object's density and stiffness by one factor leaves the motion unchanged
#: (stress, weight and friction all scale alike), so one density fixes that gauge: the first
#: object's rho stays at its given value and the other objects' densities are identified
#: relative to it (their ratios decide how momentum is exchanged in a collision).
GAUGE_PARAM = "rho"


def initial_velocity_from_points(
    points: dict[int, torch.Tensor], *, fps: float, gravity: tuple[float, float, float]
) -> dict[int, torch.Tensor]:
    """v0 per object from the centroid displacement over the first frame.

    Ballistic flight: c(1) - c(0) = v0 dt + g dt^2 / 2, so v0 = (c(1) - c(0)) / dt - g dt / 2.
    """
    dt = 1.0 / fps
    g = torch.tensor(gravity, dtype=torch.float32)
    return {
        k: ((pts[1].mean(0) - pts[0].mean(0)) / dt - 0.5 * g * dt).to(torch.float32)
        for k, pts in points.items()
    }


@dataclass
class ParameterVector:
    """The identified quantities of a scene as optimisable leaves.

    ``velocity`` leaves are m/s; ``normalized`` leaves are ParamSpec coordinates in [0, 1].
    """

    families: dict[int, str]
    fixed: dict[int, dict[str, float]]
    velocity: dict[int, torch.Tensor]
    normalized: dict[str, torch.Tensor]
    specs: dict[str, ParamSpec] = field(default_factory=dict)

    @classmethod
    def create(
        cls,
        families: dict[int, str],
        velocities: dict[int, torch.Tensor],
        *,
        values: dict[int, dict[str, float]] | None = None,
        ground_friction: float | None = GROUND_FRICTION.default,
        identify: tuple[str, ...] | None = None,
        identify_friction: bool = True,
        identify_ground_friction: bool = True,
    ) -> ParameterVector:
        """Leaves for every parameter of every object's law (from ``values`` or defaults).

        ``identify`` restricts which parameter names are optimised (default: all but the
        first object's density, see GAUGE_PARAM); the rest are kept fixed at their value.
        """
        values = values or {}
        fixed: dict[int, dict[str, float]] = {}
        normalized: dict[str, torch.Tensor] = {}
        specs: dict[str, ParamSpec] = {}
        gauge_object = min(families)
        for k, family in families.items():
            law = get_law(family)
            start = {**law.defaults(), **values.get(k, {})}
            law.validate(start, where=f"object {k}: ")
            fixed[k] = {}
            for spec in law.all_params:
                if identify is None:
                    free = not (spec.name == GAUGE_PARAM and k == gauge_object)
                else:
                    free = spec.name in identify
                if spec.name == "friction" and (not identify_friction or len(families) < 2):
                    free = False  # inter-object friction only matters with two or more bodies
                if free:
                    key = f"obj{k}.{spec.name}"
                    specs[key] = spec
                    normalized[key] = spec.to_normalized(torch.tensor(float(start[spec.name])))
                else:
                    fixed[k][spec.name] = float(start[spec.name])
        if ground_friction is not None:
            if identify_ground_friction:
                specs["ground_friction"] = GROUND_FRICTION
                normalized["ground_friction"] = GROUND_FRICTION.to_normalized(
                    torch.tensor(float(ground_friction))
                )
            else:
                fixed[0] = {"ground_friction": float(ground_friction)}
        velocity = {k: v.detach().clone().to(torch.float32) for k, v in velocities.items()}
        for leaf in [*velocity.values(), *normalized.values()]:
            leaf.requires_grad_(True)
        return cls(dict(families), fixed, velocity, normalized, specs)

    def physical(self) -> SimulationParams:
        """The SimulationParams these leaves stand for (differentiable w.r.t. the leaves)."""
        objects = {}
        for k, family in self.families.items():
            vals = {n: torch.tensor(v, dtype=torch.float32) for n, v in self.fixed[k].items()}
            for key, u in self.normalized.items():
                if key.startswith(f"obj{k}."):
                    vals[key.split(".", 1)[1]] = (
                        self.specs[key].from_normalized(u).to(torch.float32)
                    )
            objects[k] = ObjectParams(family, vals)
        if "ground_friction" in self.normalized:
            gf = GROUND_FRICTION.from_normalized(self.normalized["ground_friction"])
        else:
            gf = torch.tensor(self.fixed.get(0, {}).get("ground_friction", GROUND_FRICTION.default))
        return SimulationParams(objects, dict(self.velocity), gf.to(torch.float32))

    def to_json(self) -> dict:
        """Plain numbers: per object family, parameter values and initial velocity."""
        params = self.physical()
        return {
            "objects": {
                str(k): {
                    "family": p.family,
                    "params": {n: float(v.detach()) for n, v in sorted(p.values.items())},
                    "initial_velocity": [float(x) for x in params.initial_velocity[k]],
                }
                for k, p in params.objects.items()
            },
            "ground_friction": float(params.ground_friction),
        }

    @staticmethod
    def from_json(data: dict) -> SimulationParams:
        objects, v0 = {}, {}
        for k, obj in data["objects"].items():
            objects[int(k)] = ObjectParams(
                obj["family"], {n: torch.tensor(float(v)) for n, v in obj["params"].items()}
            )
            v0[int(k)] = torch.tensor(obj["initial_velocity"], dtype=torch.float32)
        return SimulationParams(objects, v0, torch.tensor(float(data["ground_friction"])))
