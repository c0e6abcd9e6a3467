"""An unstable rollout raises SimulationDiverged naming the object, frame, substep and advice;
particles never leave the grid and NaN is never returned."""

import pytest
import torch

from mosiv_framework.errors import SimulationDiverged
from mosiv_framework.testing.shapes import block, combine, default_params
from mosiv_framework.types import World

WORLD = World((0.0, 0.0, 0.0), (0.5, 0.5, 0.5), gravity=(0.0, 0.0, -9.8), ground_height=0.0)


def test_too_stiff_object_diverges_with_its_id(simulator_factory):
    """Object 2 is far too stiff and light for 2 substeps per frame (CFL violated ~100x);
    object 1 is soft. The error must blame object 2 and advise more substeps."""
    sim = simulator_factory(grid=16, substeps=2)
    a = block((0.1, 0.2, 0.05), (0.18, 0.28, 0.13), spacing=1.0 / 48, object_id=1)
    b = block((0.3, 0.2, 0.05), (0.38, 0.28, 0.13), spacing=1.0 / 48, object_id=2)
    p = combine([a, b])
    params = default_params(
        p,
        overrides={1: {"E": 1e3}, 2: {"E": 1e7, "rho": 50.0}},
        velocities={2: (0.0, 0.0, -1.0)},
    )
    with pytest.raises(SimulationDiverged) as err:
        with torch.no_grad():
            sim.rollout(p, params, world=WORLD, frames=20)
    e = err.value
    assert e.object_id == 2
    assert 1 <= e.frame <= 20 and 0 <= e.substep < 2
    assert "substeps" in e.advice and "lower E" in e.advice
    assert "object 2" in str(e)


def test_fast_object_stays_on_grid(simulator_factory):
    """A block thrown at 30 m/s into a wall is stopped by the slip walls: every position stays
    finite and inside the padded grid, or the run reports leaving the domain -- never NaN."""
    sim = simulator_factory(grid=16, substeps=20)
    p = block((0.2, 0.2, 0.2), (0.28, 0.28, 0.28), spacing=1.0 / 48, object_id=1)
    params = default_params(p, overrides={1: {"E": 2e4}}, velocities={1: (30.0, 0.0, 0.0)})
    try:
        with torch.no_grad():
            traj = sim.rollout(p, params, world=WORLD, frames=4)
    except SimulationDiverged as e:  # acceptable outcome: an explicit, located error
        assert e.object_id == 1 and e.frame >= 1
        return
    pos = traj.positions
    assert torch.isfinite(pos).all()
    dx = 0.5 / 16
    assert pos.min() >= -3 * dx and pos.max() <= 0.5 + 3 * dx
    # it did reach the wall region (x near the upper domain side)
    assert pos[-1, :, 0].max() > 0.5 - 3 * dx
