"""Batched forward rollouts: B parameter sets ("members") of one scene in the same launches.

The B members' particles form one array of B N particles, member-major, each in the scatter
order of a single rollout; particle p of member b carries object index b K + k, so the object
tables hold B K rows and the grid holds B grids one after the other (kernels.py, batched
rollouts). Every substep is then the single rollout's four launches over all B N particles and
B grids, and nothing of one member reaches another member's grid: member b's rollout is the
single rollout of its parameters, to float32 round-off (on the CPU, where Warp runs the threads
in order, bit for bit; on a GPU the atomic sums of P2G run in another order).

A member that diverges keeps being simulated (the kernels reset its non-finite particles, see
kernels.g2p, so its state stays on its own grid) but its result is the SimulationDiverged of its
first flagged frame; the rollout stops early when every member has diverged.

Forward only: when autograd is on and a parameter requires gradients, the call falls back to
the base class's loop over the differentiable ``rollout``.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
import warp as wp

from mosiv_framework.errors import SimulationDiverged
from mosiv_framework.interfaces import Simulator, member_particles
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
        return Simulator.rollout_batch(sim, particles, params_list, world=world, frames=frames)

    layout, ids, x0s, obj_index, volumes, inverse = sim.scatter_layout(particles, world)
    dev, batch, n, k = x0s.device, len(params_list), x0s.shape[0], len(ids)
    families = [params.objects[i].family for params in params_list for i in ids]
    member_obj = torch.cat([obj_index + b * k for b in range(batch)])
    member_vol = volumes.repeat(batch)
    key = (layout, world, sim.options.substeps, tuple(ids), tuple(families), n, batch)
    run = sim._batch_run
    if run is None or sim._batch_key != key:
        run = sim._new_run(layout, world, ids, families, member_obj, member_vol, batch=batch)
        sim._batch_run, sim._batch_key = run, key
    else:
        run.refresh(member_obj, member_vol)

    with torch.no_grad():
        v0 = torch.cat([initial_velocities(p, ids, obj_index) for p in params_list])
        theta = torch.stack([pack_theta(p, ids, world.gravity, dev) for p in params_list])
        pos, vel, errors = forward_batch(run, x0s.repeat(batch, 1), v0, theta, frames)

    out_dev = particles.positions.device
    results: list[Trajectory | SimulationDiverged] = []
    for b, err in enumerate(errors):
        if err is not None:
            results.append(err)
            continue
        rows = slice(b * n, (b + 1) * n)
        results.append(
            Trajectory(
                positions=pos[:, rows][:, inverse].to(out_dev),
                object_ids=particles.object_ids,
                fps=world.fps,
                velocities=vel[:, rows][:, inverse].to(out_dev),
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
