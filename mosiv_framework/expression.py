"""The ``expression`` physics term: a force law written as a sparse sum of library features.

Open-form discovery (``diagnose.discover``) writes what no library term explains as
a_axis = sum_k c_k phi_k, per axis, with phi_k from a library of features of an object's state.
The expression term applies such a law on the simulator's grid: at every node of object k's
velocity field, with the node's position x (m), its velocity v (the free velocity m v / m
before forces, m/s) and the time t (s),

    a = sum over the given (axis, feature) pairs of c * phi(x, v, t, ...)  e_axis  (m/s^2)

Features (``FEATURES``; the node-local ones are ``discover.NODE_LOCAL``):

- ``1``: a constant (a steady acceleration, like ``wind``);
- ``x``, ``y``, ``z``: the node's position;
- ``h``: its height above the ground, x . up - ground height, with up opposite the scene's
  declared gravity (z if it declares none) and the ground height 0 where there is no ground;
- ``v_x`` .. ``v_z``: its velocity; ``|v|v_x`` .. ``|v|v_z``: speed times velocity;
- ``t``: the time since frame 0;
- ``dp_x`` .. ``dp_z``: the sum over the other objects j of (centre of mass of j - x);
  ``dv_x`` .. ``dv_z``: the same for velocities (centre-of-mass velocity of j - v). These need
  one velocity field per object (multi-field contact), where every node belongs to one object.

Summed over an object's nodes with their masses, every feature but ``|v|v`` gives the object
exactly the law at its centre of mass (quadratic B-splines reproduce linear functions), which
is the centroid law discovery regressed.

Parameters are the coefficients, one scalar per (axis, feature) pair, named ``a_x:v_x`` (the
coefficient of v_x in a_x). The term is sparse (``PhysicsTerm.sparse``): only the pairs given
act, and an identified expression frees only those. In a recipe::

    physics_terms:
      expression: {"a_x:v_x": -0.41, "a_z:h": -2.0, identify: true}
"""

from __future__ import annotations

import torch

from mosiv_framework.interfaces import PhysicsTerm
from mosiv_framework.laws.base import ParamSpec

Tensor = torch.Tensor
AXES = ("x", "y", "z")
NAME = "expression"
#: features of the material at one place and time; their order is the simulators' feature code
NODE_FEATURES = ("1", "x", "y", "z", "h", "v_x", "v_y", "v_z", "|v|v_x", "|v|v_y", "|v|v_z", "t")
#: features of the other objects relative to the node (one velocity field per object)
RELATIVE_FEATURES = ("dp_x", "dp_y", "dp_z", "dv_x", "dv_y", "dv_z")
FEATURES = NODE_FEATURES + RELATIVE_FEATURES
#: features a torch reference can evaluate from a velocity alone (``reference_acceleration``)
VELOCITY_FEATURES = ("1", "v_x", "v_y", "v_z", "|v|v_x", "|v|v_y", "|v|v_z")

#: feature -> (coefficient unit, bound on |c|). The bounds are wide on purpose: a spring of
#: 30 rad/s is 900 1/s^2; the diagnosis's coefficient interval, not the bound, says what the
#: data support
_COEFFICIENT = {
    "1": ("m/s^2", 50.0),
    "x": ("1/s^2", 1000.0),
    "h": ("1/s^2", 1000.0),
    "dp": ("1/s^2", 1000.0),
    "v": ("1/s", 50.0),
    "dv": ("1/s", 50.0),
    "|v|v": ("1/m", 50.0),
    "t": ("m/s^3", 100.0),
}


def _kind(feature: str) -> str:
    if feature in ("x", "y", "z"):
        return "x"
    return feature.rsplit("_", 1)[0] if "_" in feature else feature


def coefficient_unit(feature: str) -> str:
    """SI unit of the coefficient of ``feature`` (so that c phi is an acceleration)."""
    return _COEFFICIENT[_kind(feature)][0]


def coefficient_name(axis: str, feature: str) -> str:
    """The parameter name of the coefficient of ``feature`` in the acceleration along ``axis``."""
    return f"a_{axis}:{feature}"


def feature_list_text() -> str:
    return ", ".join(FEATURES)


def parse_coefficient(name: str) -> tuple[int, str]:
    """(axis index, feature) of a parameter name ``a_AXIS:FEATURE``; ValueError naming what
    is wrong and what would be valid."""
    head, sep, feature = str(name).partition(":")
    if not sep or head not in tuple(f"a_{a}" for a in AXES):
        raise ValueError(
            f"expression parameter {name!r}: name a coefficient as a_AXIS:FEATURE with AXIS one "
            f"of {', '.join(AXES)} (e.g. a_x:v_x, the coefficient of v_x in a_x)"
        )
    if feature not in FEATURES:
        raise ValueError(
            f"expression parameter {name!r}: unknown feature {feature!r}; valid features: "
            f"{feature_list_text()}"
        )
    return AXES.index(head[2:]), feature


