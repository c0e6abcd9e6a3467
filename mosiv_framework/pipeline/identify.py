"""Stage III: identify initial velocities, then per-object parameters, through the simulator.

Paper section 3.5: Adam on the initial velocity first, then on the continuous parameters of each
object's known family, minimising the recipe's losses over the observed frames with a horizon
curriculum, optionally interleaving the parameter steps with re-fits of the initial velocities
(``identify.resync_every``: the paper's alternating updates with re-synchronisation of the
particle state). Checkpointed every few iterations so an interrupted run resumes where it
stopped.
"""

from __future__ import annotations

import math
import re
from collections import deque
from dataclasses import dataclass

import torch
from tqdm import tqdm

from mosiv_framework.errors import ConfigError, SimulationDiverged
from mosiv_framework.losses import WeightedSum
from mosiv_framework.pipeline.params import ParameterVector
from mosiv_framework.pipeline.rundir import RunDir
from mosiv_framework.types import GeometryFrames, ParticleSet, Trajectory, World

CHECKPOINT = "identify/checkpoint.pt"
#: consecutive diverged rollouts tolerated, each stepping one accepted iterate further back and
#: halving the step size, before the phase stops at its best iterate
MAX_BACKOFFS = 6


@dataclass
class Phase:
    """One optimisation phase: its leaves' name, iterations, learning rate, ``first``, the
    horizon its curriculum starts from, and ``last``, the last frame it fits (the horizon the
    curriculum grows to)."""

    name: str
    iterations: int
    lr: float
    first: int
    last: int


