"""Batched rollouts (Simulator.rollout_batch): every member equals the single rollout of its
parameters, a diverging member is reported without stopping the others, and the base class's
loop returns what repeated rollouts return."""

from __future__ import annotations

import pytest
import torch
import warp as wp

from mosiv_framework.errors import SimulationDiverged
from mosiv_framework.interfaces import Simulator, member_particles
from mosiv_framework.testing.shapes import block, combine, default_params
from mosiv_framework.types import ObjectParams, SimulationParams, Trajectory, World

WORLD = World((0.0, 0.0, 0.0), (1.0, 1.0, 1.0), ground_height=0.02)
#: float32 round-off allowed between a member and its single rollout (m and m/s); on the CPU
#: they agree bit for bit, on a GPU P2G's atomic sums run in another order
POSITION_TOL = 1e-5
VELOCITY_TOL = 1e-4


def two_blocks():
    """Two 8x8x8 blocks (512 particles each) that collide and land: contact, ground, walls."""
    left = block((0.20, 0.35, 0.05), (0.45, 0.60, 0.30), spacing=1.0 / 32, object_id=1)
    right = block((0.50, 0.40, 0.05), (0.75, 0.65, 0.30), spacing=1.0 / 32, object_id=2)
    return combine([left, right])


def member(particles, families, overrides, velocity, *, ground_friction=0.3, terms=None):
    """Params of one member: families per object (may differ from the particles' own)."""
    parts = member_particles(
        particles,
        SimulationParams(
            {k: ObjectParams(f, {}) for k, f in families.items()}, {}, torch.tensor(0.0)
        ),
    )
    return default_params(
        parts,
        overrides=overrides,
        velocities={1: velocity, 2: (0.0, 0.0, 0.0)},
        ground_friction=ground_friction,
        terms=terms,
    )


def members(particles):
    return [
        member(particles, {1: "elastic", 2: "elastic"}, {1: {"E": 3e4}}, (1.5, 0.0, 0.0)),
        member(
            particles,
            {1: "plasticine", 2: "sand"},
            {1: {"E": 8e4, "yield_stress": 800.0}, 2: {"friction_angle": 40.0}},
            (2.0, 0.3, -0.5),
            ground_friction=0.6,
            terms={"linear_drag": {"coefficient": 0.5}, "material_damping": {"viscosity": 5.0}},
        ),
        member(
            particles,
            {1: "newtonian", 2: "snow"},
            {1: {"viscosity": 2.0}, 2: {"E": 2e4}},
            (1.0, -0.2, 0.0),
            ground_friction=0.1,
            terms={
                "ground_restitution": {"coefficient": 0.5},
                "wind": {"acceleration": [0.5, 0.0, 0.0]},
            },
        ),
    ]


def single(sim, particles, params, frames):
    with torch.no_grad():
        return sim.rollout(member_particles(particles, params), params, world=WORLD, frames=frames)


def assert_same(batched: Trajectory, alone: Trajectory) -> None:
    assert batched.positions.shape == alone.positions.shape
    assert torch.equal(batched.object_ids, alone.object_ids)
    # every frame, positions and velocities, each to its own tolerance
    assert (batched.positions - alone.positions).abs().max() <= POSITION_TOL
    assert (batched.velocities - alone.velocities).abs().max() <= VELOCITY_TOL


