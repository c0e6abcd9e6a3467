"""The coordinate sweep after the global stage (``identify.global_polish``): a parameter left
on a plateau of the loss, where its gradient is exactly zero, is moved off it; a start the
sweep cannot beat is kept; every rollout is recorded."""

from __future__ import annotations

import math

import pytest
import torch

from mosiv_framework.interfaces import Simulator
from mosiv_framework.losses import WeightedSum
from mosiv_framework.pipeline.global_search import POLISH, coordinate_polish
from mosiv_framework.pipeline.params import ParameterVector
from mosiv_framework.pipeline.phases import Fit
from mosiv_framework.pipeline.run import stage_keys
from mosiv_framework.registry import get_registry
from mosiv_framework.types import ParticleSet, Trajectory, World

FPS = 24.0
YIELD_REACHED = 1e3  # the largest stress the toy body reaches: a yield above it never acts
TRUE_E, TRUE_YIELD = 1e4, 1e2


class YieldPlateau(Simulator):
    """One point drifting in x at a speed set by log10(E / 1e4) and in y by how far the yield
    stress lies below the largest stress reached (zero above it: the plateau a body that
    never yields puts in the loss). At the truth (E = 1e4, yield 1e2 Pa) it stays put."""

    def rollout(self, particles, params, *, world, frames):
        values = params.objects[1].values
        e, y = values["E"], values["yield_stress"]
        flow = torch.clamp(math.log10(YIELD_REACHED) - torch.log10(y), min=0.0)
        speed = torch.stack(
            [
                torch.log10(e / TRUE_E),
                flow - (math.log10(YIELD_REACHED) - math.log10(TRUE_YIELD)),
                torch.zeros(()),
            ]
        )
        t = torch.arange(frames + 1, dtype=torch.float32) / world.fps
        x = particles.positions[None] + t[:, None, None] * speed
        return Trajectory(x, particles.object_ids, world.fps)


def _toy(e: float, yield_stress: float):
    world = World((0, 0, 0), (1, 1, 1), gravity=(0, 0, 0), ground_height=None, fps=FPS)
    particles = ParticleSet(
        torch.tensor([[0.5, 0.5, 0.5]]),
        torch.ones(1),
        torch.ones(1, dtype=torch.long),
        {1: "plasticine"},
    )
    targets = {1: particles.positions[None].repeat(6, 1, 1)}  # at rest: the truth
    objective = WeightedSum({"chamfer": get_registry().create("loss", "chamfer", {})})
    vector = ParameterVector.create(
        {1: "plasticine"},
        {1: torch.zeros(3)},
        values={1: {"E": e, "yield_stress": yield_stress}},
        identify=("E", "yield_stress"),
        ground_friction=None,
    )
    return Fit(YieldPlateau(), particles, world, targets, objective), vector


def _values(vector: ParameterVector) -> dict[str, float]:
    return {k: float(v.detach()) for k, v in vector.physical().objects[1].values.items()}


def test_a_yield_stress_on_the_plateau_has_no_gradient_and_the_sweep_moves_it_off():
    fit, vector = _toy(e=TRUE_E, yield_stress=1e5)
    key = "obj1.yield_stress"
    # on the plateau the window's loss does not depend on the yield stress: its gradient is
    # exactly zero, so descent could never move it
    leaf = vector.normalized[key]
    leaf.requires_grad_(True)
    loss = fit.objective(*fit.rollout_geometry(vector, 5))
    (grad,) = torch.autograd.grad(loss, leaf)
    leaf.requires_grad_(False)
    assert float(loss.detach()) > 0.0 and float(grad) == 0.0

    history: list[dict] = []
    result = coordinate_polish(fit, vector, points=6, frames=5, history=history)
    found = _values(vector)
    # six values over 10-1e6 Pa in log space: the best lies within half a step (5/12 decade)
    assert abs(math.log10(found["yield_stress"]) - math.log10(TRUE_YIELD)) <= 5 / 12 + 1e-6
    assert found["E"] == pytest.approx(TRUE_E, rel=1e-4)  # already best: kept
    assert result["best_loss"] < result["start_loss"] and result["changed"] == [key]
    records = [h for h in history if h["phase"] == POLISH]
    assert len(records) == len(history) == 2 * 6  # two parameters, six values each
    assert {h["parameter"] for h in records} == {"obj1.E", key}


def test_the_sweep_keeps_a_start_it_cannot_beat():
    fit, vector = _toy(e=TRUE_E, yield_stress=TRUE_YIELD)
    result = coordinate_polish(fit, vector, points=5, frames=5, history=[])
    assert result["changed"] == [] and result["best_loss"] == result["start_loss"]
    found = _values(vector)
    assert found["E"] == pytest.approx(TRUE_E, rel=1e-4)
    assert found["yield_stress"] == pytest.approx(TRUE_YIELD, rel=1e-4)