def horizon(iteration: int, iterations: int, *, start: int, full_at: float, last: int) -> int:
    """Frames rolled out at ``iteration``: linear from ``start`` up to frame ``last``."""
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
    config_hash: str = "",
    velocity_frames: int | None = None,
) -> tuple[ParameterVector, list[dict]]:
    """Optimise ``vector`` in place; returns it and the per-iteration history.

    The velocity phase fits frames ``1..velocity_frames - 1`` (the free flight before any
    contact, whose motion does not depend on the unknown materials; default: all observed
    frames); the parameter phase fits every observed frame, its curriculum starting at the first
    frame after that free flight (earlier frames do not depend on any material parameter, so
    their gradients are round-off that Adam, being scale-free, would follow with full-size
    steps). A parameter whose gradient is exactly zero in a step (friction before any contact,
    a yield stress above every stress reached) holds still rather than coasting on Adam's
    momentum, and a non-finite gradient is treated like a diverged rollout: the step is taken
    back (one more accepted iterate back for each consecutive failure) and the learning rate
    halved; when ``MAX_BACKOFFS`` steps back all fail, the phase ends at its best iterate with a
    ``stopped_early`` record in the history. Each phase minimises its loss
    divided by the phase's first loss, so Adam's step sizes are the recipe's learning rates
    whatever the loss's unit or magnitude (Adam is invariant to a constant factor except for
    its epsilon, which would otherwise swamp gradients of m^2-sized Chamfer losses).
    A checkpoint is resumed only if it was written under the same ``config_hash`` (the
    fingerprint of everything identification depends on); otherwise it starts afresh.
    """
    if observed_frames < 2:
        raise ConfigError(f"identification needs at least 2 observed frames, got {observed_frames}")
    last = observed_frames - 1
    v_last = last if velocity_frames is None else max(1, min(last, velocity_frames - 1))
    # the targets move once to where the rollouts come back (the particles' device)
    targets = {k: t.to(particles.positions.device) for k, t in targets.items()}
    start = section.horizon_start
    # after a free-flight velocity phase, frames 1..v_last carry no material information
    param_start = max(start, v_last + 1) if velocity_frames is not None else start
    phases = [
        Phase("velocity", section.velocity_iterations, section.velocity_lr, start, v_last),
        Phase("params", section.param_iterations, section.param_lr, param_start, last),
    ]
    history: list[dict] = []
    start_phase, start_iter, opt_state = 0, 0, None
    ckpt = run_dir.load_torch(CHECKPOINT) if run_dir.path(CHECKPOINT).is_file() else None
    if ckpt is not None and ckpt.get("config") == config_hash:  # resume
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
        if phase.name == "velocity":
            named = {f"v0.obj{k}": v for k, v in vector.velocity.items()}
        else:
            named = dict(vector.normalized)
        leaves = list(named.values())
        if not leaves:
            continue
        optimizer = torch.optim.Adam(leaves, lr=phase.lr)
        # cosine decay to a tenth of the rate: big steps early, settling at the end
        schedule = torch.optim.lr_scheduler.LambdaLR(
            optimizer, lambda i, n=phase.iterations: 0.1 + 0.45 * (1 + math.cos(math.pi * i / n))
        )
        first, best = 0, _Best()
        if index == start_phase and opt_state is not None:
            optimizer.load_state_dict(opt_state["optimizer"])
            schedule.load_state_dict(opt_state["schedule"])
            best = _Best(opt_state["best_loss"], opt_state["best_leaves"])
            first = start_iter
            scale = opt_state.get("scale")
        else:
            scale = None
            # the start competes too: a phase never returns something worse than it was given
            # (Adam's first steps are about one learning rate long whatever the gradient, which
            # can throw an already good start, e.g. free-flight velocities, far off)
            best.offer(
                _window_loss(simulator, particles, vector, world, targets, phase.last, objective),
                vector,
            )
        bar = tqdm(range(first, phase.iterations), desc=f"identify {phase.name}", unit="it")
        # the iterates whose rollouts last succeeded, newest last: a divergence steps back one
        # of them per consecutive failure (the newest may itself diverge over the longer
        # horizon the curriculum has grown to since; a smaller step would not change that)
        trail: deque[_Best] = deque(maxlen=MAX_BACKOFFS)
        backoffs = 0
        for it in bar:
            h = horizon(
                it,
                phase.iterations,
                start=phase.first,
                full_at=section.horizon_full_at,
                last=phase.last,
            )
            if phase.name == "params" and _resync_due(it, section):
                before, after = resync_velocities(
                    simulator=simulator,
                    particles=particles,
                    vector=vector,
                    world=world,
                    targets=targets,
                    last=h,
                    objective=objective,
                    iterations=section.resync_iterations,
                    lr=section.velocity_lr,
                )
                history.append(
                    {
                        "phase": "resync",
                        "iteration": it,
                        "horizon": h,
                        "resync_loss_before": before,
                        "resync_loss_after": after,
                        "values": vector.to_json(),
                    }
                )
            optimizer.zero_grad()
            try:
                traj = simulator.rollout(particles, vector.physical(), world=world, frames=h)
                frames = list(range(1, h + 1))
                device = traj.positions.device
                target = geometry({k: t.to(device) for k, t in targets.items()}, frames)
                loss, terms = objective.evaluate(geometry(traj, frames), target)
                loss_value = float(loss.detach())
                if scale is None:  # the phase's first loss sets its unit (see the docstring)
                    scale = 1.0 / max(loss_value, 1e-30)
                (loss * scale).backward()
                _check_gradients(named, phase=phase.name, horizon=h)
            except SimulationDiverged as exc:
                # the last step went somewhere the simulator cannot follow (too stiff or too
                # soft for its substeps, or a gradient that overflowed): step back and take
                # smaller steps from there
                backoffs += 1
                where = f"{exc.reason} (identification, {phase.name} iteration {it})"
                if not trail and best.leaves is None:  # not one rollout of this phase worked
                    raise SimulationDiverged(
                        object_id=exc.object_id,
                        frame=exc.frame,
                        substep=exc.substep,
                        reason=where,
                        advice=f"{exc.advice} Or lower identify.{phase.name}_lr.",
                    ) from exc
                if not trail:
                    # every recent iterate fails at this horizon: keep the best one found so
                    # far and say so, rather than lose the run
                    history.append(
                        {
                            "phase": phase.name,
                            "iteration": it,
                            "horizon": h,
                            "stopped_early": f"{exc} after {backoffs - 1} steps back",
                            "values": vector.to_json(),
                        }
                    )
                    tqdm.write(
                        f"[identify] {phase.name} phase stopped at iteration {it}: {where}; "
                        f"{backoffs - 1} steps back did not help, keeping the best iterate"
                    )
                    break
                trail.pop().apply(vector)
                optimizer.zero_grad()
                # halve the schedule's base rate too, or its next step would undo the halving
                schedule.base_lrs = [lr * 0.5 for lr in schedule.base_lrs]
                for group in optimizer.param_groups:
                    group["lr"] *= 0.5
                history.append(
                    {
                        "phase": phase.name,
                        "iteration": it,
                        "horizon": h,
                        "diverged": str(exc),
                        "values": vector.to_json(),
                    }
                )
                continue
            backoffs = 0
            trail.append(_Best.snapshot(vector))  # the leaves this step starts from
            # gradients of the unscaled loss, per leaf, for the log
            grads = {
                n: float(leaf.grad.norm()) / scale
                for n, leaf in named.items()
                if leaf.grad is not None
            }
            grad_norm = math.sqrt(sum(g * g for g in grads.values()))
            if h == phase.last:  # only losses over the phase's whole window are comparable
                best.offer(loss_value, vector)
            for leaf in leaves:  # no evidence this step: Adam skips a leaf without a gradient
                if leaf.grad is not None and not bool(leaf.grad.any()):
                    leaf.grad = None
            optimizer.step()
            schedule.step()
            with torch.no_grad():  # keep normalised coordinates inside their bounds
                for u in vector.normalized.values():
                    u.clamp_(0.0, 1.0)
            history.append(
                {
                    "phase": phase.name,
                    "iteration": it,
                    "horizon": h,
                    "loss": loss_value,
                    "terms": terms,
                    "grad_norm": grad_norm,
                    "grads": grads,
                    "lr": optimizer.param_groups[0]["lr"],
                    "values": vector.to_json(),
                }
            )
            bar.set_postfix(loss=f"{loss_value:.3e}", h=h)
            if (it + 1) % max(1, section.checkpoint_every) == 0 and it + 1 < phase.iterations:
                resume = {
                    "optimizer": optimizer.state_dict(),
                    "schedule": schedule.state_dict(),
                    "best_loss": best.loss,
                    "best_leaves": best.leaves,
                    "scale": scale,
                }
                _save_checkpoint(run_dir, config_hash, index, it + 1, history, resume, vector)
        # end of phase (also when its last iteration diverged): keep the best iterate
        best.apply(vector)
        _save_checkpoint(run_dir, config_hash, index + 1, 0, history, None, vector)
        opt_state = None
    return vector, history


