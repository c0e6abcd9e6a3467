"""The second simulator resolution of the grid-stability check (``grid_stability``).

The check refits the null model and an effect on a second grid, ``diagnose.grid_factor`` times
the run's ``simulator.grid``, and compares. The second grid must be one the simulator can run
the fitted materials on:

- its substeps scale with the grid, so that a body moving at a given speed crosses the same
  fraction of a cell per substep, and are then raised until the recipe validator's stiffness
  check (``recipes.stiffness``) finds no law's starting stiffness above its cap and every
  fitted stiffness (E, bulk and shear moduli) of the models compared stays below the cap
  (``pipeline.params.stiffness_ceilings``) at the recipe's ``identify.stiffness_cfl``;
- its cells must not be smaller than the particle spacing (``MIN_CELL_PARTICLES``): with fewer
  particles than cells across a body, MPM bodies come apart, and a real effect would fail the
  check for the discretisation's sake;
- it must have at least ``MIN_GRID`` cells and differ from the first grid.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

from mosiv_framework.diagnose.locate import particle_spacing
from mosiv_framework.errors import ConfigError
from mosiv_framework.recipes.schema import IdentifySection
from mosiv_framework.types import ParticleSet, SimulationParams, World

#: the fewest cells along the domain's longest side a simulator grid may have (MPMOptions)
MIN_GRID = 8
#: the smallest cell side of the second grid, in particle spacings
MIN_CELL_PARTICLES = 1.0
#: how often the substeps are raised before the search gives up (each raise is at least 1)
MAX_RAISES = 64


@dataclass(frozen=True)
class Resolution:
    """A simulator resolution: cells along the domain's longest side, substeps per frame."""

    grid: int
    substeps: int


def simulator_resolution(ctx) -> Resolution:
    """The run's own resolution (its simulator's ``grid`` and ``substeps`` options).

    Raises ConfigError for a simulator without them: it has no grid to change."""
    options = getattr(ctx.simulator, "options", None)
    grid, substeps = getattr(options, "grid", None), getattr(options, "substeps", None)
    if not (
        isinstance(grid, int) and isinstance(substeps, int) and dataclasses.is_dataclass(options)
    ):
        raise ConfigError(
            f"diagnose.grid_check: simulator {ctx.simulator_name!r} has no grid and substeps "
            "options to change; set diagnose.grid_check: false"
        )
    return Resolution(grid, substeps)


def second_grid(first: Resolution, factor: float, world: World, particles: ParticleSet) -> int:
    """The second grid's cells: ``factor`` times the first grid, rounded.

    Raises ConfigError naming ``diagnose.grid_factor`` and the factors that would be valid
    when that grid equals the first, has fewer than ``MIN_GRID`` cells, or has cells smaller
    than ``MIN_CELL_PARTICLES`` particle spacings."""
    grid = round(first.grid * factor)
    spacing = particle_spacing(particles.volumes)
    # a relative margin: the spacing is read from float32 volumes
    finest = math.floor(world.extent / (MIN_CELL_PARTICLES * spacing) * (1 + 1e-6))
    valid = (
        f"valid for simulator.grid={first.grid}: a factor giving {MIN_GRID} to {finest} cells "
        f"other than {first.grid}, i.e. {MIN_GRID / first.grid:.2f} to "
        f"{finest / first.grid:.2f} (or diagnose.grid_check: false)"
    )
    if grid == first.grid:
        problem = f"gives the run's own grid of {grid} cells"
    elif grid < MIN_GRID:
        problem = f"gives {grid} cells, fewer than the simulator's {MIN_GRID}"
    elif grid > finest:
        problem = (
            f"gives {grid} cells of {1000 * world.extent / grid:.1f} mm, finer than the "
            f"particles ({1000 * spacing:.1f} mm apart): MPM bodies would come apart"
        )
    else:
        return grid
    raise ConfigError(f"diagnose.grid_factor={factor:g} {problem}; {valid}")


def second_resolution(
    first: Resolution,
    factor: float,
    *,
    world: World,
    particles: ParticleSet,
    fitted: list[SimulationParams],
    cfl: float,
) -> Resolution:
    """The second grid (``second_grid``) with a stable count of substeps.

    Args:
        first: the run's resolution.
        factor: the second grid over the first.
        world: the scene (frame rate and domain size set the cell and the step).
        particles: the run's particles (their spacing bounds how fine the grid may be).
        fitted: the models to be simulated there (their materials' stiffnesses).
        cfl: cells a P-wave may cross per substep (the recipe's ``identify.stiffness_cfl``;
            0 there means no cap in identification, and the schema's default is used).
    Returns:
        The resolution: substeps at least the first's scaled with the grid, raised until
        ``stiffness_ratio`` is at most 1 and the stiffness check passes.
    """
    from mosiv_framework.recipes.stiffness import SceneFacts, stiffness_findings

    grid = second_grid(first, factor, world, particles)
    cfl = cfl if cfl > 0 else IdentifySection.stiffness_cfl
    families = {k: p.family for params in fitted for k, p in params.objects.items()}
    facts = SceneFacts(fps=float(world.fps), extent=float(world.extent), families=families)
    substeps = max(1, math.ceil(first.substeps * grid / first.grid - 1e-9))
    for _ in range(MAX_RAISES):
        ratio = stiffness_ratio(fitted, grid, substeps, world, cfl)
        recipe = {
            "simulator": {"grid": grid, "substeps": substeps},
            "identify": {"stiffness_cfl": cfl},
        }
        errors, _ = stiffness_findings(recipe, facts)
        if ratio <= 1.0 and not errors:
            return Resolution(grid, substeps)
        substeps = max(substeps + 1, math.ceil(substeps * math.sqrt(max(ratio, 1.0))))
    raise ConfigError(
        f"diagnose.grid_factor={factor:g}: no substep count up to {substeps} keeps the fitted "
        f"materials stable on a grid of {grid} cells; choose a factor nearer 1"
    )


def stiffness_ratio(
    fitted: list[SimulationParams], grid: int, substeps: int, world: World, cfl: float
) -> float:
    """The largest fitted stiffness over its cap at this resolution (<= 1: every material
    stays below ``cfl`` cells per substep), over every object of every model in ``fitted``."""
    from mosiv_framework.pipeline.params import stiffness_ceilings

    dx, dt = world.extent / grid, 1.0 / (world.fps * substeps)
    worst = 0.0
    for params in fitted:
        families = {k: p.family for k, p in params.objects.items()}
        values = {k: {n: float(v) for n, v in p.values.items()} for k, p in params.objects.items()}
        caps = stiffness_ceilings(families, values, dx=dx, dt=dt, cfl=cfl)
        for k, limits in caps.items():
            for name, cap in limits.items():
                if name in values[k] and cap > 0:
                    worst = max(worst, values[k][name] / cap)
    return worst


def context_at(ctx, resolution: Resolution):
    """The run's context (``context.RunContext``) with its simulator at ``resolution``:
    the same options otherwise (device, contact), the same particles and targets, a rollout
    cache of its own."""
    from mosiv_framework.registry import get_registry

    options = dataclasses.replace(
        ctx.simulator.options, grid=resolution.grid, substeps=resolution.substeps
    )
    simulator = get_registry().create("simulator", ctx.simulator_name, dataclasses.asdict(options))
    return dataclasses.replace(ctx, simulator=simulator, _rollout_cache={})
