"""Cross-field check: the stiffness a recipe's simulator settings let identification reach.

Identification caps every stiffness (E, bulk and shear moduli) so that the P-wave speed stays
below ``identify.stiffness_cfl`` grid cells per substep (``stiffness_ceilings`` in
``mosiv_framework.pipeline.params``, the same function the pipeline uses). The cap grows with
the square of ``simulator.substeps`` and falls with the square of ``simulator.grid`` and of the
scene's frame rate, so a few substeps can quietly put the truth out of reach: 8 substeps on the
quickstart's 32-cell grid cap E at 4,800 Pa where the scene's objects have 5e4 Pa.

A cap below the value identification starts from (the law's default) is an error: the start
itself is clipped and the fit can never reach the usual materials. A cap below the law's upper
bound only is a warning saying where the recipe caps the parameter.

The scene's frame rate, domain and object families come from ``scene.json`` when the scene
exists, else from the scene source's optional ``declared()`` method (returning the World and
the families it will write, families None when drawn at random); without either the check
waits for the pipeline, which calls ``check_stiffness`` with the scene it read.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from mosiv_framework.errors import ConfigError
from mosiv_framework.laws import LAWS, get_law
from mosiv_framework.recipes.cell_size import KEY as CELL_SIZE
from mosiv_framework.recipes.cell_size import grid_for
from mosiv_framework.recipes.schema import IdentifySection
from mosiv_framework.scene import MATERIAL_FAMILIES


@dataclass(frozen=True)
class SceneFacts:
    """What the stiffness cap depends on besides the recipe: frame rate (1/s), longest side of
    the domain (m) and object id -> material family (None: not known before generating)."""

    fps: float
    extent: float
    families: dict[int, str] | None


def scene_facts(recipe: Mapping[str, Any], registry) -> SceneFacts | None:
    """The facts of the recipe's scene, read without generating it; None when unknown."""
    scene = recipe.get("scene") or {}
    scene_json = Path(str(scene.get("path") or "")) / "scene.json"
    if scene_json.is_file():
        try:
            return _facts_of(json.loads(scene_json.read_text(encoding="utf-8")))
        except (OSError, ValueError, KeyError, TypeError, ArithmeticError, RecursionError):
            return None  # reading the scene names what is wrong with it
    source = scene.get("source")
    if not isinstance(source, Mapping) or "name" not in source:
        return None
    options = {k: v for k, v in source.items() if k != "name"}
    declared = getattr(registry.create("scene_source", source["name"], options), "declared", None)
    if declared is None:
        return None
    world, families = declared()
    return SceneFacts(
        fps=float(world.fps),
        extent=float(world.extent),
        families=dict(enumerate(families, start=1)) if families else None,
    )


def _facts_of(data: dict) -> SceneFacts | None:
    """The facts scene.json declares; None where they are not usable numbers or families (the
    scene's validation, exit 3, names them: they are not the recipe's fault)."""
    lower, upper = data["domain"]["lower"], data["domain"]["upper"]
    numbers = [data["fps"], *lower, *upper]
    if not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in numbers):
        return None
    fps = float(data["fps"])  # OverflowError for an integer beyond float range
    extent = max(float(u) - float(lo) for lo, u in zip(lower, upper))
    families = {int(o["id"]): str(o["material"]) for o in data["objects"]}
    usable = all(f in LAWS for f in families.values()) and families
    if not (usable and math.isfinite(fps) and fps > 0 and math.isfinite(extent) and extent > 0):
        return None
    return SceneFacts(fps=fps, extent=extent, families=families)


def _is_count(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and value > 0


def stiffness_findings(recipe: Mapping[str, Any], facts: SceneFacts) -> tuple[list[str], list[str]]:
    """(errors, warnings) about the stiffness caps of ``recipe`` in the scene of ``facts``.

    Args:
        recipe: the resolved recipe (plain mapping; ``simulator`` and ``identify`` used).
        facts: the scene's frame rate, domain size and object families.
    Returns:
        errors: caps below a law's starting value (known families only);
        warnings: caps below a law's upper bound, and below the start when the families are
        not known yet (the source draws them at random).
    """
    from mosiv_framework.pipeline.params import stiffness_ceilings

    simulator, identify = recipe.get("simulator") or {}, recipe.get("identify") or {}
    grid, substeps = simulator.get("grid"), simulator.get("substeps")
    if grid is None and simulator.get(CELL_SIZE) is not None:  # the grid a run derives here
        grid = grid_for(facts.extent, float(simulator[CELL_SIZE]))
    cfl = identify.get("stiffness_cfl", IdentifySection.stiffness_cfl)
    if not (_is_count(grid) and _is_count(substeps) and cfl > 0 and facts.fps > 0):
        return [], []  # no grid, no cap: nothing the recipe limits
    known = facts.families is not None
    # a source draws scene materials, never a law variant that only a recipe names
    families = facts.families if known else dict(enumerate(sorted(MATERIAL_FAMILIES), start=1))
    dx, dt = facts.extent / grid, 1.0 / (facts.fps * substeps)
    ceilings = stiffness_ceilings(families, {}, dx=dx, dt=dt, cfl=cfl)
    # objects whose caps, starts and bounds coincide share one message
    groups: dict[tuple, list[str]] = {}
    for k, family in families.items():
        law = get_law(family)
        for name, cap in ceilings[k].items():
            spec = law.param(name)
            if cap < spec.upper:
                key = (name, cap, spec.default, spec.upper, spec.unit)
                groups.setdefault(key, []).append(f"{k} ({family})" if known else family)
    because = (
        f"(the cap follows from simulator.grid={grid}, identify.stiffness_cfl={cfl:g} and the "
        f"scene's {facts.fps:g} fps and {facts.extent:.2f} m domain)"
    )
    errors, warnings = [], []
    for (name, cap, start, upper, unit), who in groups.items():
        objects = f"object{'s' if len(who) > 1 else ''} {', '.join(who)}"
        objects = objects if known else f"{' or '.join(who)} objects (drawn at random)"
        head = f"simulator.substeps={substeps} caps {name} of {objects} at {cap:,.0f} {unit}"
        if cap < start:
            need = math.ceil(substeps * math.sqrt(start / cap))
            text = (
                f"{head}, below the {start:,.0f} {unit} identification starts from, so the "
                f"usual materials are out of reach; use simulator.substeps >= {need} {because}"
            )
            (errors if known else warnings).append(text)
        else:
            need = math.ceil(substeps * math.sqrt(upper / cap))
            warnings.append(
                f"{head} (the law allows up to {upper:,.0f} {unit}): a stiffer material would "
                f"be identified at the cap; simulator.substeps >= {need} lifts it to the law's "
                f"bound {because}"
            )
    return errors, warnings


def check_stiffness(recipe: Any, *, world, families: Mapping[int, str]) -> list[str]:
    """The pipeline's check once the scene is read: raise ConfigError for a cap below a
    starting value, return the warnings (log them and store them with the results).

    Args:
        recipe: the loaded recipe (DictConfig or plain mapping).
        world: the scene's World (its ``fps`` and ``extent`` are used).
        families: object id -> material family of the objects identified.
    """
    if not isinstance(recipe, dict):  # a DictConfig: its values as plain containers
        from omegaconf import OmegaConf

        recipe = OmegaConf.to_container(OmegaConf.create(recipe), resolve=True)
    facts = SceneFacts(fps=float(world.fps), extent=float(world.extent), families=dict(families))
    errors, warnings = stiffness_findings(recipe, facts)
    if errors:
        raise ConfigError(errors)
    return warnings
