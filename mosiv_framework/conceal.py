"""Concealed physics: effects a generating simulation contains but scene.json does not declare.

Shared by every scene source (mosiv-synth, mosiv-genesis, third-party generators) so that specs,
default strengths and gt/effects.json entries mean the same everywhere.

Spec syntax (CLI ``--conceal`` and the ``conceal`` option): ``KIND[:param=value,...]``; several
effects are separated by ``;`` or given as a list. A vector value continues over the following
comma-separated numbers: ``wind:acceleration=1.5,0,0``. Omitted parameters take the defaults
below, chosen so that the effect is clearly visible over a ~1 s clip yet does not stop the
planned collision from happening.

Body-force, material-damping and restitution kinds map onto the core PhysicsTerms
(``mosiv_framework.terms``) that the simulator backends implement; ``ground_friction`` replaces
the table's Coulomb coefficient, ``object_friction`` every body's Coulomb coefficient against
the others, and ``plasticity`` simulates every body declared ``elastic`` as ``plasticine`` (same
E, nu) with the given von Mises yield stress.

The out-of-library kinds (``vortex``, ``attractor``; ``conceal_fields``) are acceleration fields
no physics term of the diagnosis expresses. ``parse_conceal`` takes them only from a source that
lists them in its ``kinds``, and their gt/effects.json entries carry the formula and the function
that evaluate them (``Effect.to_json``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from mosiv_framework.conceal_fields import FIELD_DEFAULTS, OUT_OF_LIBRARY_KINDS, truth_record

# kind -> {param: default}; floats are scalars, 3-tuples vectors.
# linear_drag 1.5 1/s: loses ~30 % of the speed over the ~0.25 s flight before the collision.
# quadratic_drag 1.0 1/m: at 1.5 m/s it decelerates by 2.25 m/s^2, a quarter of gravity.
# wind 1.5 m/s^2 sideways: ~5 cm of drift per 0.25 s of flight, several pixels at 128 px.
# gravity -12 m/s^2: 22 % stronger than declared, so falls are visibly faster.
# ground_friction 0.05: a slippery table (PTFE-coated or wet, mu ~ 0.04-0.1) against the 0.3-0.6
#   the generator draws otherwise. A grippier table hardly shows: landed objects already stop
#   within ~1 cm at 0.3-0.6 (measured: mu = 1.2 moved a tiny scene's centroids < 0.7 cm, mu =
#   0.05 moved the sliding object by 6-12 cm within 0.3-0.5 s after landing).
# material_damping 30 Pa s: for the generator's ~0.1 m, E ~ 5e4 Pa bodies (fundamental ~200
#   rad/s) a damping ratio eta omega / (2 E) ~ 0.06, so impacts ring down within a few periods
#   and bounce less (measured on the benchmark test's 16-frame apple/barrel scene: last-frame
#   centroids moved by 2.8 and 0.9 cm). The explicit step needs dt < rho dx^2 / (6 eta): at the
#   default 32-cell grid over 1 m and 40 substeps that allows up to ~150 Pa s.
# ground_restitution 0.6: a springy table (hard rubber on wood ~0.6-0.8) against the inelastic
#   default; landings rebound higher (measured on the same scene: 2.3 cm last-frame shift).
# object_friction 1.2: sticky bodies (rubber on rubber ~1-1.5) against the 0.2-0.5 the
#   generator draws and the 0.3 a run assumes when it does not identify friction; a glancing
#   collision then spins the bodies and drags them along each other.
# plasticity 3 kPa: the middle of the generator's plasticine range; at E ~ 5e4 Pa a body yields
#   beyond ~8 % deviatoric strain, which a 1-2 m/s impact or landing exceeds, so it keeps a dent.
CONCEAL_DEFAULTS: dict[str, dict[str, float | tuple[float, float, float]]] = {
    "linear_drag": {"coefficient": 1.5},
    "quadratic_drag": {"coefficient": 1.0},
    "wind": {"acceleration": (1.5, 0.0, 0.0)},
    "gravity": {"acceleration": (0.0, 0.0, -12.0)},
    "ground_friction": {"coefficient": 0.05},
    "material_damping": {"viscosity": 30.0},
    "ground_restitution": {"coefficient": 0.6},
    "object_friction": {"coefficient": 1.2},
    "plasticity": {"yield_stress": 3000.0},
}
#: every kind a spec may name: the library's (above) and the out-of-library fields
ALL_DEFAULTS = {**CONCEAL_DEFAULTS, **FIELD_DEFAULTS}
#: plasticine's yield-stress bounds (Pa), kept here so that parsing a spec loads no law module
YIELD_STRESS_RANGE = (10.0, 1e6)
#: kinds that are simulator PhysicsTerms (the rest are realised through SimulationParams)
TERM_KINDS = (
    "linear_drag",
    "quadratic_drag",
    "wind",
    "gravity",
    "material_damping",
    "ground_restitution",
)


@dataclass(frozen=True)
class Effect:
    """One concealed effect: its kind and parameter values (floats or 3-tuples)."""

    kind: str
    params: dict[str, Any]

    @property
    def in_library(self) -> bool:
        """Whether the diagnosis has a candidate for this kind (not an out-of-library field)."""
        return self.kind not in OUT_OF_LIBRARY_KINDS

    def to_json(self) -> dict[str, Any]:
        """The gt/effects.json entry: vectors as lists; an out-of-library field also records
        its formula and function (``conceal_fields.truth_record``)."""
        params = {k: list(v) if isinstance(v, tuple) else float(v) for k, v in self.params.items()}
        out = {"kind": self.kind, "params": params}
        if not self.in_library:
            out.update(truth_record(self.kind, self.params))
        return out

    def spec(self) -> str:
        """The canonical ``KIND:param=value,...`` string (parses back to the same effect)."""
        parts = []
        for k, v in self.params.items():
            text = ",".join(repr(float(x)) for x in v) if isinstance(v, tuple) else repr(float(v))
            parts.append(f"{k}={text}")
        return f"{self.kind}:{','.join(parts)}" if parts else self.kind


def _parse_one(text: str, kinds: tuple[str, ...]) -> Effect:
    kind, _, rest = text.strip().partition(":")
    kind = kind.strip()
    if kind not in kinds:
        what = "an out-of-library field" if kind in OUT_OF_LIBRARY_KINDS else "unknown"
        raise ValueError(
            f"effect kind {kind!r}: {what} for this scene source; valid kinds: {', '.join(kinds)}"
        )
    defaults = ALL_DEFAULTS[kind]
    values: dict[str, list[float]] = {}
    current: str | None = None
    for token in (t.strip() for t in rest.split(",") if t.strip()):
        if "=" in token:
            current, _, number = token.partition("=")
            current = current.strip()
            if current not in defaults:
                raise ValueError(
                    f"{kind}: unknown parameter {current!r}; valid: {', '.join(defaults)}"
                )
            if current in values:
                raise ValueError(f"{kind}: parameter {current!r} given twice")
            values[current] = []
        elif current is None:
            raise ValueError(f"{kind}: {token!r} is not of the form param=value")
        else:
            number = token
        try:
            x = float(number)
        except ValueError:
            raise ValueError(f"{kind}.{current}: {number!r} is not a number") from None
        if not math.isfinite(x):
            raise ValueError(f"{kind}.{current}: {number!r} must be finite")
        values[current].append(x)
    params: dict[str, Any] = {}
    for name, default in defaults.items():
        if name not in values:
            params[name] = default
        elif isinstance(default, tuple):
            if len(values[name]) != 3:
                raise ValueError(
                    f"{kind}.{name}: a vector needs 3 numbers (e.g. {name}=1.5,0,0), "
                    f"got {values[name]}"
                )
            params[name] = tuple(values[name])
        else:
            if len(values[name]) != 1:
                raise ValueError(f"{kind}.{name}: takes one number, got {values[name]}")
            params[name] = values[name][0]
    _check_range(kind, params)
    return Effect(kind, params)


def _check_range(kind: str, params: dict[str, Any]) -> None:
    """Reject values no simulation can honour (negative drag or friction)."""
    for name in ("coefficient", "viscosity"):
        if name in params and params[name] < 0:
            raise ValueError(f"{kind}.{name}={params[name]} must be >= 0")
    if kind == "attractor" and params["strength"] < 0:
        raise ValueError(f"{kind}.strength={params['strength']} must be >= 0 (a pull)")
    if kind == "ground_restitution" and params["coefficient"] > 1:
        raise ValueError(f"{kind}.coefficient={params['coefficient']} must be <= 1")
    if (
        kind == "plasticity"
        and not YIELD_STRESS_RANGE[0] <= params["yield_stress"] <= YIELD_STRESS_RANGE[1]
    ):
        raise ValueError(
            f"{kind}.yield_stress={params['yield_stress']} Pa must lie in "
            f"[{YIELD_STRESS_RANGE[0]:g}, {YIELD_STRESS_RANGE[1]:g}] (the plasticine law's bounds)"
        )


def parse_conceal(spec: Any, *, kinds: tuple[str, ...] = tuple(CONCEAL_DEFAULTS)) -> list[Effect]:
    """Effects from ``None``/"" (none), a ``;``-separated string, or a list of specs.

    ``kinds`` are the effect kinds the calling scene source can realise (default: every library
    kind; a source that realises out-of-library fields lists them).
    Raises ValueError naming the bad kind or parameter; a kind may appear only once.
    """
    if spec is None:
        return []
    unknown = [k for k in kinds if k not in ALL_DEFAULTS]
    if unknown:
        raise ValueError(f"no concealed-effect defaults for kind(s) {unknown}")
    items = spec.split(";") if isinstance(spec, str) else [str(s) for s in spec]
    effects = [_parse_one(s, kinds) for s in items if s.strip()]
    kinds = [e.kind for e in effects]
    repeated = sorted({k for k in kinds if kinds.count(k) > 1})
    if repeated:
        raise ValueError(f"effect kind(s) {repeated} given more than once")
    return effects
