"""Interpolations in recipes: checked key by key, resolved once, never from the environment.

A recipe may refer to its own keys (``output.dir: runs/${scene.source.seed}``) and use the
resolvers that only read the recipe itself (``RECIPE_RESOLVERS``). Resolvers that can read the
process environment are refused (``ENVIRONMENT_RESOLVERS``): a run stores its resolved recipe
in ``recipe.yaml`` beside the results, so a token or password read from the environment would be
written to disk and shared with the run folder. ``oc.decode`` and ``oc.create`` are refused with
``oc.env`` because they evaluate text as a new interpolation, through which an escaped
``\\${oc.env:...}`` would still reach the environment. No shipped recipe or test relies on an
environment resolver; values that differ per machine are passed as ``key=value`` overrides,
which are visible on the command line that stored them.

Every problem names the key, the interpolation as written (never a resolved value) and what is
allowed; all are reported at once.
"""

from __future__ import annotations

import re
from collections.abc import Iterator
from typing import Any

from omegaconf import DictConfig, ListConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

#: resolvers that read only the recipe itself
RECIPE_RESOLVERS = ("oc.select", "oc.dict.keys", "oc.dict.values")
#: resolvers that read the process environment, directly or by evaluating text
ENVIRONMENT_RESOLVERS = ("oc.env", "oc.decode", "oc.create")
#: the name of every resolver call ``${name:...}`` in a string, nested ones included (an
#: escaped ``\${`` matches too, which only errs on the side of refusing)
_RESOLVER_CALL = re.compile(r"\$\{\s*([A-Za-z_][\w.\-]*)\s*:")


def _leaves(value: Any, prefix: str = "") -> Iterator[tuple[str, Any]]:
    """(dotted key, value) of every scalar in plain nested containers."""
    if isinstance(value, dict):
        for key, item in value.items():
            yield from _leaves(item, f"{prefix}{key}" if not prefix else f"{prefix}.{key}")
    elif isinstance(value, list):
        for i, item in enumerate(value):
            yield from _leaves(item, f"{prefix}[{i}]")
    else:
        yield prefix, value


def _first_line(exc: BaseException) -> str:
    lines = str(exc).strip().splitlines()
    return lines[0] if lines else type(exc).__name__


def syntax_problems(raw: Any) -> list[str]:
    """Strings of plain nested containers that are not valid interpolations, one per key."""
    from omegaconf import grammar_parser

    problems = []
    for key, value in _leaves(raw):
        if isinstance(value, str) and "${" in value:
            try:
                grammar_parser.parse(value)
            except OmegaConfBaseException as exc:
                reason = _first_line(exc)
                problems.append(f"{key}={value!r}: not a valid interpolation ({reason})")
    return problems


def interpolation_problems(cfg: DictConfig | ListConfig) -> list[str]:
    """Syntax errors and refused resolvers in ``cfg``'s unresolved strings, one per key."""
    raw = OmegaConf.to_container(cfg, resolve=False)
    problems = syntax_problems(raw)
    if problems:
        return problems
    for key, value in _leaves(raw):
        if not isinstance(value, str) or "${" not in value:
            continue
        for name in _RESOLVER_CALL.findall(value):
            if name in ENVIRONMENT_RESOLVERS:
                problems.append(
                    f"{key}={value!r}: the {name!r} resolver is off in recipes: it can read "
                    "environment variables, and a run writes its resolved recipe to "
                    "recipe.yaml, so secrets would be stored with the results; pass the value "
                    "as a key=value override instead"
                )
            elif name not in RECIPE_RESOLVERS:
                problems.append(
                    f"{key}={value!r}: unknown resolver {name!r}; a recipe may refer to its "
                    f"own keys (${{section.key}}) and use {', '.join(RECIPE_RESOLVERS)}"
                )
    return problems


def _resolution_problems(node: DictConfig | ListConfig, raw: Any, prefix: str) -> list[str]:
    """Access every value of ``node`` (which resolves it) and name each one that fails."""
    problems = []
    keys = range(len(node)) if isinstance(node, ListConfig) else list(node.keys())
    for key in keys:
        where = f"{prefix}[{key}]" if isinstance(node, ListConfig) else f"{prefix}{key}"
        written = raw[key] if isinstance(raw, (dict, list)) else None
        try:
            value = node[key]
        except OmegaConfBaseException as exc:
            shown = f"={written!r}" if isinstance(written, str) else ""
            problems.append(f"{where}{shown}: cannot be resolved ({_first_line(exc)})")
            continue
        if isinstance(value, (DictConfig, ListConfig)):
            inner = written if isinstance(written, (dict, list)) else None
            dot = "" if isinstance(value, ListConfig) else "."
            problems.extend(_resolution_problems(value, inner, f"{where}{dot}"))
    return problems


def resolve_recipe(cfg: DictConfig) -> tuple[dict[str, Any], list[str]]:
    """``cfg`` with every interpolation resolved, as plain containers, and the problems found.

    Refused resolvers are never called (so nothing is read from the environment); an
    unresolvable key, an unknown resolver, a syntax error or a missing mandatory value (``???``)
    is reported with its key. On any problem the returned mapping is empty.
    """
    problems = interpolation_problems(cfg)
    if problems:
        return {}, problems
    raw = OmegaConf.to_container(cfg, resolve=False)
    problems = _resolution_problems(cfg, raw, "")
    if problems:
        return {}, problems
    resolved = OmegaConf.to_container(cfg, resolve=True)
    # an escaped "\${...}" resolves to the text "${...}", which would be read as an
    # interpolation again wherever the resolved recipe is loaded (a run's recipe.yaml)
    for key, value in _leaves(resolved):
        if isinstance(value, str) and "${" in value:
            problems.append(
                f"{key}={value!r}: a value may not contain a literal '${{' (it would be read as "
                "an interpolation when the run's recipe.yaml is loaded again)"
            )
    return (resolved if not problems else {}), problems  # type: ignore[return-value]