def test_no_points_no_rollouts():
    fit, vector = _toy(e=1e6, yield_stress=1e5)
    history: list[dict] = []
    result = coordinate_polish(fit, vector, points=0, frames=5, history=history)
    assert history == [] and result["changed"] == []
    assert _values(vector)["yield_stress"] == pytest.approx(1e5, rel=1e-4)


def test_the_sweep_enters_the_stage_key_only_when_it_is_on():
    def keys(**identify) -> str:
        recipe = {
            "scene": {"path": "scene"},
            "reconstructor": {"name": "oracle"},
            "lifter": {"name": "gt-points"},
            "simulator": {"name": "warp-mpm"},
            "losses": {},
            "identify": {"contact": "fixed", **identify},
            "evaluate": {},
        }
        return stage_keys(recipe)["identify"]

    assert keys(global_polish=0) == keys()  # runs made before the sweep keep their keys
    assert keys(global_polish=6) != keys()


def test_identification_runs_the_sweep_after_the_candidates_and_only_with_them(tmp_path):
    from types import SimpleNamespace

    from mosiv_framework.pipeline.identify import identify
    from mosiv_framework.pipeline.rundir import RunDir

    def run(folder, **section):
        fit, vector = _toy(e=TRUE_E, yield_stress=1e5)
        values = dict(
            velocity_iterations=0,
            param_iterations=2,
            velocity_lr=0.01,
            param_lr=0.05,
            horizon_start=2,
            horizon_full_at=0.5,
            checkpoint_every=100,
            resync_every=0,
            resync_iterations=0,
            global_frames=0,
            intervals=False,
            seed=0,
        )
        _, history = identify(
            simulator=fit.simulator,
            vector=vector,
            particles=fit.particles,
            world=fit.world,
            targets=fit.targets,
            observed_frames=6,
            objective=fit.objective,
            section=SimpleNamespace(**{**values, **section}),
            run_dir=RunDir(tmp_path / folder),
            config_hash=folder,
        )
        return [h["phase"] for h in history], _values(vector)

    phases, found = run("swept", global_candidates=4, global_polish=3)
    assert phases[:5] == ["global"] * 5  # the start and 4 candidates
    assert phases[5:11] == [POLISH] * 6  # two parameters, three values each
    assert set(phases[11:]) == {"params"}
    assert found["yield_stress"] < YIELD_REACHED  # off the plateau before descent began
    phases, _ = run("no-stage", global_candidates=0, global_polish=3)
    assert POLISH not in phases and "global" not in phases


@pytest.mark.parametrize("contact", ["multi_field", "single_field"])
def test_the_search_scores_its_candidates_in_one_batch_as_one_by_one(contact):
    """warp-mpm rolls the candidates out together (Fit.window_losses -> rollout_batch); on
    the CPU that gives the same losses, bit for bit, and so the same choices as one rollout
    per candidate (the base class's loop), for two bodies that collide."""
    import types

    from mosiv_framework.pipeline.global_search import global_search
    from mosiv_framework.testing.pytest_plugin import require_simulator
    from mosiv_framework.testing.shapes import block, combine, default_params

    registry = require_simulator("warp-mpm")
    options = {"grid": 16, "substeps": 20, "device": "cpu", "contact": contact}
    world = World((0, 0, 0), (1, 1, 1), gravity=(0, 0, -9.8), ground_height=0.0, fps=FPS)
    particles = combine(
        [
            block((0.30, 0.42, 0.30), (0.42, 0.54, 0.42), spacing=0.04, object_id=1),
            block((0.56, 0.42, 0.30), (0.68, 0.54, 0.42), spacing=0.04, object_id=2),
        ],
        {1: "elastic", 2: "plasticine"},
    )
    truth = default_params(
        particles,
        overrides={1: {"E": 2e4}, 2: {"E": 5e4, "yield_stress": 300.0}},
        velocities={1: (1.5, 0.0, 0.0), 2: (-1.5, 0.0, 0.0)},
    )
    sim = registry.create("simulator", "warp-mpm", options)
    traj = sim.rollout(particles, truth, world=world, frames=5)
    targets = {k: traj.object_positions(k).detach() for k in (1, 2)}
    objective = WeightedSum({"chamfer": get_registry().create("loss", "chamfer", {})})

    def search(simulator):
        vector = ParameterVector.create(
            {1: "elastic", 2: "plasticine"},
            {k: truth.initial_velocity[k].clone() for k in (1, 2)},
            identify=("E", "yield_stress"),
            ground_friction=None,
        )
        fit = Fit(simulator, particles, world, targets, objective)
        history: list[dict] = []
        global_search(fit, vector, candidates=6, frames=5, seed=0, history=history)
        coordinate_polish(fit, vector, points=3, frames=5, history=history)
        return [h["global_loss"] for h in history], _values(vector)

    batched = search(sim)
    one_by_one = registry.create("simulator", "warp-mpm", options)
    one_by_one.rollout_batch = types.MethodType(Simulator.rollout_batch, one_by_one)
    assert batched == search(one_by_one)
    losses = [x for x in batched[0] if x is not None]
    assert len(losses) >= 10 and len(set(losses)) > 1  # the candidates differ
