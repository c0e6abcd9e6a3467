"""Step 3, second route: identify the model again from scratch with a candidate effect on.

A refit (``model.refit``) starts from the run's identified parameters, which the run's
curriculum bent to make up for the missing effect: the initial velocities were fitted to a
flight path that the effect had curved, and the materials then made the collision fit those
velocities. Twenty steps over the whole window rarely undo that: on the drag scenes of the full
suite the refitted true law still fitted 5-130 mm^2 over the fit frames, against
0.4-1.6 mm^2 for the controls' runs, and which of linear or quadratic drag came out ahead was
decided by where each refit stopped.

Re-identification replays the run's own schedule (docs/ARCHITECTURE.md, ``pipeline.identify``)
with the candidate switched on, which is what a user adding the effect to the recipe and
running again would get: initial velocities from the centroids, law parameters at their
defaults, then

1. flight: the initial velocities together with the candidate's coefficients (an effect that
   acts in free flight bends the path the velocities are read from) over the fit frames before
   any contact, the horizon growing over them;
2. parameters: the materials (and friction, where the run identified it) together with the
   coefficients over every fit frame, the horizon growing from the first contact frame.

The null model is re-identified the same way, so that both sides of the comparison had the same
schedule on the same frames. Each phase keeps its best iterate over its whole window.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from omegaconf import OmegaConf

from mosiv_framework.diagnose.candidates import Candidate
from mosiv_framework.diagnose.context import RunContext
from mosiv_framework.diagnose.model import Fit, assemble, count_free, restore, snapshot
from mosiv_framework.errors import SimulationDiverged
from mosiv_framework.pipeline import start_vector
from mosiv_framework.pipeline.identify import gradients_finite, horizon
from mosiv_framework.pipeline.params import ParameterVector

#: consecutive diverged rollouts a phase steps back from (halving its step sizes) before it
#: ends at its best iterate
MAX_BACKOFFS = 3


@dataclass(frozen=True)
class ReidentifyOptions:
    """Iterations and step sizes of the two phases: velocity_lr (m/s per step), param_lr
    (normalised units per step), coefficient_lr (units of the coefficient's scale, as in
    ``model.refit``); the horizon starts at ``horizon_start`` frames and covers a phase's
    window after ``full_at`` of its iterations. ``from_recipe`` takes the run's own values."""

    velocity_iterations: int = 30
    param_iterations: int = 80
    velocity_lr: float = 0.05
    param_lr: float = 0.01
    coefficient_lr: float = 0.05
    horizon_start: int = 2
    full_at: float = 0.5

    def __post_init__(self) -> None:
        if self.velocity_iterations < 0 or self.param_iterations < 1:
            raise ValueError(
                f"re-identification iterations ({self.velocity_iterations}, "
                f"{self.param_iterations}): the velocity phase needs >= 0, the parameter "
                "phase >= 1"
            )

    @classmethod
    def from_recipe(cls, section) -> ReidentifyOptions:
        """The schedule of the run's ``identify`` section."""
        return cls(
            velocity_iterations=int(section.velocity_iterations),
            param_iterations=max(1, int(section.param_iterations)),
            velocity_lr=float(section.velocity_lr),
            param_lr=float(section.param_lr),
            horizon_start=int(section.horizon_start),
            full_at=float(section.horizon_full_at),
        )


def fresh_vector(ctx: RunContext) -> tuple[ParameterVector, int]:
    """The run's identification start (``pipeline.start_vector``) and its free-flight frames."""
    sim_options = OmegaConf.to_container(ctx.recipe.simulator, resolve=True)
    families = {k: p.family for k, p in ctx.identified.objects.items()}
    return start_vector(ctx.recipe, ctx.scene, families, ctx.targets, sim_options)


