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
from dataclasses import dataclass, field

import torch
from omegaconf import OmegaConf

from mosiv_framework.diagnose.candidates import Candidate
from mosiv_framework.diagnose.context import RunContext
from mosiv_framework.diagnose.descent import keep_in_bounds
from mosiv_framework.diagnose.descent import rollouts as _rollouts
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
    (result,) = reidentify_together(
        ctx, [(candidate, start)], fit_frames=fit_frames, options=options
    )
    if isinstance(result, SimulationDiverged):
        raise result
    return result


@dataclass
class _Model:
    """One model's re-identification: its leaves and the loss of every step."""

    candidate: Candidate | None
    vector: ParameterVector
    u: torch.Tensor
    scale: torch.Tensor
    history: list[float] = field(default_factory=list)
    best_loss: float = math.inf


def reidentify_together(
    ctx: RunContext,
    models: list[tuple[Candidate | None, torch.Tensor | None]],
    *,
    fit_frames: list[int],
    options: ReidentifyOptions = ReidentifyOptions(),
    together: bool = True,
) -> list[Fit | SimulationDiverged]:
    """``reidentify`` of each (candidate, start) of ``models``, all in lockstep: the schedule
    (phases, iterations, horizons) is the run's for every model, so each step rolls every model
    still going out together (``RunContext.simulate_batch``) and back-propagates once
    (``together`` False: one model after another). One result per model, in order: its Fit, or
    the SimulationDiverged where no rollout of its parameter phase succeeded."""
    if not together:
        return [
            reidentify_together(ctx, [model], fit_frames=fit_frames, options=options)[0]
            for model in models
        ]
    vector_and_free = [fresh_vector(ctx) for _ in models]
    states = []
    for (candidate, start), (vector, _) in zip(models, vector_and_free):
        if candidate is not None:
            theta0 = candidate.clamp((candidate.zero() if start is None else start).float())
            scale = torch.maximum(theta0.abs(), candidate.step)
            u = (theta0 / scale).clone().requires_grad_(True)
        else:
            scale, u = torch.ones(0), torch.zeros(0, requires_grad=True)
        states.append(_Model(candidate, vector, u, scale))
    free = vector_and_free[0][1] if vector_and_free else 0
    last = max(fit_frames)
    flight_last = min(free - 1, last)  # frame ``free`` is the first with a contact
    phases = [
        (options.velocity_iterations, options.horizon_start, flight_last, True),
        (options.param_iterations, max(options.horizon_start, flight_last + 1), last, False),
    ]
    for iterations, first, window_end, flight in phases:
        window = [f for f in fit_frames if f <= window_end]
        if iterations == 0 or not window:
            continue
        taking_part = [(m, _groups(m, options, flight=flight)) for m in states]
        taking_part = [(m, groups) for m, groups in taking_part if groups]
        if taking_part:
            _phase_together(ctx, taking_part, iterations, first, window, options)
    return [_result(ctx, m, fit_frames) for m in states]


def _groups(m: _Model, options: ReidentifyOptions, *, flight: bool) -> list:
    """(leaves, learning rate) of the model's phase: the flight phase moves the velocities and
    a coefficient acting in free flight, the parameter phase the materials and any coefficient;
    groups without leaves left out."""
    coefficient = [m.u] if m.candidate is not None else []
    if flight:
        in_flight = m.candidate is not None and "free_flight" in m.candidate.regimes
        groups = [(list(m.vector.velocity.values()), options.velocity_lr)]
        groups += [(coefficient, options.coefficient_lr)] if in_flight else []
    else:
        groups = [(list(m.vector.normalized.values()), options.param_lr)]
        groups += [(coefficient, options.coefficient_lr)] if coefficient else []
    return [(leaves, lr) for leaves, lr in groups if leaves]


def _result(ctx: RunContext, m: _Model, fit_frames: list[int]) -> Fit | SimulationDiverged:
    """The model at its best iterate as a Fit (scored over the fit frames, with its prediction
    over all frames), or why there is none."""
    candidate = m.candidate
    if not math.isfinite(m.best_loss):
        return SimulationDiverged(
            object_id=-1,
            frame=-1,
            substep=-1,
            reason=(
                "every re-identification rollout of "
                f"{candidate.name if candidate else 'the null model'} diverged"
            ),
            advice="lower identify.param_lr or raise the simulator's substeps",
        )
    params = assemble(m.vector, candidate, m.u, m.scale).detached()
    with torch.no_grad():
        loss = float(ctx.loss(ctx.simulate(params, frames=max(fit_frames)), fit_frames))
    theta = (m.u * m.scale).detach() if candidate is not None else torch.zeros(0)
    fit = Fit(
        "null" if candidate is None else candidate.name,
        candidate,
        params,
        theta,
        loss,
        count_free(m.vector) + (candidate.dim if candidate is not None else 0),
        starts=[(theta.tolist(), loss)],
        history=m.history,
        shared=m.vector.physical().detached(),
        reidentified=True,
    )
    fit.trajectory = ctx.rollout(fit.params)
    return fit


