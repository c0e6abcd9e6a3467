"""The discrete-library baseline picks, per object, the prototype that generated the motion.

A toy simulator squashes each object along z at a rate set by its parameter values
(log-sum of the values of its prototype), so different prototypes give different motions and
the generating prototype is the unique zero-loss choice. Objects are independent in the toy, so
coordinate descent must find the pair exactly.
"""

from __future__ import annotations

import math

import pytest
import torch

from mosiv_framework.errors import ConfigError, SimulationDiverged
from mosiv_framework.interfaces import Simulator
from mosiv_framework.losses import ObjectChamferLoss, WeightedSum
from mosiv_framework.pipeline.library import PROTOTYPES, candidates, pick_prototypes
from mosiv_framework.types import ParticleSet, Trajectory, World

WORLD = World((-1.0, -1.0, 0.0), (1.0, 1.0, 1.0), ground_height=None, fps=10.0)


class Squash(Simulator):
    """Each object flattens along z by exp(-rate t), rate = 0.1 * sum_p log(1 + |value_p|)."""

    def __init__(self, diverge_on: str | None = None):
        self.diverge_on = diverge_on

    def rollout(self, particles, params, *, world, frames):
        t = torch.arange(frames + 1, dtype=torch.float32) / world.fps
        out = particles.positions[None].repeat(frames + 1, 1, 1)
        for k, p in params.objects.items():
            if self.diverge_on and float(p.values.get("E", 0)) >= 1e6:
                raise SimulationDiverged(
                    object_id=k, frame=1, substep=0, reason="too stiff", advice=""
                )
            rate = 0.1 * sum(math.log1p(abs(float(v))) for v in p.values.values())
            sel = particles.object_ids == k
            c = particles.positions[sel].mean(0)
            z = c[2] + (particles.positions[sel, 2] - c[2])[None] * torch.exp(-rate * t)[:, None]
            out[:, sel, 2] = z
        return Trajectory(out, particles.object_ids, world.fps)


def scene(families):
    gen = torch.Generator().manual_seed(0)
    pos = [
        torch.rand(60, 3, generator=gen) * 0.1 + torch.tensor([0.3 * i, 0.0, 0.5])
        for i in range(len(families))
    ]
    ids = torch.cat([torch.full((60,), i + 1) for i in range(len(families))])
    return ParticleSet(
        torch.cat(pos),
        torch.full((60 * len(families),), 1e-6),
        ids,
        {i + 1: f for i, f in enumerate(families)},
    )


def targets_from(sim, particles, choice, frames):
    from mosiv_framework.pipeline.library import library_params

    params = library_params(choice, {k: torch.zeros(3) for k in choice}, ground_friction=0.3)
    traj = sim.rollout(particles, params, world=WORLD, frames=frames)
    return {k: traj.object_positions(k) for k in choice}


@pytest.mark.parametrize("scope", ["family", "all"])
def test_library_recovers_the_generating_prototypes(scope):
    by_name = {p.name: p for p in PROTOTYPES}
    truth = {1: by_name["elastic-soft"], 2: by_name["plasticine-firm"]}
    particles = scene(["elastic", "plasticine"])
    sim = Squash()
    targets = targets_from(sim, particles, truth, frames=4)
    choice, tried = pick_prototypes(
        simulator=sim,
        particles=particles,
        world=WORLD,
        targets=targets,
        observed_frames=5,
        objective=WeightedSum({"chamfer": ObjectChamferLoss(max_points=0)}),
        velocities={1: torch.zeros(3), 2: torch.zeros(3)},
        ground_friction=0.3,
        scope=scope,
    )
    assert {k: p.name for k, p in choice.items()} == {1: "elastic-soft", 2: "plasticine-firm"}
    assert min(r["loss"] for r in tried) < 1e-12
    if scope == "all":  # every family's entries were candidates for each object
        assert len({r["choice"]["1"] for r in tried}) == len(PROTOTYPES)


def test_diverging_prototypes_are_skipped_not_fatal():
    by_name = {p.name: p for p in PROTOTYPES}
    truth = {1: by_name["elastic-medium"]}
    particles = scene(["elastic"])
    sim = Squash(diverge_on="E")
    targets = targets_from(sim, particles, truth, frames=3)
    choice, tried = pick_prototypes(
        simulator=sim,
        particles=particles,
        world=WORLD,
        targets=targets,
        observed_frames=4,
        objective=WeightedSum({"chamfer": ObjectChamferLoss(max_points=0)}),
        velocities={1: torch.zeros(3)},
        ground_friction=0.3,
    )
    assert choice[1].name == "elastic-medium"
    assert any("diverged" in r for r in tried)


def test_every_prototype_is_valid_and_unknown_scope_is_named():
    for proto in PROTOTYPES:
        proto.values()  # raises naming the prototype if outside its law's bounds
    assert {p.family for p in candidates("sand", scope="family")} == {"sand"}
    with pytest.raises(ConfigError, match="library_scope"):
        candidates("sand", scope="nearby")