def reidentify(
    ctx: RunContext,
    candidate: Candidate | None,
    *,
    fit_frames: list[int],
    start: torch.Tensor | None = None,
    options: ReidentifyOptions = ReidentifyOptions(),
) -> Fit:
    """Identify the model afresh with ``candidate`` on (None: the null), its coefficients
    starting at ``start`` (default zero); fits ``fit_frames`` only. Raises SimulationDiverged
    if no rollout of the parameter phase succeeds."""
    vector, free = fresh_vector(ctx)
    if candidate is not None:
        theta0 = candidate.clamp((candidate.zero() if start is None else start).float())
        scale = torch.maximum(theta0.abs(), candidate.step)
        u = (theta0 / scale).clone().requires_grad_(True)
    else:
        scale, u = torch.ones(0), torch.zeros(0, requires_grad=True)
    coefficient = [u] if candidate is not None else []
    in_flight = candidate is not None and "free_flight" in candidate.regimes
    last = max(fit_frames)
    flight_last = min(free - 1, last)  # frame ``free`` is the first with a contact
    history: list[float] = []
    phases = [
        (
            options.velocity_iterations,
            [(list(vector.velocity.values()), options.velocity_lr)]
            + ([(coefficient, options.coefficient_lr)] if in_flight else []),
            options.horizon_start,
            flight_last,
        ),
        (
            options.param_iterations,
            [(list(vector.normalized.values()), options.param_lr)]
            + ([(coefficient, options.coefficient_lr)] if coefficient else []),
            max(options.horizon_start, flight_last + 1),
            last,
        ),
    ]
    best_loss = math.inf
    for iterations, groups, first, window_end in phases:
        window = [f for f in fit_frames if f <= window_end]
        groups = [(leaves, lr) for leaves, lr in groups if leaves]
        if iterations == 0 or not window or not groups:
            continue
        best_loss = _phase(
            ctx, vector, candidate, u, scale, groups, iterations, first, window, options, history
        )
    if not math.isfinite(best_loss):
        raise SimulationDiverged(
            object_id=-1,
            frame=-1,
            substep=-1,
            reason=(
                "every re-identification rollout of "
                f"{candidate.name if candidate else 'the null model'} diverged"
            ),
            advice="lower identify.param_lr or raise the simulator's substeps",
        )
    params = assemble(vector, candidate, u, scale).detached()
    with torch.no_grad():
        loss = float(ctx.loss(ctx.simulate(params, frames=last), fit_frames))
    theta = (u * scale).detach() if candidate is not None else torch.zeros(0)
    fit = Fit(
        "null" if candidate is None else candidate.name,
        candidate,
        params,
        theta,
        loss,
        count_free(vector) + (candidate.dim if candidate is not None else 0),
        starts=[(theta.tolist(), loss)],
        history=history,
        shared=vector.physical().detached(),
        reidentified=True,
    )
    fit.trajectory = ctx.rollout(fit.params)
    return fit


def _phase(ctx, vector, candidate, u, scale, groups, iterations, first, window, options, history):
    """One phase of Adam with a growing horizon over ``window`` (fit frames); leaves the
    vector at the phase's best iterate over the whole window and returns that loss."""
    optimizer = torch.optim.Adam([{"params": leaves, "lr": lr} for leaves, lr in groups])
    # cosine decay to a tenth of the rate, as the run's identification does
    schedule = torch.optim.lr_scheduler.LambdaLR(
        optimizer, lambda i: 0.1 + 0.45 * (1 + math.cos(math.pi * i / iterations))
    )
    leaves = [leaf for group in optimizer.param_groups for leaf in group["params"]]
    end = max(window)
    best_loss, best_snap = math.inf, None
    previous = snapshot(vector, u)
    unit, backoffs = None, 0
    for it in range(iterations + 1):  # the last pass only scores the last step
        h = (
            end
            if it == iterations
            else horizon(it, iterations, start=min(first, end), full_at=options.full_at, last=end)
        )
        frames = [f for f in window if f <= h] or [min(window)]
        h = max(h, max(frames))
        optimizer.zero_grad()
        try:
            traj = ctx.simulate(assemble(vector, candidate, u, scale), frames=h)
            loss = ctx.loss(traj, frames)
            value = float(loss.detach())
            if not math.isfinite(value):
                raise FloatingPointError
            if unit is None:  # scale-free steps, whatever the loss's magnitude
                unit = 1.0 / max(value, 1e-30)
            (loss * unit).backward()
            if not gradients_finite(leaves):
                raise FloatingPointError
        except (SimulationDiverged, FloatingPointError):
            backoffs += 1
            if backoffs > MAX_BACKOFFS:
                break
            restore(vector, u, previous)
            for group in optimizer.param_groups:
                group["lr"] *= 0.5
            schedule.base_lrs = [lr * 0.5 for lr in schedule.base_lrs]
            continue
        backoffs = 0
        history.append(value)
        if h == end and value < best_loss:
            best_loss, best_snap = value, snapshot(vector, u)
        if it == iterations:
            break
        previous = snapshot(vector, u)
        for leaf in leaves:  # a leaf this horizon does not reach yet holds still
            if leaf.grad is not None and not bool(leaf.grad.any()):
                leaf.grad = None
        optimizer.step()
        schedule.step()
        with torch.no_grad():
            for leaf in vector.normalized.values():
                leaf.clamp_(0.0, 1.0)
            if candidate is not None:
                u.copy_(candidate.clamp(u * scale) / scale)
    if best_snap is not None:
        restore(vector, u, best_snap)
    return best_loss