def gradients_finite(leaves) -> bool:
    """Whether every gradient the leaves hold is finite (leaves without one count as finite)."""
    return all(bool(torch.isfinite(leaf.grad).all()) for leaf in leaves if leaf.grad is not None)


def _check_gradients(named: dict[str, torch.Tensor], *, phase: str, horizon: int) -> None:
    """Raise SimulationDiverged naming the leaves whose gradient is not finite (NaN or inf
    would otherwise enter Adam's state and every later step)."""
    bad = [name for name, leaf in named.items() if not gradients_finite([leaf])]
    if bad:
        owner = re.search(r"obj(\d+)", bad[0])
        raise SimulationDiverged(
            object_id=int(owner.group(1)) if owner else 0,
            frame=horizon,
            substep=0,
            reason=f"non-finite gradient of {', '.join(bad)} in the backward pass over frames "
            f"1..{horizon} ({phase})",
            advice="",
        )


def _resync_due(iteration: int, section) -> bool:
    every = int(getattr(section, "resync_every", 0) or 0)
    return every > 0 and iteration > 0 and iteration % every == 0


def resync_velocities(
    *, simulator, particles, vector, world, targets, last, objective, iterations: int, lr: float
) -> tuple[float, float]:
    """Re-fit the initial velocities to frames 1..last with the parameters held: a few Adam
    steps of their own (scale-free, as in ``identify``), keeping the best iterate, the start
    included, so a re-synchronisation never raises the loss. Returns (loss before, after);
    inf for both if the very first rollout diverges (nothing is changed then)."""
    frames = list(range(1, last + 1))
    best, start = _Best(), math.inf
    leaves = list(vector.velocity.values())
    optimizer = torch.optim.Adam(leaves, lr=lr)
    for step in range(iterations + 1):  # the last pass only scores the last step's iterate
        optimizer.zero_grad()
        try:
            traj = simulator.rollout(particles, vector.physical(), world=world, frames=last)
        except SimulationDiverged:
            break  # the best iterate so far stands
        device = traj.positions.device
        target = geometry({k: t.to(device) for k, t in targets.items()}, frames)
        loss = objective(geometry(traj, frames), target)
        value = float(loss.detach())
        start = value if step == 0 else start
        best.offer(value, vector)
        if step == iterations:
            break
        (loss / max(value, 1e-30)).backward()
        if not gradients_finite(leaves):
            break  # a non-finite gradient: the best iterate so far stands
        optimizer.step()
    best.apply(vector)
    for leaf in leaves:  # the parameter phase's next step starts from clean gradients
        leaf.grad = None
    return start, best.loss


def _window_loss(simulator, particles, vector, world, targets, last, objective) -> float:
    """The objective over frames 1..last for the current leaves, without a tape."""
    frames = list(range(1, last + 1))
    with torch.no_grad():
        traj = simulator.rollout(particles, vector.physical(), world=world, frames=last)
        device = traj.positions.device
        target = geometry({k: t.to(device) for k, t in targets.items()}, frames)
        return float(objective(geometry(traj, frames), target))


def _save_checkpoint(run_dir, config_hash, phase, iteration, history, resume, vector) -> None:
    run_dir.save_torch(
        CHECKPOINT,
        {
            "config": config_hash,
            "phase": phase,
            "iteration": iteration,
            "history": history,
            "optimizer": resume,
            "velocity": {k: v.detach().clone() for k, v in vector.velocity.items()},
            "normalized": {k: u.detach().clone() for k, u in vector.normalized.items()},
        },
    )


class _Best:
    """The lowest full-horizon loss seen in a phase and the leaves that gave it.

    Adam on a noisy (subsampled) objective wanders around the optimum; returning the best
    iterate rather than the last makes the result independent of where it stopped.
    """

    def __init__(self, loss: float = math.inf, leaves: dict | None = None):
        self.loss, self.leaves = loss, leaves

    def offer(self, loss: float, vector: ParameterVector) -> None:
        if loss < self.loss:
            self.loss = loss
            self.leaves = {
                "velocity": {k: v.detach().clone() for k, v in vector.velocity.items()},
                "normalized": {k: u.detach().clone() for k, u in vector.normalized.items()},
            }

    @classmethod
    def snapshot(cls, vector: ParameterVector) -> _Best:
        """A copy of the current leaves (to step back to)."""
        best = cls()
        best.offer(-math.inf, vector)
        return best

    def apply(self, vector: ParameterVector) -> None:
        if self.leaves is None:
            return
        with torch.no_grad():
            for k, v in self.leaves["velocity"].items():
                vector.velocity[k].copy_(v)
            for k, u in self.leaves["normalized"].items():
                vector.normalized[k].copy_(u)