@pytest.mark.parametrize(
    ("count", "contact"), [(1, "multi_field"), (3, "multi_field"), (3, "single_field")]
)
def test_members_equal_their_single_rollouts(make_warp_simulator, count, contact) -> None:
    sim = make_warp_simulator(grid=16, substeps=20, contact=contact)
    particles = two_blocks()
    params_list = members(particles)[:count]
    with torch.no_grad():
        out = sim.rollout_batch(particles, params_list, world=WORLD, frames=3)
    assert len(out) == count
    for b, params in enumerate(params_list):
        alone = single(sim, particles, params, 3)
        assert isinstance(out[b], Trajectory), f"member {b}: {out[b]}"
        assert_same(out[b], alone)
    if count == 3:  # the members really differ: a shared or swapped table would show here
        spread = (out[0].positions[-1] - out[2].positions[-1]).abs().max()
        assert spread > 10 * POSITION_TOL
    # the run is reused by the next call of the same layout
    run = sim._batch_run
    with torch.no_grad():
        again = sim.rollout_batch(particles, params_list, world=WORLD, frames=3)
    assert sim._batch_run is run
    cuda = wp.get_device(sim.device).is_cuda  # trajectories come back on the host either way
    for a, b in zip(again, out):
        if cuda:  # CUDA's atomics sum P2G in another order every run
            assert (a.positions - b.positions).abs().max() <= POSITION_TOL
        else:
            assert torch.equal(a.positions, b.positions)


def test_a_diverging_member_is_reported_and_the_others_go_on(make_warp_simulator) -> None:
    sim = make_warp_simulator(grid=16, substeps=10)
    particles = two_blocks()
    good = members(particles)[0]
    bad = member(particles, {1: "elastic", 2: "elastic"}, {2: {"E": 1e9}}, (1.5, 0.0, 0.0))
    with torch.no_grad():
        out = sim.rollout_batch(particles, [good, bad, good], world=WORLD, frames=3)
    with pytest.raises(SimulationDiverged) as alone:
        single(sim, particles, bad, 3)
    err = out[1]
    assert isinstance(err, SimulationDiverged)
    expected = alone.value
    where = (expected.object_id, expected.frame, expected.substep)
    assert (err.object_id, err.frame, err.substep) == where
    assert err.reason == expected.reason
    reference = single(sim, particles, good, 3)
    for b in (0, 2):
        assert isinstance(out[b], Trajectory)
        assert_same(out[b], reference)


def test_no_members_and_bad_inputs(make_warp_simulator) -> None:
    from mosiv_framework.errors import ConfigError

    sim = make_warp_simulator(grid=16, substeps=10)
    particles = two_blocks()
    assert sim.rollout_batch(particles, [], world=WORLD, frames=2) == []
    broken = members(particles)[0]
    del broken.objects[2].values["E"]
    with pytest.raises(ConfigError, match="missing parameter 'E'"):
        sim.rollout_batch(particles, [members(particles)[0], broken], world=WORLD, frames=2)


#: relative difference allowed between a member's gradient and its single rollout's on a GPU,
#: where the adjoints' float32 atomics run in another order (on the CPU they agree bit for bit)
GRAD_RTOL_CUDA = 1e-3


def _leaves(params: SimulationParams) -> dict[str, torch.Tensor]:
    """The member's differentiable inputs: object 1's E (and yield stress where plastic),
    object 2's density and contact friction, the ground friction and object 1's initial
    velocity."""
    one, two = params.objects[1].values, params.objects[2].values
    leaves = {"E": one["E"], "rho": two["rho"], "v0": params.initial_velocity[1]}
    leaves["friction"] = two["friction"]
    if "yield_stress" in one:
        leaves["yield_stress"] = one["yield_stress"]
    leaves["ground_friction"] = params.ground_friction
    return {name: t.requires_grad_(True) for name, t in leaves.items()}


def _loss(traj: Trajectory, b: int) -> torch.Tensor:
    """A different readout per member, so a gradient sent to the wrong member would show."""
    return traj.positions[-1, :, b % 3].mean() + 0.3 * traj.positions[1:, :, 2].square().mean()


