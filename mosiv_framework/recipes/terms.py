"""The recipe's ``physics_terms`` section: optional effects switched on in every rollout.

Each key names a registered PhysicsTerm; its value maps the term's parameter names to initial
values (SI units, within the term's ParamSpec bounds) and may set ``identify: true`` to make the
term's parameters part of the identified parameter vector (of a sparse term, such as
``expression``, only the parameters given exist)::

    physics_terms:
      wind: {acceleration: [1.0, 0, 0], identify: true}
      linear_drag: {coefficient: 0.5, identify: false}

A parameter whose ParamSpec description begins with ``[3]`` is a 3-vector (the convention of
``mosiv_framework.terms``); every other parameter is a scalar. Parameters left out start at the
spec's default (a vector at the default on every axis), except in a sparse term.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import torch

from mosiv_framework.laws.base import ParamSpec

#: the key beside a term's parameters that frees them for identification
IDENTIFY_KEY = "identify"


def param_size(spec: ParamSpec) -> int:
    """How many numbers a term parameter holds: 3 for ``[3]`` vectors, else 1."""
    return 3 if spec.description.strip().startswith("[3]") else 1


def _shape_text(spec: ParamSpec) -> str:
    size = param_size(spec)
    return "a list of 3 numbers" if size == 3 else "a number"


def _check_value(where: str, spec: ParamSpec, value: Any, problems: list[str]) -> Any:
    """One parameter's value: right shape, finite, inside the spec's bounds."""
    size = param_size(spec)
    items = value if isinstance(value, (list, tuple)) else [value]
    numeric = all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in items)
    if not numeric or len(items) != size or (size == 1 and isinstance(value, (list, tuple))):
        problems.append(
            f"{where}={value!r}: must be {_shape_text(spec)} in {spec.unit} "
            f"({spec.description or spec.name})"
        )
        return value
    for x in items:
        try:
            spec.check(float(x), where=where)
        except ValueError as exc:
            problems.append(f"{where}: {exc}")
            return value
    floats = [float(x) for x in items]
    return floats if size == 3 else floats[0]


def check_physics_terms(value: Any, registry, problems: list[str]) -> dict[str, dict[str, Any]]:
    """Validate ``physics_terms`` against the registry's terms and their ParamSpecs.

    Returns the resolved section (every parameter present, ``identify`` a bool); appends one
    problem per mistake, each naming the key and what would be valid.
    """
    if value is None:
        return {}
    valid_terms = registry.names("physics_term")
    if not isinstance(value, Mapping):
        problems.append(
            f"physics_terms must map physics-term names to their parameters, got {value!r}; "
            f"registered terms: {', '.join(valid_terms) or 'none installed'}"
        )
        return {}
    resolved: dict[str, dict[str, Any]] = {}
    for name, params in value.items():
        where = f"physics_terms.{name}"
        if name not in valid_terms:
            problems.append(
                f"{where}: no physics term {name!r} is registered; registered terms: "
                f"{', '.join(valid_terms) or 'none installed'}"
            )
            continue
        term = registry.create("physics_term", name, {})
        specs = {spec.name: spec for spec in term.params}
        params = {} if params is None else params
        if not isinstance(params, Mapping):
            problems.append(
                f"{where} must be a mapping of its parameters ({', '.join(specs)}) and "
                f"'{IDENTIFY_KEY}', got {params!r}"
            )
            continue
        entry: dict[str, Any] = {}
        for key, item in params.items():
            if key == IDENTIFY_KEY:
                if not isinstance(item, bool):
                    problems.append(f"{where}.{IDENTIFY_KEY}={item!r}: must be true or false")
                continue
            if key not in specs:
                problems.append(
                    f"unknown key {where}.{key}; valid keys of {name}: "
                    f"{term.parameter_names_text()}, {IDENTIFY_KEY}"
                )
                continue
            entry[key] = _check_value(f"{where}.{key}", specs[key], item, problems)
        for spec in term.params:  # parameters left out start at the spec's default
            if spec.name not in entry and not term.sparse:  # a sparse term has only those given
                entry[spec.name] = (
                    [spec.default] * 3 if param_size(spec) == 3 else float(spec.default)
                )
        entry[IDENTIFY_KEY] = bool(params.get(IDENTIFY_KEY, False))
        resolved[name] = entry
    return resolved


def term_tensors(section: Mapping[str, Mapping[str, Any]]) -> dict[str, dict[str, torch.Tensor]]:
    """A resolved ``physics_terms`` section as SimulationParams.terms (float32 tensors:
    0-d for scalars, [3] for vectors); the ``identify`` flags are left out."""
    return {
        name: {
            key: torch.tensor(value, dtype=torch.float32)
            for key, value in params.items()
            if key != IDENTIFY_KEY
        }
        for name, params in section.items()
    }


def identified_terms(section: Mapping[str, Mapping[str, Any]]) -> tuple[str, ...]:
    """Names of the terms whose parameters the recipe identifies."""
    return tuple(name for name, params in section.items() if params.get(IDENTIFY_KEY, False))
