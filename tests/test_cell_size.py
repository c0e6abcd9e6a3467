"""``simulator.cell_size``: a resolution in metres that a run turns into the grid of its scene.

The recipe check keeps it (or lets an explicit grid win, with a note), refuses a value that is
no length or a simulator without a grid; the run replaces it by round(extent / cell_size)
before building the simulator, writes that grid into the run's recipe.yaml, and the stiffness
caps follow the derived grid."""

from __future__ import annotations

from dataclasses import dataclass

import pytest
import torch
from omegaconf import OmegaConf

from mosiv_framework.errors import ConfigError
from mosiv_framework.interfaces import Simulator
from mosiv_framework.pipeline import run_pipeline
from mosiv_framework.pipeline.run import build_simulator
from mosiv_framework.recipes import validate_recipe
from mosiv_framework.recipes.cell_size import grid_for, resolve_cell_size
from mosiv_framework.recipes.stiffness import SceneFacts, stiffness_findings
from mosiv_framework.registry import Component, Registry, hookimpl, manager
from mosiv_framework.types import Trajectory


@dataclass
class GridOptions:
    grid: int = 8
    substeps: int = 10


class GridRecorder(Simulator):
    """Particles moving at their initial velocities; remembers the grid it was built with."""

    built: list[int] = []

    def __init__(self, **options):
        self.options = GridOptions(**options)
        GridRecorder.built.append(self.options.grid)

    def rollout(self, particles, params, *, world, frames):
        t = torch.arange(frames + 1, dtype=torch.float32) / world.fps
        v0 = torch.stack([params.initial_velocity[int(k)] for k in particles.object_ids.tolist()])
        x = particles.positions[None] + t[:, None, None] * v0[None]
        return Trajectory(x, particles.object_ids, world.fps)


class GridPlugin:
    @hookimpl
    def mosiv_simulators(self, register):
        register(Component("simulator", "still-grid", factory=GridRecorder, options=GridOptions))
        register(Component("simulator", "no-grid", factory=GridRecorder))


@pytest.fixture
def registry(monkeypatch):
    reg = Registry().load_entry_points(disabled=["warp-mpm", "taichi-mpm", "gauss"])
    reg.add_plugin(GridPlugin(), name="grid-test")
    monkeypatch.setattr(manager, "_REGISTRY", reg)
    return reg


def _raw(tmp_path, simulator):
    return {
        "scene": {
            "path": str(tmp_path / "scene"),
            "generate": "if-missing",
            "source": {"name": "example", "n_frames": 4, "n_cameras": 2, "size": 24},
        },
        "reconstructor": {"name": "oracle", "max_points": 100},
        "lifter": {"name": "gt-points", "max_particles_per_object": 100},
        "simulator": simulator,
        "losses": {"chamfer": {"weight": 1.0, "max_points": 100}},
        "identify": {"velocity_iterations": 1, "param_iterations": 0, "horizon_start": 2},
        "evaluate": {"emd_samples": 32, "render_videos": False},
        "output": {"dir": str(tmp_path / "run")},
    }


def test_the_check_keeps_a_cell_size_and_refuses_what_is_no_length(tmp_path, registry):
    resolved, problems = validate_recipe(
        _raw(tmp_path, {"name": "still-grid", "cell_size": 0.0125}), registry
    )
    assert problems == [] and resolved["simulator"]["cell_size"] == 0.0125
    assert resolved["simulator"]["grid"] is None  # so that a second check keeps the cell size
    again, problems = validate_recipe(resolved, registry)
    assert problems == [] and again["simulator"]["cell_size"] == 0.0125
    assert again["simulator"]["grid"] is None
    for bad in (0, -0.01, "fine", True):
        _, problems = validate_recipe(
            _raw(tmp_path, {"name": "still-grid", "cell_size": bad}), registry
        )
        assert problems == [f"simulator.cell_size={bad!r}: must be a positive length in metres"]
    _, problems = validate_recipe(_raw(tmp_path, {"name": "no-grid", "cell_size": 0.01}), registry)
    assert len(problems) == 1 and "has no 'grid' option" in problems[0]


def test_an_explicit_grid_wins_with_a_note(tmp_path, registry, caplog):
    warnings: list[str] = []
    raw = _raw(tmp_path, {"name": "still-grid", "cell_size": 0.0125, "grid": 48})
    resolved, problems = validate_recipe(raw, registry, warnings=warnings)
    assert problems == [] and resolved["simulator"]["grid"] == 48
    assert "cell_size" not in resolved["simulator"]
    note = "simulator.grid=48 given beside simulator.cell_size=0.0125"
    assert any(note in w for w in warnings)
    assert note in caplog.text  # load_recipe keeps no warnings: a run shows it in its log


def test_resolving_sets_the_nearest_grid_and_drops_the_key():
    recipe = OmegaConf.create({"simulator": {"name": "still-grid", "grid": 8, "cell_size": 0.0125}})
    assert resolve_cell_size(recipe, 1.0798) == 86 == grid_for(1.0798, 0.0125)
    assert recipe.simulator.grid == 86 and "cell_size" not in recipe.simulator
    assert resolve_cell_size(recipe, 0.8) is None  # nothing left to resolve
    assert grid_for(0.8, 0.0125) == 64 and grid_for(0.01, 1.0) == 2


def test_a_simulator_is_not_built_from_an_unresolved_cell_size(registry):
    section = OmegaConf.create({"name": "still-grid", "cell_size": 0.0125})
    with pytest.raises(ConfigError, match="resolve_cell_size"):
        build_simulator(section)


def test_the_stiffness_caps_follow_the_derived_grid():
    facts = SceneFacts(fps=24.0, extent=1.08, families={1: "elastic"})
    identify = {"stiffness_cfl": 0.5}
    by_cell = stiffness_findings(
        {"simulator": {"grid": None, "substeps": 20, "cell_size": 0.0125}, "identify": identify},
        facts,
    )
    by_grid = stiffness_findings(
        {"simulator": {"grid": 86, "substeps": 20}, "identify": identify}, facts
    )
    assert by_cell == by_grid and by_cell != ([], [])


def test_a_run_builds_its_simulator_on_the_grid_of_its_scene(tmp_path, registry):
    from mosiv_framework.scene import read_scene

    resolved, problems = validate_recipe(
        _raw(tmp_path, {"name": "still-grid", "cell_size": 0.05, "substeps": 100}), registry
    )
    assert problems == []
    recipe = OmegaConf.create(resolved)
    GridRecorder.built.clear()
    torch.manual_seed(0)
    run_pipeline(recipe, run_dir=tmp_path / "run")
    extent = read_scene(tmp_path / "scene").world.extent
    expected = round(extent / 0.05)
    assert expected != 8 and set(GridRecorder.built) == {expected}
    written = OmegaConf.load(tmp_path / "run" / "recipe.yaml")
    assert written.simulator.grid == expected and "cell_size" not in written.simulator


def test_a_null_grid_beside_a_cell_size_leaves_the_choice_to_the_cell(tmp_path, registry):
    warnings: list[str] = []
    raw = _raw(tmp_path, {"name": "still-grid", "grid": None, "cell_size": 0.02})
    resolved, problems = validate_recipe(raw, registry, warnings=warnings)
    assert problems == [] and warnings == [] and resolved["simulator"]["cell_size"] == 0.02