@dataclass
class _PhaseRun:
    """One model's Adam in one phase: optimizer, cosine schedule, backoff state, best iterate."""

    model: _Model
    optimizer: torch.optim.Adam
    schedule: torch.optim.lr_scheduler.LambdaLR
    leaves: list[torch.Tensor]
    previous: dict
    best_loss: float = math.inf
    best_snap: dict | None = None
    unit: float | None = None
    backoffs: int = 0
    done: bool = False


def _phase_run(m: _Model, groups: list, iterations: int) -> _PhaseRun:
    optimizer = torch.optim.Adam([{"params": leaves, "lr": lr} for leaves, lr in groups])
    # cosine decay to a tenth of the rate, as the run's identification does
    schedule = torch.optim.lr_scheduler.LambdaLR(
        optimizer, lambda i: 0.1 + 0.45 * (1 + math.cos(math.pi * i / iterations))
    )
    leaves = [leaf for group in optimizer.param_groups for leaf in group["params"]]
    return _PhaseRun(m, optimizer, schedule, leaves, snapshot(m.vector, m.u))


def _phase_together(ctx, taking_part, iterations, first, window, options) -> None:
    """One phase of Adam with a growing horizon over ``window`` (fit frames) for every model
    of ``taking_part`` ((model, groups)), their rollouts together each step; leaves each model
    at its best iterate over the whole window, its loss in ``best_loss``."""
    runs = [_phase_run(m, groups, iterations) for m, groups in taking_part]
    end = max(window)
    for it in range(iterations + 1):  # the last pass only scores the last step
        h = (
            end
            if it == iterations
            else horizon(it, iterations, start=min(first, end), full_at=options.full_at, last=end)
        )
        frames = [f for f in window if f <= h] or [min(window)]
        h = max(h, max(frames))
        active = [r for r in runs if not r.done]
        if not active:
            break
        for r in active:
            r.optimizer.zero_grad()
        params = [
            assemble(r.model.vector, r.model.candidate, r.model.u, r.model.scale) for r in active
        ]
        losses = [
            _step_loss(ctx, r, result, frames)
            for r, result in zip(active, _rollouts(ctx, params, h))
        ]
        scaled = [loss * r.unit for r, loss in zip(active, losses) if loss is not None]
        if scaled:
            torch.stack(scaled).sum().backward()  # each model's leaves: its own gradient
        for r, loss in zip(active, losses):
            _step(r, loss, last=it == iterations, at_end=h == end)
    for r in runs:
        if r.best_snap is not None:
            restore(r.model.vector, r.model.u, r.best_snap)
        r.model.best_loss = r.best_loss


def _step_loss(ctx, r: _PhaseRun, result, frames: list[int]) -> torch.Tensor | None:
    """The model's loss this step (None where its rollout diverged or the loss is not
    finite); the first finite loss sets its scale-free unit."""
    if isinstance(result, SimulationDiverged):
        return None
    loss = ctx.loss(result, frames)
    value = float(loss.detach())
    if not math.isfinite(value):
        return None
    if r.unit is None:  # scale-free steps, whatever the loss's magnitude
        r.unit = 1.0 / max(value, 1e-30)
    return loss


def _step(r: _PhaseRun, loss: torch.Tensor | None, *, last: bool, at_end: bool) -> None:
    """After the step's backward: back off (step sizes halved, back to the previous iterate)
    on a diverged rollout or non-finite gradients, ending after MAX_BACKOFFS in a row; else
    record the loss, keep the best iterate over the whole window, and take Adam's step."""
    m = r.model
    if loss is None or not gradients_finite(r.leaves):
        r.backoffs += 1
        if r.backoffs > MAX_BACKOFFS:
            r.done = True
            return
        restore(m.vector, m.u, r.previous)
        for group in r.optimizer.param_groups:
            group["lr"] *= 0.5
        r.schedule.base_lrs = [lr * 0.5 for lr in r.schedule.base_lrs]
        return
    r.backoffs = 0
    value = float(loss.detach())
    m.history.append(value)
    if at_end and value < r.best_loss:
        r.best_loss, r.best_snap = value, snapshot(m.vector, m.u)
    if last:
        r.done = True
        return
    r.previous = snapshot(m.vector, m.u)
    for leaf in r.leaves:  # a leaf this horizon does not reach yet holds still
        if leaf.grad is not None and not bool(leaf.grad.any()):
            leaf.grad = None
    r.optimizer.step()
    r.schedule.step()
    keep_in_bounds(m.vector, m.candidate, m.u, m.scale)
