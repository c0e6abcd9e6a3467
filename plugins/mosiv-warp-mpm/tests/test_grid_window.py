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


def _assert_same(got: tuple, expected: tuple, *, cuda: bool) -> None:
    """Positions and gradients of two rollouts: bit for bit on the CPU; on CUDA, whose float
    atomics sum P2G and the adjoints in another order every run (on an H200 a gradient through
    this collision differed by 0.14 % between runs), positions within 1e-4 and gradients
    within 1 %."""
    for i, (g, e) in enumerate(zip(got, expected)):
        if cuda:
            rtol = 1e-4 if i == 0 else 1e-2
            assert torch.allclose(g, e, rtol=rtol, atol=1e-6), (i, g, e)
        else:
            assert torch.equal(g, e), i


def test_windowed_grid_matches_the_whole_grid_bit_for_bit(make_warp_simulator) -> None:
    whole = make_warp_simulator(grid=16, substeps=20, grid_window="whole")
    windowed = make_warp_simulator(grid=16, substeps=20, grid_window="particles")
    expected = _collide_and_land(whole)
    got = _collide_and_land(windowed)
    assert windowed._grad_run.windowed and not whole._grad_run.windowed
    assert len(got) == len(expected) >= 5  # positions, two v0 and the laws' parameters
    _assert_same(got, expected, cuda=wp.get_device(whole.device).is_cuda)
    moved = expected[0][-1, :, 0].max() - expected[0][0, :, 0].max()
    assert moved > 0.0  # the bodies did move across nodes during the rollout


@pytest.mark.parametrize("threads", [None, 7])
def test_the_device_window_matches_the_whole_grid_bit_for_bit(
    make_warp_simulator, monkeypatch, threads
) -> None:
    """grid_window "device": each substep's box found and kept on the device, the launches of
    a fixed size, so that a CUDA frame stays one captured graph. Positions and gradients are
    those of the whole grid (bit for bit on the CPU), the boxes it used were windows, not the
    whole grid, and with 7 threads a field (state.WINDOW_THREADS), each thread taking every
    7th node of the box, nothing changes either."""
    if threads is not None:
        monkeypatch.setattr("mosiv_warp_mpm.run.WINDOW_THREADS", threads)
    whole = make_warp_simulator(grid=16, substeps=20, grid_window="whole")
    device = make_warp_simulator(grid=16, substeps=20, grid_window="device")
    expected = _collide_and_land(whole)
    got = _collide_and_land(device)
    run = device._grad_run
    assert run.window == "device" and run.graphed == wp.get_device(device.device).is_cuda
    _assert_same(got, expected, cuda=wp.get_device(whole.device).is_cuda)
    if threads is not None:
        assert run.substep_window(run.a, 0).stride == threads
    rows = run.boxes.numpy().reshape(-1, 2, 3)
    counts = rows[:, 1].prod(axis=1)
    assert len(rows) == 20 and (counts < run.layout.nodes_per_field).all()


def test_the_box_found_on_the_device_is_the_hosts(make_warp_simulator) -> None:
    """node_window.box_from_bounds makes NodeBox.from_bases's box from the same stencil-base
    bounds: inside the grid, clipped at either side, and the whole grid when no particle was
    counted (the bounds still at their start)."""
    from mosiv_warp_mpm.node_window import box_from_bounds
    from mosiv_warp_mpm.run import _NO_BASE

    layout = GridLayout.for_world(WORLD, grid=16, fields=1)
    cases = [
        ((3, 4, 5), (7, 9, 6)),  # inside
        ((0, -2, 5), (20, 3, 30)),  # clipped at both ends
        ((_NO_BASE,) * 3, (-_NO_BASE,) * 3),  # nothing counted
    ]
    boxes = wp.zeros(2, dtype=wp.vec3i, device="cpu")
    for low, high in cases:
        bounds = wp.array([*low, *high], dtype=int, device="cpu")
        wp.launch(
            box_from_bounds, dim=1, inputs=[bounds, wp.vec3i(*layout.nodes), boxes, 0], device="cpu"
        )
        lo, dims = (tuple(int(v) for v in row) for row in boxes.numpy())
        assert NodeBox(lo, dims) == NodeBox.from_bases(low, high, layout), (low, high)


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


