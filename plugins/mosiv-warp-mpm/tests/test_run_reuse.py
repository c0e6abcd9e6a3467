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


def _gradients(sim, E: float, speed: float) -> tuple[torch.Tensor, torch.Tensor]:
    """d(mean final height)/dE and /dv0 of a falling block that lands during the rollout."""
    p = block((0.4, 0.4, 0.02), (0.5, 0.5, 0.12), spacing=1.0 / 32, object_id=1)
    params = default_params(p, velocities={1: (speed, 0.0, -1.0)}, requires_grad=True)
    params.objects[1].values["E"] = torch.tensor(E, requires_grad=True)
    traj = sim.rollout(p, params, world=WORLD, frames=3)
    traj.positions[-1, :, 2].mean().backward()
    return params.objects[1].values["E"].grad, params.initial_velocity[1].grad


def test_reused_differentiable_run_matches_a_fresh_simulator(make_warp_simulator) -> None:
    # identification rolls out the same layout every iteration: the second rollout reuses the
    # first's run, its backward workspace (and on CUDA the captured adjoint graph)
    reused = make_warp_simulator(grid=16, substeps=10)
    _gradients(reused, 5.0e4, 0.0)
    first_run = reused._grad_run
    second = _gradients(reused, 8.0e4, 0.3)
    fresh = _gradients(make_warp_simulator(grid=16, substeps=10), 8.0e4, 0.3)
    assert reused._grad_run is first_run
    assert all(torch.equal(a, b) for a, b in zip(second, fresh))
    assert float(second[0].abs()) > 0.0  # the landing makes the height depend on E


def test_two_rollouts_before_backward_keep_their_own_runs(make_warp_simulator) -> None:
    sim = make_warp_simulator(grid=16, substeps=10)
    p = block((0.4, 0.4, 0.02), (0.5, 0.5, 0.12), spacing=1.0 / 32, object_id=1)
    grads = []
    losses = []
    for E in (5.0e4, 8.0e4):
        params = default_params(p, velocities={1: (0.0, 0.0, -1.0)}, requires_grad=True)
        params.objects[1].values["E"] = torch.tensor(E, requires_grad=True)
        traj = sim.rollout(p, params, world=WORLD, frames=3)
        losses.append((traj.positions[-1, :, 2].mean(), params.objects[1].values["E"]))
    for loss, E in losses:  # backward in the order of the rollouts, after both forwards
        loss.backward()
        grads.append(E.grad)
    expected = [
        _gradients(make_warp_simulator(grid=16, substeps=10), E, 0.0)[0] for E in (5e4, 8e4)
    ]
    assert all(torch.equal(a, b) for a, b in zip(grads, expected))
