"""Stage III: identify initial velocities, then per-object parameters, through the simulator.

Paper section 3.5: Adam on the initial velocity first, then on the continuous parameters of each
object's known family, minimising the recipe's losses over the observed frames with a horizon
curriculum. Checkpointed every few iterations so an interrupted run resumes where it stopped.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from tqdm import tqdm

from mosiv_framework.errors import ConfigError
from mosiv_framework.losses import WeightedSum
from mosiv_framework.pipeline.params import ParameterVector
from mosiv_framework.pipeline.rundir import RunDir
from mosiv_framework.types import GeometryFrames, ParticleSet, Trajectory, World

CHECKPOINT = "identify/checkpoint.pt"


@dataclass
class Phase:
    name: str
    iterations: int
    lr: float


def horizon(iteration: int, iterations: int, *, start: int, full_at: float, observed: int) -> int:
    """Frames rolled out at ``iteration``: linear from ``start`` to all observed frames."""
    last = observed - 1
    ramp = max(1, math.ceil(full_at * iterations))
    h = start + (last - start) * min(1.0, iteration / ramp)
    return int(max(1, min(last, round(h))))


def geometry(traj_or_points, frames: list[int]) -> GeometryFrames:
    """Per-object point sets at ``frames`` from a Trajectory or an id -> [T, N, 3] mapping."""
    if isinstance(traj_or_points, Trajectory):
        ids = sorted(int(k) for k in traj_or_points.object_ids.unique().tolist())
        per_object = {k: traj_or_points.object_positions(k) for k in ids}
    else:
        per_object = traj_or_points
    return GeometryFrames(frames, {k: [pts[f] for f in frames] for k, pts in per_object.items()})


def identify(
    *,
    simulator,
    particles: ParticleSet,
    world: World,
    targets: dict[int, torch.Tensor],
    observed_frames: int,
    objective: WeightedSum,
    vector: ParameterVector,
    section,
    run_dir: RunDir,
) -> tuple[ParameterVector, list[dict]]:
    """Optimise ``vector`` in place; returns it and the per-iteration history."""
    if observed_frames < 2:
        raise ConfigError(f"identification needs at least 2 observed frames, got {observed_frames}")
    phases = [
        Phase("velocity", section.velocity_iterations, section.velocity_lr),
        Phase("params", section.param_iterations, section.param_lr),
    ]
    history: list[dict] = []
    start_phase, start_iter, opt_state = 0, 0, None
    if run_dir.path(CHECKPOINT).is_file():  # resume
        ckpt = run_dir.load_torch(CHECKPOINT)
        start_phase, start_iter, history = ckpt["phase"], ckpt["iteration"], ckpt["history"]
        opt_state = ckpt["optimizer"]
        with torch.no_grad():
            for k, v in ckpt["velocity"].items():
                vector.velocity[k].copy_(v)
            for key, u in ckpt["normalized"].items():
                vector.normalized[key].copy_(u)

    for index, phase in enumerate(phases):
        if index < start_phase or phase.iterations == 0:
            continue
        leaves = (
            list(vector.velocity.values())
            if phase.name == "velocity"
            else list(vector.normalized.values())
        )
        if not leaves:
            continue
        optimizer = torch.optim.Adam(leaves, lr=phase.lr)
        first = 0
        if index == start_phase and opt_state is not None:
            optimizer.load_state_dict(opt_state)
            first = start_iter
        bar = tqdm(
            range(first, phase.iterations), desc=f"identify {phase.name}", unit="it", leave=False
        )
        for it in bar:
            h = horizon(
                it,
                phase.iterations,
                start=section.horizon_start,
                full_at=section.horizon_full_at,
                observed=observed_frames,
            )
            optimizer.zero_grad()
            traj = simulator.rollout(particles, vector.physical(), world=world, frames=h)
            frames = list(range(1, h + 1))
            device = traj.positions.device
            target = geometry({k: t.to(device) for k, t in targets.items()}, frames)
            loss, terms = objective.evaluate(geometry(traj, frames), target)
            loss.backward()
            grad_norm = float(
                torch.sqrt(sum((leaf.grad**2).sum() for leaf in leaves if leaf.grad is not None))
            )
            optimizer.step()
            with torch.no_grad():  # keep normalised coordinates inside their bounds
                for u in vector.normalized.values():
                    u.clamp_(0.0, 1.0)
            history.append(
                {
                    "phase": phase.name,
                    "iteration": it,
                    "horizon": h,
                    "loss": float(loss),
                    "terms": terms,
                    "grad_norm": grad_norm,
                    "values": vector.to_json(),
                }
            )
            bar.set_postfix(loss=f"{float(loss):.3e}", h=h)
            if (it + 1) % max(1, section.checkpoint_every) == 0 or it + 1 == phase.iterations:
                nxt_phase, nxt_iter = (
                    (index, it + 1) if it + 1 < phase.iterations else (index + 1, 0)
                )
                run_dir.save_torch(
                    CHECKPOINT,
                    {
                        "phase": nxt_phase,
                        "iteration": nxt_iter,
                        "history": history,
                        "optimizer": optimizer.state_dict() if nxt_iter else None,
                        "velocity": {k: v.detach().clone() for k, v in vector.velocity.items()},
                        "normalized": {k: u.detach().clone() for k, u in vector.normalized.items()},
                    },
                )
        opt_state = None
    return vector, history
