"""The refits' Adam descents (step 3 of a diagnosis), several at once.

Every start of every refit (``diagnose.model``) is an Adam descent over leaves of its own: the
free parameters (``pipeline.params.ParameterVector``) and the candidate's scaled coefficients
u, with theta = u * scale. The descents are independent, so each step rolls out every descent
still going together (``RunContext.simulate_batch``: one differentiable simulation on
backends that batch, e.g. warp-mpm) and back-propagates the sum of their losses once; each
descent's leaves receive its own loss's gradient only. On warp-mpm's CPU path each descent is,
bit for bit, the descent it would be alone (tests/test_diagnose_descent.py). A lone descent
rolls out alone (``RunContext.simulate``).

One descent: ``settle`` steps with the coefficient held, the ``iterations``, then ``polish``
backtracking steps, and a last pass that only scores (``RefitOptions`` says why each).
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field

import torch

from mosiv_framework.diagnose.candidates import Candidate
from mosiv_framework.diagnose.context import RunContext
from mosiv_framework.errors import SimulationDiverged
from mosiv_framework.pipeline.identify import gradients_finite
from mosiv_framework.pipeline.params import ParameterVector
from mosiv_framework.types import SimulationParams, Trajectory

log = logging.getLogger(__name__)

#: seconds between the progress lines of a long descent: on a CPU one refit can take many
#: minutes, with no other sign of life (``descend_together``)
PROGRESS_INTERVAL_S = 60.0


@dataclass
class Descent:
    """One start's descent and what it has found so far."""

    candidate: Candidate | None
    vector: ParameterVector
    u: torch.Tensor
    scale: torch.Tensor
    settle: int
    iterations: int
    polish: int
    optimizer: torch.optim.Adam
    #: the optimizer's leaves, in its groups' order
    leaves: list[torch.Tensor]
    #: the lowest loss (m^2) and the ``snapshot`` where it was reached (None: no rollout yet)
    best_loss: float = math.inf
    best: dict | None = None
    #: the leaves' gradients at the best point, for polishing (``_back_to_best``)
    best_grads: list | None = None
    #: the loss of every step
    history: list[float] = field(default_factory=list)
    #: the divergence that ended the descent (None if none did)
    failure: SimulationDiverged | None = None
    step: int = 0
    done: bool = False
    #: whether this step's loss is the lowest yet (``_score``, read by ``_advance``)
    improved: bool = False

    @property
    def main_steps(self) -> int:
        return self.settle + self.iterations


def start_descent(
    candidate: Candidate | None,
    vector: ParameterVector,
    u: torch.Tensor,
    scale: torch.Tensor,
    *,
    settle: int,
    iterations: int,
    polish: int,
    learning_rates: tuple[float, float, float],
) -> Descent:
    """A descent from the leaves' current values; Adam over the velocities, the normalised
    parameters and (with a candidate) ``u``, each group at its own learning rate
    (``learning_rates``: velocity, parameter, coefficient)."""
    velocity_lr, param_lr, coefficient_lr = learning_rates
    groups = [
        {"params": list(vector.velocity.values()), "lr": velocity_lr},
        {"params": list(vector.normalized.values()), "lr": param_lr},
    ]
    if candidate is not None:
        groups.append({"params": [u], "lr": coefficient_lr})
    optimizer = torch.optim.Adam([g for g in groups if g["params"]])
    leaves = [p for g in optimizer.param_groups for p in g["params"]]
    return Descent(
        candidate, vector, u, scale, settle, iterations, polish, optimizer, leaves=leaves
    )


def descend_together(ctx: RunContext, descents: list[Descent], *, fit_frames: list[int]) -> None:
    """Run every descent to its end, the ones still going rolled out together each step.

    Args:
        ctx: the run (its simulator, loss and targets).
        descents: started by ``start_descent``; each ends with its best point found, the loss
            of every step and, where its rollouts diverged, the divergence.
        fit_frames: the frames the loss averages over; rollouts run to the last.
    """
    horizon = max(fit_frames)
    last_said = time.monotonic()
    while active := [d for d in descents if not d.done]:
        if time.monotonic() - last_said >= PROGRESS_INTERVAL_S:
            log.info(progress_line(descents))
            last_said = time.monotonic()
        for d in active:
            d.optimizer.zero_grad()
        params = [assemble(d.vector, d.candidate, d.u, d.scale) for d in active]
        results = rollouts(ctx, params, horizon)
        losses = [_score(ctx, d, result, fit_frames) for d, result in zip(active, results)]
        scored = [loss for loss in losses if loss is not None and loss.requires_grad]
        if scored:
            torch.stack(scored).sum().backward()  # each descent's leaves: its own gradient
        for d, loss in zip(active, losses):
            if not d.done:
                _advance(d, loss)