@pytest.mark.parametrize("window", ["whole", "particles"])
def test_gradients_of_the_batch_equal_each_members_own(make_warp_simulator, window) -> None:
    """Under autograd the batch is one simulation (no per-member loop), and each member's
    parameter gradients are those of its single differentiable rollout (bit for bit on the
    CPU), whether the grid kernels visit every node or only the box around the particles."""
    sim = make_warp_simulator(grid=16, substeps=10, grid_window=window)
    particles = two_blocks()
    params_list = members(particles)[:2]
    batch_leaves = [_leaves(p) for p in params_list]
    calls = []
    original = sim.rollout
    sim.rollout = lambda *a, **k: calls.append(1) or original(*a, **k)
    out = sim.rollout_batch(particles, params_list, world=WORLD, frames=2)
    sim.rollout = original
    assert not calls, "the batch fell back to one rollout per member"
    sum(_loss(traj, b) for b, traj in enumerate(out)).backward()
    cuda = wp.get_device(sim.device).is_cuda
    for b, params in enumerate(members(particles)[:2]):
        leaves = _leaves(params)
        alone = sim.rollout(member_particles(particles, params), params, world=WORLD, frames=2)
        _loss(alone, b).backward()
        for name, leaf in leaves.items():
            batched = batch_leaves[b][name].grad
            assert batched is not None and float(leaf.grad.abs().max()) > 0.0, (b, name)
            if cuda:
                assert torch.allclose(batched, leaf.grad, rtol=GRAD_RTOL_CUDA, atol=1e-9), name
            else:
                assert torch.equal(batched, leaf.grad), (b, name)


def test_gradients_stay_with_their_member(make_warp_simulator) -> None:
    """A loss on one member only leaves every other member's gradients at zero."""
    sim = make_warp_simulator(grid=16, substeps=10)
    particles = two_blocks()
    params_list = members(particles)[:2]
    leaves = [_leaves(p) for p in params_list]
    out = sim.rollout_batch(particles, params_list, world=WORLD, frames=2)
    _loss(out[0], 0).backward()
    assert float(leaves[0]["E"].grad.abs()) > 0.0
    for name, leaf in leaves[1].items():
        assert leaf.grad is None or float(leaf.grad.abs().max()) == 0.0, name


def test_a_diverging_member_under_autograd_is_reported_and_the_others_differentiate(
    make_warp_simulator,
) -> None:
    sim = make_warp_simulator(grid=16, substeps=10)
    particles = two_blocks()
    good = members(particles)[0]
    E = good.objects[1].values["E"].requires_grad_(True)
    bad = member(particles, {1: "elastic", 2: "elastic"}, {2: {"E": 1e9}}, (1.5, 0.0, 0.0))
    out = sim.rollout_batch(particles, [good, bad], world=WORLD, frames=3)
    assert isinstance(out[1], SimulationDiverged)
    assert isinstance(out[0], Trajectory)
    out[0].positions[-1, :, 0].mean().backward()
    assert float(E.grad.abs()) > 0.0


class FakeSimulator(Simulator):
    """Free flight of every particle at its object's initial velocity, damped by E; diverges
    when an object's E exceeds 1e8 (a stand-in for any backend without its own batching)."""

    supported_laws = frozenset({"elastic", "plasticine"})

    def rollout(self, particles, params, *, world, frames):
        if particles.materials != {k: p.family for k, p in params.objects.items()}:
            raise AssertionError("the member's families were not applied to its particles")
        for k, p in params.objects.items():
            if float(p.values["E"]) > 1e8:
                raise SimulationDiverged(
                    object_id=k, frame=1, substep=0, reason="too stiff", advice="lower E"
                )
        v = torch.stack([params.initial_velocity[int(k)] for k in particles.object_ids])
        E = torch.stack([params.objects[int(k)].values["E"] for k in particles.object_ids])
        t = torch.arange(frames + 1, dtype=torch.float32)[:, None, None] / world.fps
        positions = particles.positions + t * v / (1.0 + E[:, None] * 1e-5)
        return Trajectory(positions, particles.object_ids, world.fps)


