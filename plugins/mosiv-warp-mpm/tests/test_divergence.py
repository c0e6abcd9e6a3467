"""An absurd stiffness with far too few substeps raises SimulationDiverged, never NaN."""

from __future__ import annotations

import pytest
import torch

from mosiv_framework.errors import SimulationDiverged
from mosiv_framework.testing.shapes import block, default_params
from mosiv_framework.types import World


def test_stiff_block_with_one_substep_raises(make_warp_simulator) -> None:
    sim = make_warp_simulator(grid=16, substeps=1)
    world = World((0.0, 0.0, 0.0), (1.0, 1.0, 1.0), ground_height=0.0)
    p = block((0.4, 0.4, 0.0), (0.6, 0.6, 0.2), spacing=1.0 / 32, object_id=3)
    params = default_params(p, overrides={3: {"E": 1e9}}, velocities={3: (0.0, 0.0, -3.0)})
    with pytest.raises(SimulationDiverged) as info:
        with torch.no_grad():
            sim.rollout(p, params, world=world, frames=5)
    err = info.value
    assert err.object_id == 3 and err.frame >= 1 and 0 <= err.substep < 1
    assert "substeps" in err.advice and "object 3" in str(err)


def test_particles_stay_on_the_grid(make_warp_simulator) -> None:
    """A fast block thrown at a wall is stopped by the slip wall inside the padded grid."""
    sim = make_warp_simulator(grid=16, substeps=20)
    world = World((0.0, 0.0, 0.0), (1.0, 1.0, 1.0), gravity=(0, 0, 0), ground_height=None)
    p = block((0.8, 0.4, 0.4), (0.9, 0.5, 0.5), spacing=1.0 / 32, object_id=1)
    params = default_params(p, velocities={1: (3.0, 0.0, 0.0)})
    with torch.no_grad():
        traj = sim.rollout(p, params, world=world, frames=4)
    assert torch.isfinite(traj.positions).all()
    dx = 1.0 / 16
    assert traj.positions[..., 0].max() <= 1.0 + dx, "particles passed the wall"