def progress_line(descents: list[Descent]) -> str:
    """How far ``descents`` have gone: the furthest step of the total, the descents still
    going and the lowest loss found so far."""
    total = max(d.main_steps + d.polish + 1 for d in descents)
    going = sum(not d.done for d in descents)
    best = min((d.best_loss for d in descents), default=math.inf)
    return (
        f"descending: step {max(d.step for d in descents)} of {total}, {going} of "
        f"{len(descents)} descents going, lowest loss {best:.4g} m^2"
    )


def rollouts(ctx: RunContext, params: list[SimulationParams], frames: int) -> list:
    """Each parameter set's differentiable rollout, or the SimulationDiverged that stopped it:
    together (``RunContext.simulate_batch``), or alone (``simulate``) where there is one."""
    if len(params) == 1:
        try:
            return [ctx.simulate(params[0], frames=frames)]
        except SimulationDiverged as exc:
            return [exc]
    return ctx.simulate_batch(params, frames=frames)


def _score(
    ctx: RunContext, d: Descent, result: Trajectory | SimulationDiverged, fit_frames: list[int]
) -> torch.Tensor | None:
    """The step's loss of ``d`` (None where its rollout diverged), recorded in its history and,
    where it is the lowest yet, as its best point. A divergence ends the descent, except in
    polishing once a best point has gradients: that step is taken back (``_advance``)."""
    if isinstance(result, SimulationDiverged):
        if d.step < d.main_steps or not d.polish or d.best_grads is None:
            d.failure, d.done = result, True
        return None
    loss = ctx.loss(result, fit_frames)
    value = float(loss.detach())
    d.history.append(value)
    d.improved = value < d.best_loss
    if d.improved:
        d.best_loss, d.best = value, snapshot(d.vector, d.u)
    return loss


def _advance(d: Descent, loss: torch.Tensor | None) -> None:
    """After the step's backward: hold the coefficient while settling, stop on non-finite
    gradients, keep the best point's gradients, backtrack while polishing, then Adam's step
    and the leaves' bounds."""
    if loss is not None:
        if d.step < d.settle:
            d.u.grad = None  # Adam skips a leaf without a gradient: the coefficient holds
        if not gradients_finite(d.leaves):
            d.done = True  # a NaN step would poison every later one: the start ends at its best
            return
        if d.improved:
            d.best_grads = [None if p.grad is None else p.grad.clone() for p in d.leaves]
    if d.polish and d.step >= d.main_steps and (loss is None or not d.improved):
        _back_to_best(d)
    d.optimizer.step()
    keep_in_bounds(d.vector, d.candidate, d.u, d.scale)
    d.step += 1
    d.done = d.step > d.main_steps + d.polish  # the last pass only scores


def _back_to_best(d: Descent) -> None:
    """Polishing after a step that did not lower the loss: back to the best point, and half the
    step from there. Adam starts afresh, so that step is the gradient's sign per coordinate,
    which lowers the loss once it is short enough (the moments of steps that overshot need
    not)."""
    restore(d.vector, d.u, d.best)
    for leaf, grad in zip(d.leaves, d.best_grads):
        leaf.grad = None if grad is None else grad.clone()
    d.optimizer.state.clear()
    for group in d.optimizer.param_groups:
        group["lr"] *= 0.5


def keep_in_bounds(vector: ParameterVector, candidate, u: torch.Tensor, scale) -> None:
    """After an optimizer step: the normalised parameters back into [0, 1], every stiffness
    inside the simulator's stability limit (``ParameterVector.keep_stable``) and the
    coefficients (theta = u * scale) into the candidate's bounds."""
    with torch.no_grad():
        for leaf in vector.normalized.values():
            leaf.clamp_(0.0, 1.0)
        vector.keep_stable()
        if candidate is not None:
            u.copy_(candidate.clamp(u * scale) / scale)


def assemble(vector, candidate, u, scale) -> SimulationParams:
    """The parameters ``vector`` stands for with ``candidate`` on at theta = u * scale."""
    params = vector.physical()
    return params if candidate is None else candidate.apply(params, u * scale)


def snapshot(vector: ParameterVector, u: torch.Tensor) -> dict:
    """A copy of the leaves (velocities, normalised parameters, scaled coefficients)."""
    return {
        "velocity": {k: v.detach().clone() for k, v in vector.velocity.items()},
        "normalized": {k: v.detach().clone() for k, v in vector.normalized.items()},
        "u": u.detach().clone(),
    }


def restore(vector: ParameterVector, u: torch.Tensor, snap: dict) -> None:
    """Put a ``snapshot`` back into the leaves."""
    with torch.no_grad():
        for k, v in snap["velocity"].items():
            vector.velocity[k].copy_(v)
        for k, v in snap["normalized"].items():
            vector.normalized[k].copy_(v)
        u.copy_(snap["u"])
