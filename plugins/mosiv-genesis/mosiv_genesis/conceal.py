"""Concealed physics for Genesis scenes: effects recorded in gt/effects.json, not in scene.json.

Same spec syntax and default strengths as the ``synth`` source (``KIND[:param=value,...]``,
several separated by ``;``; a vector continues over the following numbers:
``wind:acceleration=1.5,0,0``), realised with Genesis' own means: drag and wind as its
acceleration fields (``gs.force_fields.Drag`` / ``Constant``), gravity through ``SimOptions``.
Ground friction is not offered: Genesis' MPM-ground contact has no coefficient to change.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

# kind -> {param: default}; the values (and the reasons for them) are those of mosiv-synth:
# linear drag 1.5 1/s, quadratic drag 1.0 1/m, wind 1.5 m/s^2 sideways, gravity -12 m/s^2
DEFAULTS: dict[str, dict[str, float | tuple[float, float, float]]] = {
    "linear_drag": {"coefficient": 1.5},
    "quadratic_drag": {"coefficient": 1.0},
    "wind": {"acceleration": (1.5, 0.0, 0.0)},
    "gravity": {"acceleration": (0.0, 0.0, -12.0)},
}


@dataclass(frozen=True)
class Effect:
    """One concealed effect: kind and parameter values (floats or 3-tuples)."""

    kind: str
    params: dict[str, Any]

    def to_json(self) -> dict[str, Any]:
        return {
            "kind": self.kind,
            "params": {
                k: list(v) if isinstance(v, tuple) else float(v) for k, v in self.params.items()
            },
        }

    def spec(self) -> str:
        """Canonical ``KIND:param=value,...`` text (parses back to the same effect)."""
        parts = [
            f"{k}={','.join(repr(float(x)) for x in v) if isinstance(v, tuple) else repr(float(v))}"
            for k, v in self.params.items()
        ]
        return f"{self.kind}:{','.join(parts)}"


def _parse_one(text: str) -> Effect:
    kind, _, rest = text.strip().partition(":")
    kind = kind.strip()
    if kind not in DEFAULTS:
        raise ValueError(f"unknown effect kind {kind!r}; valid kinds: {', '.join(DEFAULTS)}")
    values: dict[str, list[float]] = {}
    current = None
    for token in (t.strip() for t in rest.split(",") if t.strip()):
        if "=" in token:
            current, _, token = (s.strip() for s in token.partition("="))
            if current not in DEFAULTS[kind]:
                raise ValueError(
                    f"{kind}: unknown parameter {current!r}; valid: {', '.join(DEFAULTS[kind])}"
                )
            values[current] = []
        elif current is None:
            raise ValueError(f"{kind}: {token!r} is not of the form param=value")
        try:
            x = float(token)
        except ValueError:
            raise ValueError(f"{kind}.{current}: {token!r} is not a number") from None
        if not math.isfinite(x):
            raise ValueError(f"{kind}.{current}: {token!r} must be finite")
        values[current].append(x)
    params: dict[str, Any] = {}
    for name, default in DEFAULTS[kind].items():
        given = values.get(name)
        size = 3 if isinstance(default, tuple) else 1
        if given is not None and len(given) != size:
            raise ValueError(f"{kind}.{name}: takes {size} number(s), got {given}")
        if given is None:
            params[name] = default
        else:
            params[name] = tuple(given) if size == 3 else given[0]
    if params.get("coefficient", 0.0) < 0:
        raise ValueError(f"{kind}.coefficient={params['coefficient']} must be >= 0")
    return Effect(kind, params)


def parse_conceal(spec: Any) -> list[Effect]:
    """Effects from None/"" (none), a ``;``-separated string or a list; each kind at most once."""
    if spec is None:
        return []
    items = spec.split(";") if isinstance(spec, str) else [str(s) for s in spec]
    effects = [_parse_one(s) for s in items if s.strip()]
    kinds = [e.kind for e in effects]
    repeated = sorted({k for k in kinds if kinds.count(k) > 1})
    if repeated:
        raise ValueError(f"effect kind(s) {repeated} given more than once")
    return effects