def test_device_box_is_the_box_around_the_particles(make_warp_simulator) -> None:
    """The box a windowed CUDA run reduces on the device (kernels.stencil_base_bounds) is the
    one read from the positions on the host, and a non-finite position counts for nothing."""
    sim = make_warp_simulator(grid=32, substeps=4, grid_window="particles")
    a = sphere((0.12, 0.30, 0.08), 0.04, spacing=1.0 / 64, object_id=1, material="elastic")
    b = sphere((0.37, 0.21, 0.33), 0.03, spacing=1.0 / 64, object_id=2, material="sand")
    p = combine([a, b])
    sim.rollout(p, default_params(p), world=WORLD, frames=1)
    run = sim._forward_run
    state = run.a
    x = state.x.numpy().copy()
    assert run.device_box(state) == NodeBox.around(x, run.layout)
    x[0] = float("nan")
    state.x.assign(x)
    assert run.device_box(state) == NodeBox.around(x[1:], run.layout)
    assert not run.device_box(state).is_whole(run.layout)


def test_a_rollout_through_the_device_box_matches_the_whole_grid(
    make_warp_simulator, monkeypatch
) -> None:
    """The windowed CUDA path's boxes (device_box, one per substep, no captured graph) give
    the whole grid's rollout and gradients. On the CPU, where a windowed run reads its boxes
    from the positions on the host, the device boxes are swapped in, and the results must
    agree bit for bit; on CUDA they are the windowed run's own boxes."""
    whole = make_warp_simulator(grid=16, substeps=20, grid_window="whole")
    expected = _collide_and_land(whole)
    from mosiv_warp_mpm.run import MPMRun

    boxes = []

    def device_box(run, state):
        boxes.append(MPMRun.device_box(run, state))
        return boxes[-1]

    monkeypatch.setattr(MPMRun, "active_box", device_box)
    got = _collide_and_land(make_warp_simulator(grid=16, substeps=20, grid_window="particles"))
    _assert_same(got, expected, cuda=wp.get_device(whole.device).is_cuda)
    assert boxes and all(
        not box.is_whole(GridLayout.for_world(WORLD, grid=16, fields=2)) for box in boxes
    )


def test_grid_window_names_its_valid_values(make_warp_simulator) -> None:
    with pytest.raises(ConfigError, match="grid_window='box': valid values are"):
        make_warp_simulator(grid=16, substeps=4, grid_window="box")


def test_auto_leaves_the_window_to_the_device(make_warp_simulator) -> None:
    """grid_window auto: the run chooses (the host's box on the CPU, the device's box on
    CUDA), for single and batched rollouts alike; an explicit choice holds for every run."""
    auto = make_warp_simulator(grid=16, substeps=4)
    assert auto._window(1) is None and auto._window(4) is None
    for choice in ("whole", "particles", "device"):
        sim = make_warp_simulator(grid=16, substeps=4, grid_window=choice)
        assert sim._window(1) == choice and sim._window(4) == choice


def test_a_run_without_a_choice_windows_as_its_device_does(make_warp_simulator) -> None:
    sim = make_warp_simulator(grid=16, substeps=4)
    p = sphere((0.25, 0.25, 0.1), 0.04, spacing=1.0 / 32, object_id=1, material="elastic")
    sim.rollout(p, default_params(p), world=WORLD, frames=1)
    cuda = wp.get_device(sim.device).is_cuda
    run = sim._forward_run
    assert run.window == ("device" if cuda else "particles") and run.graphed == cuda


def test_deterministic_atomics_keep_one_node_a_thread(make_warp_simulator) -> None:
    """Warp sizes a deterministic launch's records by one per atomic and thread, so the device
    window then launches one thread a node (the whole grid's count), not WINDOW_THREADS
    threads each looping over several nodes. Only the option is read: a deterministic
    simulator is built in a child process elsewhere (test_deterministic_option.py)."""
    from dataclasses import replace

    sim = make_warp_simulator(grid=16, substeps=4)
    layout = GridLayout.for_world(WORLD, grid=16, fields=2)
    assert sim._window_threads(layout) is None
    sim.options = replace(sim.options, deterministic=True)
    assert sim._window_threads(layout) == layout.nodes_per_field
