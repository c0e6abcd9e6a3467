"""The ``expression`` term costs nothing when it is off.

Identification rollouts at small particle counts are bound by kernel launches, so a rollout
without the term must launch none of its work: not the centre-sum kernels, not their memsets,
not the per-frame clock update. An expression without the other objects' features (dp, dv)
skips the centre sums. Counted by wrapping ``wp.launch`` and the arrays' memsets, forward and
backward, on one simulator that also runs the other modes (so a flag left over from an earlier
rollout would show). And the switch changes nothing else: an expression whose coefficients are
all 0 gives the rollout without the term bit for bit, positions and gradients. On CUDA
(MOSIV_TEST_DEVICE=cuda) the counted rollouts capture their graphs anew, and the comparisons
hold to float32 round-off (the GPU's atomic sums run in schedule order).
"""

from __future__ import annotations

import pytest
import torch
import warp as wp
from mosiv_warp_mpm import expression_kernels as XK

from mosiv_framework.testing.shapes import block, combine, default_params
from mosiv_framework.types import World

WORLD = World((0.0, 0.0, 0.0), (1.0, 1.0, 1.0), ground_height=0.0)
SUBSTEPS, FRAMES = 10, 2
CENTRE_KERNELS = (XK.field_moments, XK.other_centres)
RELATIVE = {"a_x:dp_x": 6.0, "a_y:dv_y": -1.0}
LOCAL = {"a_x:v_x": -0.5, "a_z:h": 1.0, "a_y:t": 0.2}


def _particles():
    """Two blocks, one velocity field each (multi-field contact), falling onto the ground."""
    return combine(
        [
            block((0.3, 0.4, 0.05), (0.4, 0.5, 0.15), spacing=1.0 / 48, object_id=1),
            block((0.55, 0.42, 0.05), (0.65, 0.52, 0.15), spacing=1.0 / 48, object_id=2),
        ]
    )


def _params(particles, expression: dict[str, float], requires_grad: bool):
    params = default_params(
        particles,
        velocities={1: (0.4, 0.0, -0.3), 2: (-0.4, 0.1, -0.2)},
        requires_grad=requires_grad,
    )
    if expression:
        params.terms["expression"] = {
            name: torch.tensor(value, requires_grad=requires_grad)
            for name, value in expression.items()
        }
    return params


def _rollout_with_backward(sim, particles, expression: dict[str, float]):
    """Positions and the gradients of a weighted sum of them w.r.t. every parameter."""
    params = _params(particles, expression, requires_grad=True)
    traj = sim.rollout(particles, params, world=WORLD, frames=FRAMES)
    weights = torch.linspace(-1.0, 1.0, traj.positions.numel()).reshape(traj.positions.shape)
    (traj.positions * weights).sum().backward()
    grads = {n: t.grad for n, t in params.named_tensors() if not n.startswith("term.")}
    return traj.positions.detach(), grads


class LaunchLog:
    """The kernels launched through ``wp.launch`` and the arrays memset (``zero_``/``fill_``),
    while installed; the originals still run."""

    def __init__(self, monkeypatch):
        self.kernels: list = []
        self.memsets: list = []  # the arrays themselves: an id could be reused after a free
        launch, zero, fill = wp.launch, wp.array.zero_, wp.array.fill_

        def counted_launch(kernel, *args, **kwargs):
            self.kernels.append(kernel)
            return launch(kernel, *args, **kwargs)

        def counted_zero(arr):
            self.memsets.append(arr)
            return zero(arr)

        def counted_fill(arr, value):
            self.memsets.append(arr)
            return fill(arr, value)

        monkeypatch.setattr(wp, "launch", counted_launch)
        monkeypatch.setattr(wp.array, "zero_", counted_zero)
        monkeypatch.setattr(wp.array, "fill_", counted_fill)

    def reset(self) -> None:
        self.kernels.clear()
        self.memsets.clear()

    def centre_launches(self) -> int:
        return sum(any(k is c for c in CENTRE_KERNELS) for k in self.kernels)

    def memsets_of(self, arrays) -> int:
        return sum(any(m is a for a in arrays) for m in self.memsets)


def _term_arrays(run) -> tuple[list, list]:
    """(the per-field sums of the run's grids and their gradients, the clock)."""
    grids = [run.grid] + ([run._backward.grid] if run._backward is not None else [])
    sums = [a for g in grids for a in g.field_arrays()]
    sums += [a.grad for a in sums if a.grad is not None]
    return sums, [run.clock]


def _is_cuda(sim) -> bool:
    return wp.get_device(sim.device).is_cuda


def _same(a: torch.Tensor, b: torch.Tensor) -> bool:
    """Bit for bit on the CPU, where Warp runs the threads in order; on a GPU the atomic sums
    run in schedule order (docs/BENCHMARKS.md, Determinism), so to float32 round-off."""
    if a.device.type == "cpu" and not torch.cuda.is_available():
        return torch.equal(a.view(torch.int32), b.view(torch.int32))
    return torch.allclose(a, b, rtol=1e-4, atol=1e-6)


