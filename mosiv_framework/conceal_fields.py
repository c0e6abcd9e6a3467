"""Out-of-library concealed effects: acceleration fields that no MOSIV physics term expresses.

A diagnosis can only name effects its library holds (``mosiv_framework.terms`` and the
candidates of ``diagnose.candidates``); these kinds are there to test what it says about an
effect outside that library ("unexplained" or "discrepancy", and the law ``discover`` writes).
No registered physics term may carry one of their names (``library_conflicts``).

Each field is written as Genesis' force fields compute it (``genesis.engine.force_fields``,
genesis-world 1.4.5), with the settings the ``genesis`` scene source uses, so that the numpy
function here is the truth the recording was made with:

- ``vortex``: Genesis' ``Vortex`` (always about the vertical axis through ``center``; falloff
  power 0, no damping): a = strength (-(y - c_y), x - c_x, 0) - radial (x - c_x, y - c_y, 0).
  ``strength`` (1/s^2) > 0 turns counter-clockwise seen from above; ``radial`` (1/s^2) > 0
  pulls towards the axis. The acceleration grows linearly with the distance from the axis.
- ``attractor``: Genesis' ``Point`` with a negative strength (falloff power 0, no flow): a pull
  of constant magnitude ``strength`` (m/s^2) towards ``position``,
  a = -strength (x - p) / sqrt(|x - p|^2 + eps), eps = 1.19e-7 m^2 (Genesis' float32 EPS).

Genesis adds a field's acceleration on the MPM grid nodes, at the node's position and velocity;
a body's centroid acceleration is the mass-weighted mean of the field over its material, which
for the vortex (linear in position) equals the field at the centroid.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from typing import Any

import numpy as np

# Defaults: clearly visible over the ~0.2 s flight before a collision of the Genesis protocol
# (launch points 0.15-0.25 m from the vertical axis through the domain centre, collision
# point within 4 cm of it at 0.22-0.32 m height).
# vortex 12 1/s^2: 1.8-3 m/s^2 sideways at the launch points, the two bodies pushed in opposite
#   directions (no uniform wind can do that); ~1 m/s^2 within 8 cm of the axis after impact.
# attractor 3 m/s^2 towards the middle of the collision region: the bodies are pulled along
#   their approach, towards each other (a drag cannot speed them up, a wind cannot pull them
#   apart-ways), and lifted by up to 3 m/s^2 once they lie on the table below it.
FIELD_DEFAULTS: dict[str, dict[str, float | tuple[float, float, float]]] = {
    "vortex": {"strength": 12.0, "radial": 0.0, "center": (0.0, 0.0, 0.0)},
    "attractor": {"strength": 3.0, "position": (0.0, 0.0, 0.27)},
}
#: concealed kinds outside the diagnosis library
OUT_OF_LIBRARY_KINDS = tuple(FIELD_DEFAULTS)
#: Genesis' regularisation of |x - p| (its EPS at 32-bit precision), m^2
ATTRACTOR_EPS = float(np.finfo(np.float32).eps)

FORMULAS = {
    "vortex": "a = strength * (-(y - center_y), x - center_x, 0) "
    "- radial * (x - center_x, y - center_y, 0)",
    "attractor": "a = -strength * (x - position) / sqrt(|x - position|^2 + 1.19e-7)",
}


def vortex_acceleration(
    pos: np.ndarray,
    vel: np.ndarray | None = None,
    t: float = 0.0,
    *,
    strength: float,
    radial: float = 0.0,
    center: Iterable[float] = (0.0, 0.0, 0.0),
) -> np.ndarray:
    """The vortex's acceleration (m/s^2) at positions ``pos``.

    Args:
        pos: [..., 3] positions (m), z up.
        vel: velocities (unused: the field does not depend on them).
        t: time (s, unused: the field is steady).
        strength: tangential strength (1/s^2), counter-clockwise about +z if positive.
        radial: radial strength (1/s^2), towards the axis if positive.
        center: a point of the vertical axis (m); its z does not matter.

    Returns:
        [..., 3] accelerations.
    """
    pos = np.asarray(pos, dtype=np.float64)
    c = np.asarray(tuple(center), dtype=np.float64)
    dx, dy = pos[..., 0] - c[0], pos[..., 1] - c[1]
    ax = -strength * dy - radial * dx
    ay = strength * dx - radial * dy
    return np.stack([ax, ay, np.zeros_like(ax)], axis=-1)


def attractor_acceleration(
    pos: np.ndarray,
    vel: np.ndarray | None = None,
    t: float = 0.0,
    *,
    strength: float,
    position: Iterable[float],
) -> np.ndarray:
    """The attractor's acceleration (m/s^2) at positions ``pos``.

    Args:
        pos: [..., 3] positions (m).
        vel: velocities (unused).
        t: time (s, unused).
        strength: magnitude of the pull (m/s^2), towards ``position``.
        position: the attracting point (m).

    Returns:
        [..., 3] accelerations, of magnitude ``strength`` away from the point itself.
    """
    d = np.asarray(pos, dtype=np.float64) - np.asarray(tuple(position), dtype=np.float64)
    r = np.sqrt((d * d).sum(axis=-1, keepdims=True) + ATTRACTOR_EPS)
    return -strength * d / r


FUNCTIONS = {"vortex": vortex_acceleration, "attractor": attractor_acceleration}


def field_acceleration(
    effect: Mapping[str, Any], pos: np.ndarray, vel: np.ndarray | None = None, t: float = 0.0
) -> np.ndarray:
    """The acceleration of one out-of-library effect as gt/effects.json records it (``kind``,
    ``params``) at ``pos`` [..., 3] (m), ``vel`` (m/s) and time ``t`` (s).

    Raises ValueError for a kind that is not one of ``OUT_OF_LIBRARY_KINDS``. The function is
    chosen by the kind, never by a name read from the file."""
    kind = effect.get("kind")
    if kind not in FUNCTIONS:
        raise ValueError(
            f"no acceleration field for effect kind {kind!r}; fields: "
            f"{', '.join(OUT_OF_LIBRARY_KINDS)}"
        )
    params = {k: tuple(v) if isinstance(v, list) else v for k, v in effect["params"].items()}
    return FUNCTIONS[kind](pos, vel, t, **params)


def linear_form(kind: str, params: Mapping[str, Any]) -> dict[str, dict[str, float]] | None:
    """The field as a linear law in the discovery's features (``diagnose.discover``: "1", x,
    y, ...; z up), per axis {feature: coefficient}, where it is one exactly (the vortex);
    None where it is not (the attractor's unit direction is no linear law)."""
    if kind != "vortex":
        return None
    s, r = float(params["strength"]), float(params["radial"])
    cx, cy = float(params["center"][0]), float(params["center"][1])
    return {  # + 0.0: no negative zero in the record
        "x": {"x": -r + 0.0, "y": -s + 0.0, "1": s * cy + r * cx + 0.0},
        "y": {"x": s + 0.0, "y": -r + 0.0, "1": -s * cx + r * cy + 0.0},
        "z": {},
    }


def truth_record(kind: str, params: Mapping[str, Any]) -> dict[str, Any]:
    """What gt/effects.json adds to an out-of-library effect's kind and params: its formula,
    the function that evaluates it, ``library: false``, and its linear form where it has one."""
    return {
        "library": False,
        "formula": FORMULAS[kind],
        "function": f"{__name__}:{FUNCTIONS[kind].__name__}",
        "linear_form": linear_form(kind, params),
    }


def library_conflicts(names: Iterable[str]) -> list[str]:
    """The out-of-library kinds among ``names`` (e.g. the registered physics terms): a term of
    that name would put the effect inside the library, and the suite's scoring would be wrong."""
    return sorted(set(names) & set(OUT_OF_LIBRARY_KINDS))
