"""Batched forward rollouts: B parameter sets ("members") of one scene in the same launches.

The B members' particles form one array of B N particles, member-major, each in the scatter
order of a single rollout; particle p of member b carries object index b K + k, so the object
tables hold B K rows and the grid holds B grids one after the other (kernels.py, batched
rollouts). Every substep is then the single rollout's four launches over all B N particles and
B grids, and nothing of one member reaches another member's grid: member b's rollout is the
single rollout of its parameters, to float32 round-off (on the CPU, where Warp runs the threads
in order, bit for bit; on a GPU the atomic sums of P2G run in another order).

A member that diverges keeps being simulated (the kernels reset its non-finite particles, see
transfer_kernels.g2p_fused, so its state stays on its own grid) but its result is the
SimulationDiverged of its first flagged frame; the rollout stops early when every member has
diverged.

Under autograd, with a parameter or the positions requiring gradients, the batch runs through
the same torch.autograd.Function as a single rollout (autograd.WarpRollout): its backward
replays all members' frames at once, the per-object and per-member parameter sums already keep
the members apart. If a member diverges there, the call rolls the members out one by one
instead, so that each diverged member gets its own SimulationDiverged and the others their
trajectories, as in the forward-only batch.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
import warp as wp

from mosiv_framework.errors import SimulationDiverged
from mosiv_framework.interfaces import Simulator, member_particles
from mosiv_framework.particle_order import ScatterOrdered
from mosiv_framework.types import ParticleSet, SimulationParams, Trajectory, World
from mosiv_warp_mpm.packing import check_inputs, initial_velocities, pack_theta
from mosiv_warp_mpm.run import MPMRun
from mosiv_warp_mpm.simulator import WarpMPMSimulator


def rollout_batch(
    sim: WarpMPMSimulator,
    particles: ParticleSet,
    params_list: Sequence[SimulationParams],
    *,
    world: World,
    frames: int,
) -> list[Trajectory | SimulationDiverged]:
    """``Simulator.rollout_batch`` for warp-mpm: all members in one simulation.

    Args:
        sim: the simulator (its options, device and cached batched run).
        particles: the scene's particles; member b simulates them with the families of
            ``params_list[b]``.
        params_list: one SimulationParams per member (B >= 0).
        world, frames: as for ``rollout``.

    Returns:
        Per member, its Trajectory (frames + 1 states, positions and velocities on the
        particles' device, in their order) or the SimulationDiverged that stopped it.
    """
    members = [member_particles(particles, p) for p in params_list]
    for member, params in zip(members, params_list):
        check_inputs(member, params, world, frames, contact=sim.options.contact)
    if not params_list:
        return []
    if _needs_grad(particles, params_list):
        return _differentiable_batch(sim, particles, params_list, world=world, frames=frames)
    layout, ids, ordered = sim.scatter_layout(particles, world)
    x0s, obj_index, volumes = ordered.positions, ordered.obj_index, ordered.volumes
    run = _batch_run(sim, params_list, layout, world, ids, obj_index, volumes, grad=False)
    with torch.no_grad():
        v0, theta = _member_inputs(params_list, ids, obj_index, world, x0s.device)
        pos, vel, errors = forward_batch(run, x0s.repeat(len(params_list), 1), v0, theta, frames)
    return _split_members(pos, vel, errors, particles, ordered, world)


def _differentiable_batch(
    sim: WarpMPMSimulator,
    particles: ParticleSet,
    params_list: Sequence[SimulationParams],
    *,
    world: World,
    frames: int,
) -> list[Trajectory | SimulationDiverged]:
    """The batch as one differentiable simulation (autograd.WarpRollout on a run of B
    members); the members one by one where one of them diverges."""
    from mosiv_warp_mpm.autograd import WarpRollout  # autograd imports run, as this does

    layout, ids, ordered = sim.scatter_layout(particles, world)
    x0s, obj_index, volumes = ordered.positions, ordered.obj_index, ordered.volumes
    run = _batch_run(sim, params_list, layout, world, ids, obj_index, volumes, grad=True)
    v0, theta = _member_inputs(params_list, ids, obj_index, world, x0s.device)
    try:
        pos, vel = WarpRollout.apply(run, sim, frames, x0s.repeat(len(params_list), 1), v0, theta)
    except SimulationDiverged:
        # which members diverged, where and why, is what the one-by-one loop reports
        return Simulator.rollout_batch(sim, particles, params_list, world=world, frames=frames)
    return _split_members(pos, vel, [None] * len(params_list), particles, ordered, world)


def _batch_run(sim, params_list, layout, world, ids, obj_index, volumes, *, grad: bool) -> MPMRun:
    """The simulator's batched run for these members, made anew where the layout, families or
    batch size changed (or, for ``grad``, where the run still awaits a backward pass)."""
    batch, k = len(params_list), len(ids)
    families = [params.objects[i].family for params in params_list for i in ids]
    member_obj = torch.cat([obj_index + b * k for b in range(batch)])
    member_vol = volumes.repeat(batch)
    n = obj_index.shape[0]
    key = (layout, world, sim.options.substeps, tuple(ids), tuple(families), n, batch)
    run = sim._grad_batch_run if grad else sim._batch_run
    stale = sim._grad_batch_key != key if grad else sim._batch_key != key
    if run is None or stale or (grad and run.awaiting_backward):
        run = sim._new_run(layout, world, ids, families, member_obj, member_vol, batch=batch)
        if grad:
            sim._grad_batch_run, sim._grad_batch_key = run, key
        else:
            sim._batch_run, sim._batch_key = run, key
    else:
        run.refresh(member_obj, member_vol)
    return run


def _member_inputs(params_list, ids, obj_index, world, device) -> tuple[torch.Tensor, torch.Tensor]:
    """Initial velocities [B N, 3] (member-major, scatter order) and packed parameters [B, P]."""
    v0 = torch.cat([initial_velocities(p, ids, obj_index) for p in params_list])
    theta = torch.stack([pack_theta(p, ids, world.gravity, device) for p in params_list])
    return v0, theta


def _split_members(
    pos, vel, errors, particles: ParticleSet, ordered: ScatterOrdered, world: World
) -> list:
    """Per member its Trajectory (in the caller's particle order, on its device), or its
    SimulationDiverged."""
    n, out_dev = ordered.order.shape[0], particles.positions.device
    results: list[Trajectory | SimulationDiverged] = []
    for b, err in enumerate(errors):
        if err is not None:
            results.append(err)
            continue
        rows = slice(b * n, (b + 1) * n)
        results.append(
            Trajectory(
                positions=ordered.to_caller(pos[:, rows]).to(out_dev),
                object_ids=particles.object_ids,
                fps=world.fps,
                velocities=ordered.to_caller(vel[:, rows].detach()).to(out_dev),
            )
        )
    return results


def _needs_grad(particles: ParticleSet, params_list: Sequence[SimulationParams]) -> bool:
    if not torch.is_grad_enabled():
        return False
    tensors = [t for p in params_list for _, t in p.named_tensors()]
    return particles.positions.requires_grad or any(t.requires_grad for t in tensors)


def forward_batch(
    run: MPMRun, x0: torch.Tensor, v0: torch.Tensor, theta: torch.Tensor, frames: int
) -> tuple[torch.Tensor, torch.Tensor, list[SimulationDiverged | None]]:
    """Roll all members of ``run`` out for ``frames`` frames.

    Args:
        run: an MPMRun made with batch = B.
        x0, v0: [B N, 3] initial positions and velocities, member-major, scatter order.
        theta: [B, P] packed parameters, one row per member (pack_theta).
        frames: video frames after frame 0.

    Returns:
        positions and velocities [frames + 1, B N, 3] (frames after the last member diverged
        are left unfilled) and, per member, the SimulationDiverged of its first flagged frame
        or None.
    """
    run.tables.load(theta)
    run.a.set_initial(x0, v0)
    dev = wp.device_to_torch(run.device)
    pos = torch.empty(frames + 1, run.n, 3, device=dev)
    vel = torch.empty(frames + 1, run.n, 3, device=dev)
    pos[0], vel[0] = wp.to_torch(run.a.x), wp.to_torch(run.a.v)
    errors: list[SimulationDiverged | None] = [None] * run.batch
    for f in range(1, frames + 1):
        run.advance_frame(f, check=False)
        for b, err in enumerate(run.divergences(f)):
            if err is not None and errors[b] is None:
                errors[b] = err
        pos[f], vel[f] = wp.to_torch(run.a.x), wp.to_torch(run.a.v)
        run._sample_memory()
        if all(e is not None for e in errors):
            break
    return pos, vel, errors
