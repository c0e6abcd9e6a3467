"""Rules between recipe sections, checked once every section is valid on its own.

Each rule catches a setting that would otherwise be accepted and then fail late (after
reconstruction and lifting) or quietly change the result: a loss objective with nothing in it,
a re-synchronisation period longer than the phase it re-synchronises, a contact choice
(``identify.contact=auto``) for a simulator without contact modes, and simulator settings whose
stability cap puts the materials out of reach (``mosiv_framework.recipes.stiffness``).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from mosiv_framework.errors import ConfigError
from mosiv_framework.recipes.stiffness import scene_facts, stiffness_findings
from mosiv_framework.simulation import CONTACT_MODES


def cross_section_findings(recipe: Mapping[str, Any], registry) -> tuple[list[str], list[str]]:
    """(problems, warnings) of a recipe whose sections each validated.

    Args:
        recipe: the resolved recipe (plain mapping, defaults filled in).
        registry: the component registry (to ask a scene source what it will declare).
    """
    problems: list[str] = []
    warnings: list[str] = []
    losses = recipe.get("losses") or {}
    weights = {name: float((opts or {}).get("weight", 1.0)) for name, opts in losses.items()}
    if not any(w > 0 for w in weights.values()):
        shown = ", ".join(f"losses.{n}.weight={w:g}" for n, w in weights.items()) or "losses={}"
        problems.append(
            f"{shown}: identification would have nothing to minimise; give at least one loss "
            "a weight > 0 (e.g. losses.chamfer.weight=1)"
        )
    identify = recipe.get("identify") or {}
    every, iterations = identify.get("resync_every", 0), identify.get("param_iterations", 0)
    if identify.get("method") == "gradient" and 0 < iterations <= every:
        warnings.append(
            f"identify.resync_every={every} is not below identify.param_iterations="
            f"{iterations}: the velocities are never re-synchronised (0 switches it off)"
        )
    problems.extend(contact_problems(recipe))
    try:
        facts = scene_facts(recipe, registry)
    except ConfigError as exc:
        problems.extend(f"scene: {p}" for p in exc.problems)
        return problems, warnings
    if facts is not None:
        errors, caps = stiffness_findings(recipe, facts)
        problems.extend(errors)
        warnings.extend(caps)
    return problems, warnings


def contact_problems(recipe: Mapping[str, Any]) -> list[str]:
    """identify.contact=auto chooses the simulator's ``contact`` option between the modes of
    ``CONTACT_MODES``: a simulator without that option has nothing to choose."""
    identify = recipe.get("identify") or {}
    simulator = recipe.get("simulator") or {}
    if identify.get("contact") != "auto" or simulator.get("contact") in CONTACT_MODES:
        return []
    return [
        f"identify.contact='auto' chooses simulator.contact among {list(CONTACT_MODES)}, but "
        f"simulator {simulator.get('name')!r} has no such contact option; use "
        "identify.contact=fixed, or a simulator with one (warp-mpm, taichi-mpm)"
    ]
