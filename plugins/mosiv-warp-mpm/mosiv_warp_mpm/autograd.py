"""Gradients of a rollout as a torch.autograd.Function, with memory bounded by frames.

Forward keeps one particle state per frame boundary (no tape). Backward walks the frames from
last to first; for each frame it re-simulates the frame from its checkpoint into per-substep
state buffers, then replays the substeps in reverse, each under its own short Warp tape, carrying
the adjoint of the particle state. Because each substep writes a fresh state buffer and each
tape is consumed before the shared grid is reused, nothing a tape recorded is overwritten before
its adjoint runs. Memory: checkpoints grow with frames; the workspace (substeps + 1 particle
states and one grid) is the same for every frame and does not grow with the number of frames.
"""

from __future__ import annotations

import torch
import warp as wp

from mosiv_warp_mpm.state import Grid, ParticleState


class WarpRollout(torch.autograd.Function):
    """(x0 [N,3], v0 [N,3], theta [P]) -> (positions [T+1,N,3], velocities [T+1,N,3])."""

    @staticmethod
    def forward(ctx, run, simulator, frames: int, x0, v0, theta):
        pos, vel = run.forward(x0, v0, theta, frames, keep=True)
        ctx.run, ctx.simulator, ctx.frames = run, simulator, frames
        ctx.theta_device = theta.device
        simulator.last_memory = {"checkpoint_bytes": run.checkpoint_bytes()}
        ctx.mark_non_differentiable(vel)
        return pos, vel

    @staticmethod
    def backward(ctx, grad_pos, grad_vel):
        run = ctx.run
        n, S, dev = run.n, run.substeps, run.device
        work = [ParticleState(n, dev, requires_grad=True) for _ in range(S + 1)]
        grid = Grid(run.layout, dev, requires_grad=True)
        carry = ParticleState(n, dev, requires_grad=True)
        run.tables.zero_grad()
        if grad_pos is None:
            grad_pos = torch.zeros(ctx.frames + 1, n, 3, device=wp.device_to_torch(dev))
        grad_pos = grad_pos.to(wp.device_to_torch(dev), torch.float32)
        carry_x = wp.to_torch(carry.x.grad)
        for f in range(ctx.frames, 0, -1):
            carry_x += grad_pos[f]
            backward_frame(run, run.checkpoints[f - 1], carry, work, grid, frame=f)
            carry.copy_grad_from(work[0])
        carry_x += grad_pos[0]
        ctx.simulator.last_memory["backward_workspace_bytes"] = sum(w.nbytes() for w in work) + sum(
            a.capacity * 2 for a in grid.arrays()
        )
        run._sample_memory()
        grad_x0 = wp.to_torch(carry.x.grad).clone()
        grad_v0 = wp.to_torch(carry.v.grad).clone()
        grad_theta = run.tables.grad_theta().to(ctx.theta_device)
        run.checkpoints = []  # free the checkpoints once the backward has used them
        return None, None, None, grad_x0, grad_v0, grad_theta


def backward_frame(run, start: ParticleState, carry: ParticleState, work, grid: Grid, *, frame):
    """Adjoint of one frame: work[0].grad <- d(loss)/d(state at frame start), given carry.grad
    = d(loss)/d(state at frame end); parameter gradients accumulate in run.tables."""
    S = run.substeps
    work[0].copy_from(start)
    run.flag.fill_(2**30)
    for s in range(S):  # re-simulate the frame, keeping every substep's state
        grid.clear()
        run.substep(work[s], work[s + 1], grid, s)
    run.check_divergence(frame)
    work[S].copy_grad_from(carry)
    for s in range(S - 1, -1, -1):
        work[s].zero_grad()
        grid.zero_grad()
        grid.clear()
        tape = wp.Tape()
        with tape:
            run.substep(work[s], work[s + 1], grid, s)
        tape.backward()  # no tape.reset(): it would zero every gradient, parameters included
