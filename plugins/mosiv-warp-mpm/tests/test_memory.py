"""Backward memory: checkpoints grow with frames only; the one-frame workspace does not grow
with frames (it holds substeps + 1 particle states and one grid)."""

from __future__ import annotations

from mosiv_framework.testing.shapes import block, default_params
from mosiv_framework.types import World


def _memory(make, frames: int, substeps: int) -> dict:
    sim = make(grid=16, substeps=substeps)
    world = World((0.0, 0.0, 0.0), (1.0, 1.0, 1.0), ground_height=0.0)
    p = block((0.4, 0.4, 0.1), (0.5, 0.5, 0.2), spacing=1.0 / 32, object_id=1)
    params = default_params(p, requires_grad=True)
    traj = sim.rollout(p, params, world=world, frames=frames)
    traj.positions[-1].sum().backward()
    assert params.objects[1]["E"].grad is not None
    return dict(sim.last_memory)


def test_checkpoints_grow_with_frames_not_substeps(make_warp_simulator) -> None:
    a = _memory(make_warp_simulator, frames=2, substeps=10)
    b = _memory(make_warp_simulator, frames=4, substeps=10)
    c = _memory(make_warp_simulator, frames=2, substeps=20)
    assert b["checkpoint_bytes"] == 2 * a["checkpoint_bytes"]
    assert c["checkpoint_bytes"] == a["checkpoint_bytes"]
    assert b["backward_workspace_bytes"] == a["backward_workspace_bytes"]
