"""Forward-only rollouts reuse one run (buffers, CUDA graph): a reused run must give exactly
what a fresh simulator gives, for new positions, volumes, velocities and parameters."""

from __future__ import annotations

import torch

from mosiv_framework.testing.shapes import block, default_params
from mosiv_framework.types import World

WORLD = World((0.0, 0.0, 0.0), (1.0, 1.0, 1.0), ground_height=0.0)


def _rollout(sim, shift: float, speed: float, E: float):
    p = block((0.4 + shift, 0.4, 0.1), (0.5 + shift, 0.5, 0.2), spacing=1.0 / 32, object_id=1)
    p.volumes.mul_(1.0 + shift)  # a different volume per call, so refresh() is exercised
    params = default_params(p, velocities={1: (speed, 0.0, 0.0)})
    params.objects[1].values["E"] = torch.tensor(E)
    with torch.no_grad():
        return sim.rollout(p, params, world=WORLD, frames=2).positions


def test_reused_forward_run_matches_a_fresh_simulator(make_warp_simulator) -> None:
    reused = make_warp_simulator(grid=16, substeps=10)
    _rollout(reused, 0.0, 0.0, 5.0e4)  # builds the run that the next call reuses
    second = _rollout(reused, 0.05, 0.4, 8.0e4)
    fresh = _rollout(make_warp_simulator(grid=16, substeps=10), 0.05, 0.4, 8.0e4)
    assert reused._forward_run is not None
    assert torch.equal(second, fresh)
