"""On the CPU the grid kernels visit only the box of nodes around the particles
(state.NodeBox). Nodes outside it hold no mass and are never read, so a windowed rollout must
give exactly, bit for bit, what a sweep of the whole grid gives: positions and gradients, through
a collision between two objects, ground contact and a wall."""

from __future__ import annotations

import pytest
import torch
import warp as wp
from mosiv_warp_mpm.state import GridLayout, NodeBox

from mosiv_framework.errors import ConfigError
from mosiv_framework.testing.shapes import combine, default_params, sphere
from mosiv_framework.types import World

WORLD = World((0.0, 0.0, 0.0), (0.5, 0.5, 0.5), ground_height=0.0, fps=24.0)


def _collide_and_land(sim) -> tuple[torch.Tensor, ...]:
    # two balls meet just above the table and the first slides into the x = 0.5 wall
    a = sphere((0.30, 0.25, 0.07), 0.05, spacing=1.0 / 48, object_id=1, material="elastic")
    b = sphere((0.40, 0.25, 0.09), 0.05, spacing=1.0 / 48, object_id=2, material="sand")
    p = combine([a, b])
    params = default_params(
        p,
        overrides={1: {"friction": 0.3}, 2: {"friction": 0.2}},
        velocities={1: (2.0, 0.0, -0.5), 2: (-0.5, 0.0, -1.0)},
        requires_grad=True,
    )
    traj = sim.rollout(p, params, world=WORLD, frames=4)
    weights = torch.randn(len(p), 3, generator=torch.Generator().manual_seed(2))
    (traj.positions[1:] * weights).sum().backward()
    grads = [t.grad for _, t in params.named_tensors() if t.grad is not None]
    return (traj.positions.detach(), *grads)


def test_windowed_grid_matches_the_whole_grid_bit_for_bit(make_warp_simulator) -> None:
    whole = make_warp_simulator(grid=16, substeps=20)
    if wp.get_device(whole.device).is_cuda:
        # CUDA replays one captured graph per frame, so it must sweep the whole grid: asking
        # for the node box there is refused rather than silently ignored
        whole.windowed_grid = True
        with pytest.raises(ConfigError, match="windowed grid needs the CPU"):
            _collide_and_land(whole)
        return
    whole.windowed_grid = False
    windowed = make_warp_simulator(grid=16, substeps=20)
    expected = _collide_and_land(whole)
    got = _collide_and_land(windowed)
    assert windowed._grad_run.windowed and not whole._grad_run.windowed
    assert len(got) == len(expected) >= 5  # positions, two v0 and the laws' parameters
    for g, e in zip(got, expected):
        assert torch.equal(g, e)
    moved = expected[0][-1, :, 0].max() - expected[0][0, :, 0].max()
    assert moved > 0.0  # the bodies did move across nodes during the rollout


def test_node_box_covers_every_stencil_and_stays_in_the_grid() -> None:
    layout = GridLayout.for_world(WORLD, grid=16, fields=2)
    x = torch.tensor([[0.1, 0.2, 0.05], [0.31, 0.22, 0.4]]).numpy()
    box = NodeBox.around(x, layout)
    base = ((x - layout.origin) / layout.dx - 0.5).astype(int)
    for axis in range(3):
        assert box.lo[axis] <= base[:, axis].min()
        assert box.lo[axis] + box.dims[axis] - 1 >= base[:, axis].max() + 2
        assert 0 <= box.lo[axis] and box.lo[axis] + box.dims[axis] <= layout.nodes[axis]
    assert box.count < layout.nodes_per_field
    assert NodeBox.whole(layout).is_whole(layout) and not box.is_whole(layout)
