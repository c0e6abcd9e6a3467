"""Fakes shared by the diagnosis tests (tests/test_diagnose_parts_*.py): an elastic/sand pair's
parameters, a RunContext stand-in for building and screening candidates, a simulator
divergence, and a real RunContext of one body on warp-mpm's CPU path."""

from __future__ import annotations

import math
from types import SimpleNamespace

import torch


def _elastic_pair_params():
    from mosiv_framework.types import ObjectParams, SimulationParams

    elastic = {"E": torch.tensor(5e4), "nu": torch.tensor(0.25), "rho": torch.tensor(1e3)}
    elastic["friction"] = torch.tensor(0.3)
    sand = {**elastic, "friction_angle": torch.tensor(30.0)}
    return SimulationParams(
        {1: ObjectParams("elastic", elastic), 2: ObjectParams("sand", sand)},
        {1: torch.zeros(3), 2: torch.zeros(3)},
        torch.tensor(0.3),
        {},
    )


class _OneByOneLosses:
    """``RunContext.rollout_losses`` and ``simulate_batch`` for fake contexts: the fake's own
    ``rollout`` and ``loss`` per parameter set, in order (inf where the rollout diverges or the
    loss is not finite), and its own ``simulate`` per set (the SimulationDiverged where it
    raises one)."""

    def simulate_batch(self, params_list, *, frames):
        from mosiv_framework.errors import SimulationDiverged

        results = []
        for params in params_list:
            try:
                results.append(self.simulate(params, frames=frames))
            except SimulationDiverged as exc:
                results.append(exc)
        return results

    def rollout_losses(self, params_list, fit_frames):
        from mosiv_framework.errors import SimulationDiverged

        losses = []
        for params in params_list:
            try:
                value = float(self.loss(self.rollout(params, frames=max(fit_frames)), fit_frames))
            except SimulationDiverged:
                value = math.inf
            losses.append(value if math.isfinite(value) else math.inf)
        return losses


class _FakeContext(_OneByOneLosses):
    """The few RunContext members that candidate building and screening read, for an elastic
    pair on a simulator supporting ``terms`` (subclasses add rollouts and a loss)."""

    identified = _elastic_pair_params()
    object_ids = [1, 2]
    simulator_name = "fake"
    fps = 24.0

    def __init__(self, terms: frozenset[str], *, ground_height: float | None = None):
        from types import SimpleNamespace

        self.simulator = SimpleNamespace(supported_terms=terms)
        self.world = SimpleNamespace(gravity=(0.0, 0.0, -9.81), ground_height=ground_height)

    def parameter_vector(self):
        from types import SimpleNamespace

        return SimpleNamespace(normalized={"obj1.friction": None})  # no friction candidate


def _diverged(frame: int = 18) -> Exception:
    from mosiv_framework.errors import SimulationDiverged

    return SimulationDiverged(
        object_id=2, frame=frame, substep=1, reason="a particle moved too far", advice="test"
    )


def one_body_context(world, particles, truth, identified, *, n_frames, observed_frames):
    """A RunContext of ``particles`` on warp-mpm's CPU path (grid 16, 10 substeps) whose
    targets are ``truth``'s rollout over ``n_frames`` frames and whose identified model is
    ``identified`` (friction not identified, no physics terms in the recipe)."""
    from omegaconf import OmegaConf

    from mosiv_framework.diagnose.context import RunContext
    from mosiv_framework.testing.pytest_plugin import require_simulator

    sim = require_simulator("warp-mpm").create(
        "simulator", "warp-mpm", {"grid": 16, "substeps": 10, "device": "cpu"}
    )
    with torch.no_grad():
        target = sim.rollout(particles, truth, world=world, frames=n_frames - 1)
    recipe = {"identify": {"identify_friction": False, "identify_ground_friction": False}}
    return RunContext(
        run_dir=None,
        recipe=OmegaConf.create({**recipe, "physics_terms": {}}),
        scene=SimpleNamespace(world=world, fps=world.fps),
        particles=particles,
        targets={1: target.object_positions(1).detach().cpu()},
        identified=identified,
        identified_json={},
        simulator=sim,
        simulator_name="warp-mpm",
        observed_frames=observed_frames,
        n_frames=n_frames,
        loss_points=0,
    )


def windy_block_context(n_frames: int):
    """A RunContext of one elastic block thrown onto the ground under a concealed sideways wind
    (warp-mpm on the CPU, grid 16, 10 substeps, every frame observed), identified without the
    wind."""
    from mosiv_framework.testing.shapes import block, default_params
    from mosiv_framework.types import World

    world = World((0, 0, 0), (1, 1, 1), gravity=(0, 0, -9.8), ground_height=0.0, fps=24.0)
    p = block((0.35, 0.45, 0.12), (0.45, 0.55, 0.22), spacing=0.025, object_id=1)
    velocity = {1: (0.5, 0.0, -0.5)}
    truth = default_params(p, velocities=velocity, terms={"wind": {"acceleration": [0, 2, 0]}})
    identified = default_params(p, velocities=velocity)
    return one_body_context(
        world, p, truth, identified, n_frames=n_frames, observed_frames=n_frames
    )


def spy_batches(monkeypatch, sim) -> list[int]:
    """Record the member count of every ``rollout_batch`` call ``sim`` gets."""
    sizes: list[int] = []
    batched = sim.rollout_batch

    def spy(particles, params_list, **kwargs):
        sizes.append(len(params_list))
        return batched(particles, params_list, **kwargs)

    monkeypatch.setattr(sim, "rollout_batch", spy)
    return sizes