def coefficient_problems(values) -> list[str]:
    """What a backend cannot apply of an expression's coefficients (name -> value): names
    that are no (axis, feature) pair, and values that are not one finite number."""
    problems = []
    for name, value in values.items():
        try:
            parse_coefficient(name)
        except ValueError as exc:
            problems.append(str(exc))
            continue
        t = torch.as_tensor(value)
        if t.numel() != 1 or not bool(torch.isfinite(t).all()):
            problems.append(f"expression parameter {name!r} must be one finite number (got {t})")
    return problems


def uses_relative(values) -> bool:
    """Whether an expression's parameters (names) use the other objects' features."""
    return any(parse_coefficient(name)[1] in RELATIVE_FEATURES for name in values)


class ExpressionTerm(PhysicsTerm):
    """a = sum c phi over the (axis, feature) coefficients given (module docstring)."""

    name = NAME
    params = tuple(
        ParamSpec(
            coefficient_name(axis, feature),
            coefficient_unit(feature),
            -_COEFFICIENT[_kind(feature)][1],
            _COEFFICIENT[_kind(feature)][1],
            0.0,
            description=f"c in a_{axis} += c {feature}",
        )
        for axis in AXES
        for feature in FEATURES
    )
    regimes = frozenset({"free_flight", "object_contact", "ground_contact", "rest"})
    description = "a discovered force law a = sum_k c_k phi_k(x, v, t, ...) on grid nodes"
    sparse = True

    def parameter_names_text(self) -> str:
        return (
            f"a_AXIS:FEATURE with AXIS one of {', '.join(AXES)} and FEATURE one of "
            f"{feature_list_text()} (e.g. a_x:v_x)"
        )

    def reference_acceleration(self, velocity: Tensor, values: dict[str, Tensor]) -> Tensor:
        """The acceleration of a law of the velocity features only (``VELOCITY_FEATURES``); a
        law of position, time or the other objects needs ``acceleration``."""
        needs = sorted({parse_coefficient(n)[1] for n in values} - set(VELOCITY_FEATURES))
        if needs:
            raise ValueError(
                f"expression uses {needs}: its acceleration needs positions, time or the other "
                "objects (ExpressionTerm.acceleration), not the velocity alone"
            )
        zero = torch.zeros_like(velocity[:, 0])
        features = node_features(velocity * 0.0, velocity, zero)
        return acceleration(values, features)


def up_vector(gravity) -> Tensor:
    """The unit "up" of a scene: opposite its gravity, z where it declares none."""
    g = torch.as_tensor(gravity, dtype=torch.float64)
    norm = g.norm()
    return torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64) if norm == 0 else -g / norm


def node_features(
    position: Tensor,
    velocity: Tensor,
    time: Tensor,
    *,
    up=(0.0, 0.0, 1.0),
    ground_height: float | None = None,
    others_position: Tensor | None = None,
    others_velocity: Tensor | None = None,
) -> dict[str, Tensor]:
    """Every feature [N] at N points: positions, velocities [N, 3], times [N]; the other
    objects' features from ``others_position``/``others_velocity`` [N, J, 3] (their centres
    of mass and velocities, J others; zero features without them)."""
    up = torch.as_tensor(up, dtype=position.dtype, device=position.device)
    speed = velocity.norm(dim=1)
    out = {"1": torch.ones_like(time)}
    for a, axis in enumerate(AXES):
        out[axis] = position[:, a]
    out["h"] = position @ up - (ground_height or 0.0)
    for a, axis in enumerate(AXES):
        out[f"v_{axis}"] = velocity[:, a]
        out[f"|v|v_{axis}"] = speed * velocity[:, a]
    out["t"] = time
    rel_p = torch.zeros_like(position)
    rel_v = torch.zeros_like(velocity)
    if others_position is not None:
        rel_p = (others_position - position[:, None]).sum(dim=1)
        rel_v = (others_velocity - velocity[:, None]).sum(dim=1)
    for a, axis in enumerate(AXES):
        out[f"dp_{axis}"] = rel_p[:, a]
        out[f"dv_{axis}"] = rel_v[:, a]
    return out


def acceleration(values: dict[str, Tensor], features: dict[str, Tensor]) -> Tensor:
    """[N, 3] sum of c phi over the coefficients ``values`` (name -> 0-d tensor), with the
    features of ``node_features``; the torch reference of the simulators' kernels."""
    one = features["1"]
    columns = [torch.zeros_like(one) for _ in AXES]
    for name, c in values.items():
        axis, feature = parse_coefficient(name)
        columns[axis] = columns[axis] + torch.as_tensor(c).to(one) * features[feature]
    return torch.stack(columns, dim=1)