@pytest.fixture(scope="module")
def sim(make_warp_simulator):
    return make_warp_simulator(grid=16, substeps=SUBSTEPS)


def _forget_graphs(run) -> None:
    """Drop the run's captured CUDA graphs, so that its next rollout captures them again,
    launching through wp.launch (a replay goes past Python)."""
    run._graphs.clear()
    if run._backward is not None:
        run._backward._graphs.clear()


@pytest.mark.parametrize("differentiable", [False, True])
def test_without_the_term_a_rollout_launches_none_of_its_work(sim, monkeypatch, differentiable):
    particles = _particles()

    def roll(expression):
        if differentiable:
            _rollout_with_backward(sim, particles, expression)
        else:
            with torch.no_grad():
                params = _params(particles, expression, False)
                sim.rollout(particles, params, world=WORLD, frames=FRAMES)
        run = sim._grad_run if differentiable else sim._forward_run
        return run, *_term_arrays(run)

    run, _, _ = roll(RELATIVE)  # the run (and its backward grid) exist, the term's flags were on
    _forget_graphs(run)
    log = LaunchLog(monkeypatch)
    run, sums, clock = roll({})
    assert log.centre_launches() == 0
    assert log.memsets_of(sums) == 0
    assert log.memsets_of(clock) == 0
    assert len(log.kernels) > 0  # the log sees the rollout's own launches

    # the counting can fail: with the other objects' features every substep launches the two
    # centre-sum kernels and zeroes the sums, and a backward frame's substep does both three
    # times more (its re-simulation, its taped replay: the kernels' adjoints and the sums'
    # gradients); on CUDA only the first frame's launches go through Python, the others
    # replay its graph, while the clock is set outside the graph every frame
    _forget_graphs(run)
    log.reset()
    run, sums, clock = roll(RELATIVE)
    passes = 4 if differentiable else 1
    launched_frames = 1 if _is_cuda(sim) else FRAMES
    assert log.centre_launches() == 2 * passes * SUBSTEPS * launched_frames
    per_pass = len(run.grid.field_arrays())
    assert log.memsets_of(sums) == per_pass * passes * SUBSTEPS * launched_frames
    assert log.memsets_of(clock) == FRAMES * (2 if differentiable else 1)


def test_an_expression_of_local_features_skips_the_centre_sums(sim, monkeypatch):
    particles = _particles()
    _rollout_with_backward(sim, particles, RELATIVE)
    _forget_graphs(sim._grad_run)
    log = LaunchLog(monkeypatch)
    _rollout_with_backward(sim, particles, LOCAL)
    run = sim._grad_run
    sums, clock = _term_arrays(run)
    assert log.centre_launches() == 0
    # the sums the expression reads (times zero coefficients) hold the earlier rollout's
    # values: zeroed once per grid (forward, backward), not per substep
    grids = (run.grid, run._backward.grid)
    assert log.memsets_of(sums) == sum(len(g.field_arrays()) for g in grids)
    assert log.memsets_of(clock) == 2 * FRAMES  # forward and backward frames read the time


@pytest.mark.parametrize(
    "zeros", [{"a_x:1": 0.0, "a_z:v_z": 0.0}, {"a_x:dp_x": 0.0, "a_y:dv_z": 0.0}]
)
def test_zero_coefficients_give_the_rollout_without_the_term_bit_for_bit(sim, zeros):
    """Local features, and the other objects' (which turn the centre sums on): positions and
    gradients w.r.t. the material parameters, friction and initial velocities."""
    particles = _particles()
    pos_off, grads_off = _rollout_with_backward(sim, particles, {})
    pos_on, grads_on = _rollout_with_backward(sim, particles, zeros)
    assert _same(pos_on, pos_off)
    assert grads_on.keys() == grads_off.keys()
    for name, g in grads_off.items():
        assert _same(grads_on[name], g), name
    assert float(grads_off["v0.obj2"].abs().sum()) > 0.0


def test_one_simulator_switching_modes_matches_fresh_simulators(sim, make_warp_simulator):
    """Runs (and on CUDA their captured graphs, one per centre-sum mode) serve rollouts of
    every mode in turn: each equals a fresh simulator's rollout, positions and gradients."""
    particles = _particles()
    for expression in (RELATIVE, LOCAL, {}, RELATIVE, {}):
        reused = _rollout_with_backward(sim, particles, expression)
        fresh = _rollout_with_backward(
            make_warp_simulator(grid=16, substeps=SUBSTEPS), particles, expression
        )
        with torch.no_grad():
            params = _params(particles, expression, requires_grad=False)
            forward = sim.rollout(particles, params, world=WORLD, frames=FRAMES).positions
        assert _same(reused[0], fresh[0]) and _same(forward, fresh[0])
        assert all(_same(reused[1][n], g) for n, g in fresh[1].items())
