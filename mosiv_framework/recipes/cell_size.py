"""A simulator's resolution in metres: the recipe key ``simulator.cell_size``.

``simulator.grid`` counts cells along the largest side of the scene's domain, so one recipe
simulates a scene with a larger domain at coarser cells: another discretisation of the same
physics, whose best-fitting parameters differ. A recording's domain comes from its visual hull
(``mosiv data import``), so it is rarely the box a synthetic scene had: on the paper-size
capture round trip the imported domain was 1.08 m against the scene's 0.8 m, and the true
parameters rolled out from the scene's own particles at grid 64 there missed the future by
28,000 mm^2 where grid 86 (the scene's cell) reproduced it (docs/RESULTS.md, "A recording
through a rig and back").

``simulator.cell_size`` (m) states the resolution itself: a run turns it into
``grid = round(extent / cell_size)`` for its scene before anything is simulated (and writes
that grid into the run's recipe.yaml), so the cell is the same whatever the domain. A
``simulator.grid`` given beside it wins (a command-line override of a recipe that sets
``cell_size``), with a note; ``simulator.grid=null`` beside a cell size leaves the choice to
the cell size (a run's recipe.yaml, which holds the grid, re-resolved for another scene). Only
simulators with a ``grid`` option take it.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping
from typing import Any

from omegaconf import DictConfig, open_dict

log = logging.getLogger("mosiv")

KEY = "cell_size"


def grid_for(extent: float, cell_size: float) -> int:
    """The grid (cells along the domain's largest side, ``extent`` m) nearest a cell of
    ``cell_size`` m; at least 2."""
    return max(2, round(extent / cell_size))


def take_cell_size(
    where: str, options: dict[str, Any], has_grid_option: bool, problems: list[str], notes: list
) -> float | None:
    """Remove ``cell_size`` from a simulator section's raw ``options`` and check it.

    Returns the cell size (m) the run resolves into a grid, or None: none given, given with an
    explicit ``grid`` (which wins; a note says so, in ``notes`` and the log) or invalid (a
    problem says why). The checked section keeps the cell size with ``grid: None``, so that
    checking it again keeps it too."""
    if KEY not in options:
        return None
    value = options.pop(KEY)
    if value is None:
        return None
    if not has_grid_option:
        problems.append(
            f"{where}.{KEY}={value!r}: this simulator has no 'grid' option to set from it; "
            f"give its own resolution options instead"
        )
        return None
    number = value if isinstance(value, (int, float)) and not isinstance(value, bool) else None
    if number is None or not math.isfinite(number) or number <= 0:
        problems.append(f"{where}.{KEY}={value!r}: must be a positive length in metres")
        return None
    if "grid" in options and options["grid"] is None:  # grid=null: the cell size decides
        del options["grid"]
    if "grid" in options:
        note = (
            f"{where}.grid={options['grid']!r} given beside {where}.{KEY}={value!r}: the grid "
            f"is used (set {where}.{KEY}=null to silence this)"
        )
        notes.append(note)
        log.warning("%s", note)  # load_recipe keeps no warnings: `mosiv run` shows this one
        return None
    return float(number)


def resolve_cell_size(recipe: DictConfig, extent: float) -> int | None:
    """Replace ``recipe.simulator.cell_size`` by the grid it gives in a domain whose largest
    side is ``extent`` m; returns that grid (None when the recipe gives no cell size)."""
    simulator = recipe.simulator
    cell = simulator.get(KEY) if isinstance(simulator, (DictConfig, Mapping)) else None
    if cell is None:
        return None
    grid = grid_for(extent, float(cell))
    with open_dict(simulator):
        simulator.grid = grid
        del simulator[KEY]
    log.info(
        "simulator.cell_size=%g m in the scene's %.3g m domain: simulator.grid=%d "
        "(cells of %.4g m)",
        float(cell),
        extent,
        grid,
        extent / grid,
    )
    return grid