def test_default_loop_equals_repeated_rollouts() -> None:
    sim = FakeSimulator()
    particles = two_blocks()
    params_list = [
        member(particles, {1: "elastic", 2: "elastic"}, {1: {"E": 3e4}}, (1.0, 0.0, 0.0)),
        member(particles, {1: "plasticine", 2: "elastic"}, {2: {"E": 1e9}}, (1.0, 0.0, 0.0)),
        member(particles, {1: "elastic", 2: "plasticine"}, {1: {"E": 9e4}}, (0.0, 2.0, 0.0)),
    ]
    out = sim.rollout_batch(particles, params_list, world=WORLD, frames=4)
    assert isinstance(out[1], SimulationDiverged) and out[1].object_id == 2
    for b in (0, 2):
        alone = sim.rollout(
            member_particles(particles, params_list[b]), params_list[b], world=WORLD, frames=4
        )
        assert torch.equal(out[b].positions, alone.positions)
    assert not torch.equal(out[0].positions, out[2].positions)


def test_bench_sim_batch_reports_both_sides(capsys) -> None:
    import json

    from mosiv_framework.cli.main import main

    argv = ["bench", "sim", "--backend", "warp-mpm", "--batch", "1", "3", "--particles", "64"]
    assert main([*argv, "--grid", "8", "--substeps", "2", "--frames", "1", "--json"]) == 0
    rows = json.loads(capsys.readouterr().out)
    assert [r["batch"] for r in rows] == [1, 3]
    for r in rows:
        work = r["particles"] * r["substeps"] * r["frames"] * r["batch"]
        assert r["batched_particle_substeps_per_s"] == pytest.approx(work / r["batched_s"])
        assert r["sequential_particle_substeps_per_s"] == pytest.approx(work / r["sequential_s"])
        assert r["gain"] == pytest.approx(r["sequential_s"] / r["batched_s"])
        assert r["max_rss_after_batched_bytes"] >= r["max_rss_after_sequential_bytes"] > 0


def test_bench_sim_passes_simulator_options(capsys, monkeypatch) -> None:
    """--sim-option reaches the simulator of both sides (here the grid window, recorded in the
    row); a pair without '=' is refused with the flag's expected form."""
    import json

    from mosiv_warp_mpm.simulator import WarpMPMSimulator

    from mosiv_framework.cli.main import main

    made = []
    original = WarpMPMSimulator.__init__

    def init(self, *args, **kwargs):
        original(self, *args, **kwargs)
        made.append(self.options.grid_window)

    monkeypatch.setattr(WarpMPMSimulator, "__init__", init)
    argv = ["bench", "sim", "--backend", "warp-mpm", "--batch", "2", "--particles", "64"]
    argv += ["--grid", "8", "--substeps", "2", "--frames", "1", "--json"]
    assert main([*argv, "--sim-option", "grid_window=whole"]) == 0
    rows = json.loads(capsys.readouterr().out)
    assert rows[0]["options"] == {"grid_window": "whole"} and made == ["whole"]
    assert main([*argv, "--sim-option", "grid_window"]) == 2
    assert "expected KEY=VALUE" in capsys.readouterr().err


def test_bench_sim_batch_with_gradients_times_forward_plus_backward(capsys) -> None:
    import json

    from mosiv_framework.cli.main import main

    argv = ["bench", "sim", "--backend", "warp-mpm", "--batch", "2", "--particles", "64"]
    argv += ["--grid", "8", "--substeps", "2", "--frames", "1", "--gradients", "--json"]
    assert main(argv) == 0
    (row,) = json.loads(capsys.readouterr().out)
    assert row["gradients"] is True and row["batch"] == 2
    work = row["particles"] * row["substeps"] * row["frames"] * row["batch"]
    assert row["batched_particle_substeps_per_s"] == pytest.approx(work / row["batched_s"])
    assert main(["bench", "sim", "--gradients"]) == 2
    assert "--gradients goes with --batch" in capsys.readouterr().err
