"""The phases of identification and what they share: each phase says which leaves it fits, over
which frames, and what it does before a step; ``mosiv_framework.pipeline.identify`` runs them.

- ``VelocityPhase``: the initial velocities, over the free flight before any contact (or every
  observed frame), whose motion does not depend on the unknown materials.
- ``ParameterPhase``: the normalised law parameters over every observed frame, optionally
  re-fitting the initial velocities every ``identify.resync_every`` steps (the paper's
  alternating updates with re-synchronisation of the particle state).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from mosiv_framework.errors import ConfigError, SimulationDiverged
from mosiv_framework.losses import WeightedSum
from mosiv_framework.pipeline.params import ParameterVector
from mosiv_framework.types import GeometryFrames, ParticleSet, SimulationParams, Trajectory, World

#: parameter sets ``Fit.window_losses`` rolls out in one ``rollout_batch`` call: each member
#: carries its own grid, so a bound keeps a search's memory that of 16 rollouts
BATCH_MEMBERS = 16


def batched_losses(
    simulator,
    particles: ParticleSet,
    params_list: list[SimulationParams],
    *,
    world: World,
    frames: int,
    loss,
) -> list[float]:
    """``loss`` of each parameter set's rollout, the sets rolled out together without a tape.

    Args:
        simulator: a Simulator; its ``rollout_batch`` gets at most ``BATCH_MEMBERS`` sets a
            call (one simulation on backends that batch, e.g. warp-mpm).
        particles, world, frames: as for ``rollout_batch``.
        params_list: the parameter sets (members), independent of each other.
        loss: the Trajectory -> float to score each member's rollout with.

    Returns:
        One loss per set, in order: ``inf`` for a set whose rollout diverged (the others still
        run) or whose loss is not finite.
    """
    losses: list[float] = []
    with torch.no_grad():
        for start in range(0, len(params_list), BATCH_MEMBERS):
            chunk = params_list[start : start + BATCH_MEMBERS]
            results = simulator.rollout_batch(particles, chunk, world=world, frames=frames)
            for result in results:
                value = math.inf if isinstance(result, SimulationDiverged) else float(loss(result))
                losses.append(value if math.isfinite(value) else math.inf)
    return losses


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


def gradients_finite(leaves) -> bool:
    """Whether every gradient the leaves hold is finite (leaves without one count as finite)."""
    return all(bool(torch.isfinite(leaf.grad).all()) for leaf in leaves if leaf.grad is not None)


@dataclass
class Fit:
    """What every phase fits against: the simulator rolling ``particles`` out in ``world``, the
    per-object ``targets`` (on the particles' device) and the recipe's ``objective``."""

    simulator: object
    particles: ParticleSet
    world: World
    targets: dict[int, torch.Tensor]
    objective: WeightedSum

    def rollout_geometry(self, vector: ParameterVector, last: int):
        """(predicted, target) GeometryFrames over frames 1..last for the current leaves."""
        traj = self.simulator.rollout(
            self.particles, vector.physical(), world=self.world, frames=last
        )
        frames = list(range(1, last + 1))
        device = traj.positions.device
        target = geometry({k: t.to(device) for k, t in self.targets.items()}, frames)
        return geometry(traj, frames), target

    def window_loss(self, vector: ParameterVector, last: int) -> float:
        """The objective over frames 1..last for the current leaves, without a tape."""
        with torch.no_grad():
            return float(self.objective(*self.rollout_geometry(vector, last)))

    def window_losses(self, params_list: list[SimulationParams], last: int) -> list[float]:
        """The objective over frames 1..last for each parameter set, without a tape, the sets
        rolled out together (``Simulator.rollout_batch``, at most ``BATCH_MEMBERS`` at a time:
        one simulation on backends that batch, e.g. warp-mpm). ``inf`` for a set the simulator
        could not follow or whose loss is not finite. Equal to ``window_loss`` of each set to
        float32 round-off (bit for bit on warp-mpm's CPU path)."""
        frames = list(range(1, last + 1))
        target = None

        def loss(result: Trajectory) -> float:
            nonlocal target
            if target is None:  # on the rollouts' device, made once
                device = result.positions.device
                target = geometry({k: t.to(device) for k, t in self.targets.items()}, frames)
            return float(self.objective(geometry(result, frames), target))

        return batched_losses(
            self.simulator, self.particles, params_list, world=self.world, frames=last, loss=loss
        )


class BestIterate:
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
    def snapshot(cls, vector: ParameterVector) -> BestIterate:
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

    def leaves(self, vector: ParameterVector) -> dict[str, torch.Tensor]:
        """The tensors this phase optimises, by the name the history logs them under."""
        # abstract: every phase (VelocityPhase, ParameterPhase) names its own leaves; a Phase
        # itself is only the shared record of iterations, rate and curriculum
        raise NotImplementedError

    def before_iteration(
        self, iteration: int, h: int, fit: Fit, vector: ParameterVector, history: list[dict]
    ) -> None:
        """Work due before the step of ``iteration`` at horizon ``h`` (none by default)."""


class VelocityPhase(Phase):
    def leaves(self, vector: ParameterVector) -> dict[str, torch.Tensor]:
        return {f"v0.obj{k}": v for k, v in vector.velocity.items()}


@dataclass
class ParameterPhase(Phase):
    """The law parameters; every ``resync_every`` steps (0: never) the initial velocities are
    re-fitted first, ``resync_iterations`` Adam steps at ``resync_lr``."""

    resync_every: int = 0
    resync_iterations: int = 0
    resync_lr: float = 0.0

    def leaves(self, vector: ParameterVector) -> dict[str, torch.Tensor]:
        return dict(vector.normalized)

    def before_iteration(
        self, iteration: int, h: int, fit: Fit, vector: ParameterVector, history: list[dict]
    ) -> None:
        every = self.resync_every
        if not (every > 0 and iteration > 0 and iteration % every == 0):
            return
        before, after = resync_velocities(
            simulator=fit.simulator,
            particles=fit.particles,
            vector=vector,
            world=fit.world,
            targets=fit.targets,
            last=h,
            objective=fit.objective,
            iterations=self.resync_iterations,
            lr=self.resync_lr,
        )
        history.append(
            {
                "phase": "resync",
                "iteration": iteration,
                "horizon": h,
                "resync_loss_before": before,
                "resync_loss_after": after,
                "values": vector.to_json(),
            }
        )


def build_phases(section, *, observed_frames: int, velocity_frames: int | None) -> list[Phase]:
    """The velocity phase, then the parameter phase, as ``section`` (identify) configures them.

    The velocity phase fits frames 1..velocity_frames - 1 (default: every observed frame); after
    a free-flight velocity phase those frames carry no material information, so the parameter
    phase's curriculum starts at the first frame after them. ``identify.holdout_frames`` ends
    the parameter phase that many frames before the last observed one (ConfigError when no
    frame after its start would be left)."""
    last = observed_frames - 1
    v_last = last if velocity_frames is None else max(1, min(last, velocity_frames - 1))
    start = section.horizon_start
    param_start = max(start, v_last + 1) if velocity_frames is not None else start
    holdout = int(getattr(section, "holdout_frames", 0) or 0)
    if holdout and last - holdout < param_start:
        raise ConfigError(
            f"identify.holdout_frames={holdout}: the parameter phase would fit frames "
            f"{param_start}..{last - holdout} of the {observed_frames} observed; hold out at "
            f"most {max(0, last - param_start)}"
        )
    return [
        VelocityPhase("velocity", section.velocity_iterations, section.velocity_lr, start, v_last),
        ParameterPhase(
            "params",
            section.param_iterations,
            section.param_lr,
            param_start,
            last - holdout,
            resync_every=int(getattr(section, "resync_every", 0) or 0),
            resync_iterations=getattr(section, "resync_iterations", 0),
            resync_lr=section.velocity_lr,
        ),
    ]


def resync_velocities(
    *, simulator, particles, vector, world, targets, last, objective, iterations: int, lr: float
) -> tuple[float, float]:
    """Re-fit the initial velocities to frames 1..last with the parameters held: a few Adam
    steps of their own (scale-free, as in ``identify``), keeping the best iterate, the start
    included, so a re-synchronisation never raises the loss. Returns (loss before, after);
    inf for both if the very first rollout diverges (nothing is changed then)."""
    fit = Fit(simulator, particles, world, targets, objective)
    best, start = BestIterate(), math.inf
    leaves = list(vector.velocity.values())
    optimizer = torch.optim.Adam(leaves, lr=lr)
    for step in range(iterations + 1):  # the last pass only scores the last step's iterate
        optimizer.zero_grad()
        try:
            loss = objective(*fit.rollout_geometry(vector, last))
        except SimulationDiverged:
            break  # the best iterate so far stands
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
