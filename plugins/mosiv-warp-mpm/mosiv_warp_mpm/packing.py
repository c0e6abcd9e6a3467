"""What a warp-mpm rollout is given, checked and flattened: the input checks, the packed
parameter vector ``theta`` (ObjectTables' layout) and the particles' initial velocities."""

from __future__ import annotations

import torch

from mosiv_framework.errors import ConfigError
from mosiv_framework.expression import (
    FEATURES,
    coefficient_problems,
    parse_coefficient,
    uses_relative,
)
from mosiv_framework.expression import NAME as EXPRESSION
from mosiv_framework.particle_order import rows_of
from mosiv_framework.types import ParticleSet, SimulationParams, World
from mosiv_warp_mpm.laws import LAW_IDS, LAW_PARAM_NAMES, N_SLOTS

#: physics term -> its parameter names (docs/PHYSICS.md, Physics terms); ``expression`` takes
#: any of its coefficients a_AXIS:FEATURE (mosiv_framework.expression), so it lists none here
TERMS: dict[str, tuple[str, ...]] = {
    "linear_drag": ("coefficient",),
    "quadratic_drag": ("coefficient",),
    "wind": ("acceleration",),
    "gravity": ("acceleration",),
    "material_damping": ("viscosity",),
    "ground_restitution": ("coefficient",),
    EXPRESSION: (),
}


def pack_theta(
    params: SimulationParams, object_ids: list[int], gravity: tuple, device
) -> torch.Tensor:
    """Flatten every differentiable parameter into ObjectTables' layout (float32, differentiable).

    Layout: per object N_SLOTS law parameters | rho per object | friction per object |
    ground_friction | body acceleration (3) | drag (linear, quadratic) | material_damping
    viscosity (Pa s) | ground_restitution coefficient | the expression term
    (``pack_expression``). An absent term packs as 0, its "off".
    """
    zero = torch.zeros((), dtype=torch.float32, device=device)

    def val(t) -> torch.Tensor:
        return torch.as_tensor(t, dtype=torch.float32).to(device).reshape(-1)

    parts = []
    for k in object_ids:
        p = params.objects[k]
        names = LAW_PARAM_NAMES[p.family]
        parts += [val(p.values[n]) for n in names] + [zero.reshape(1)] * (N_SLOTS - len(names))
    parts += [val(params.objects[k].values["rho"]) for k in object_ids]
    parts += [val(params.objects[k].values["friction"]) for k in object_ids]
    parts.append(val(params.ground_friction))
    terms = params.terms
    g = val(terms["gravity"]["acceleration"]) if "gravity" in terms else val(gravity)
    wind = val(terms["wind"]["acceleration"]) if "wind" in terms else torch.zeros(3, device=device)
    parts.append(g + wind)
    lin = val(terms["linear_drag"]["coefficient"]) if "linear_drag" in terms else val(zero)
    quad = val(terms["quadratic_drag"]["coefficient"]) if "quadratic_drag" in terms else val(zero)
    parts += [lin, quad]
    for term, name in (("material_damping", "viscosity"), ("ground_restitution", "coefficient")):
        parts.append(val(terms[term][name]) if term in terms else val(zero))
    parts.append(pack_expression(terms.get(EXPRESSION, {}), device))
    return torch.cat(parts)


def pack_expression(values: dict[str, torch.Tensor], device) -> torch.Tensor:
    """The expression term's part of theta: two switches (the term is on; it uses the other
    objects' features) then, per feature of ``FEATURES`` in order, its coefficients in
    (a_x, a_y, a_z); coefficients not given are 0. Differentiable in ``values``."""
    zero = torch.zeros((), dtype=torch.float32, device=device)
    coefficients = [zero] * (3 * len(FEATURES))
    for name, c in values.items():
        axis, feature = parse_coefficient(name)
        coefficients[3 * FEATURES.index(feature) + axis] = (
            torch.as_tensor(c, dtype=torch.float32).to(device).reshape(())
        )
    switches = torch.tensor(
        [float(bool(values)), float(bool(values) and uses_relative(values))],
        dtype=torch.float32,
        device=device,
    )
    return torch.cat([switches, torch.stack(coefficients)])


def initial_velocities(
    params: SimulationParams, object_ids: list[int], obj_index: torch.Tensor
) -> torch.Tensor:
    """Each particle's initial velocity [N, 3] (its object's), differentiable in params."""
    dev = obj_index.device
    v_obj = torch.stack(
        [
            torch.as_tensor(params.initial_velocity[k], dtype=torch.float32).to(dev)
            for k in object_ids
        ]
    )
    return rows_of(v_obj, obj_index)


def check_inputs(
    particles: ParticleSet,
    params: SimulationParams,
    world: World,
    frames: int,
    *,
    contact: str = "multi_field",
):
    """Raise ConfigError listing every inconsistency between particles, params and world
    (and, for the expression term, the ``contact`` mode)."""
    problems = []
    if not isinstance(frames, int) or frames < 0:
        problems.append(f"frames={frames!r}: must be an integer >= 0")
    for k, fam in sorted(particles.materials.items()):
        if fam not in LAW_IDS:
            problems.append(f"object {k}: material {fam!r} unsupported; valid: {list(LAW_IDS)}")
            continue
        if k not in params.objects:
            problems.append(f"object {k}: no ObjectParams in params.objects")
            continue
        p = params.objects[k]
        if p.family != fam:
            problems.append(f"object {k}: params family {p.family!r} but particles say {fam!r}")
        needed = (*LAW_PARAM_NAMES[fam], "rho", "friction")
        for name in needed:
            if name not in p.values:
                problems.append(f"object {k} ({fam}): missing parameter {name!r}; needs {needed}")
            elif not torch.isfinite(torch.as_tensor(p.values[name])).all():
                problems.append(f"object {k}: parameter {name} is not finite")
        nu = float(torch.as_tensor(p.values["nu"]).detach()) if "nu" in p.values else None
        if nu is not None and not 0.0 <= nu < 0.5:
            problems.append(f"object {k}: nu={nu} must lie in [0, 0.5)")
        if k not in params.initial_velocity:
            problems.append(f"object {k}: no initial_velocity")
    for term, values in params.terms.items():
        if term not in TERMS:
            problems.append(f"physics term {term!r} unsupported; valid: {sorted(TERMS)}")
        elif term == EXPRESSION:
            problems += expression_problems(values, contact)
        elif set(values) != set(TERMS[term]):
            problems.append(
                f"physics term {term!r} needs exactly {TERMS[term]}, got {sorted(values)}"
            )
    x = particles.positions
    lo = torch.tensor(world.domain_lower, dtype=x.dtype, device=x.device)
    hi = torch.tensor(world.domain_upper, dtype=x.dtype, device=x.device)
    outside = int(((x < lo) | (x > hi)).any(dim=1).sum())
    if outside:
        problems.append(
            f"{outside} particle(s) lie outside the scene domain {world.domain_lower}.."
            f"{world.domain_upper} m"
        )
    if problems:
        raise ConfigError([f"warp-mpm rollout: {p}" for p in problems])


def expression_problems(values: dict[str, torch.Tensor], contact: str) -> list[str]:
    """What is wrong with the expression term's coefficients: names that are no (axis,
    feature) pair, values that are not finite numbers, and the other objects' features
    without one velocity field per object."""
    problems = coefficient_problems(values)
    if not problems and contact != "multi_field" and uses_relative(values):
        problems.append(
            "expression uses the other objects' features (dp_*, dv_*), which need one velocity "
            f"field per object: set the simulator's contact: multi_field (now {contact!r})"
        )
    return problems
