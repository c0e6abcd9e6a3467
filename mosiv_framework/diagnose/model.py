"""Step 3 of a diagnosis: refit the model with a candidate effect, through the simulator.

A new coefficient fitted alone would be judged against old parameters that were biased to make
up for the missing effect, so the refit frees the run's parameters (initial velocities, the
material parameters the run identified, see ``pipeline.params.ParameterVector``) together with
the candidate's coefficients. The model without any new effect (the "null") is refitted by the
same procedure and budget, so any improvement a candidate shows is not just more optimisation.
Several starts (the screening's regression and probe estimates of the coefficient, and
multiples of them) guard against local minima; their spread feeds the coefficient's interval.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch

from mosiv_framework.diagnose.candidates import Candidate
from mosiv_framework.diagnose.context import RunContext
from mosiv_framework.diagnose.descent import (  # noqa: F401 (reidentify imports these from here)
    Descent,
    assemble,
    descend_together,
    restore,
    snapshot,
    start_descent,
)
from mosiv_framework.errors import SimulationDiverged
from mosiv_framework.pipeline.params import ParameterVector
from mosiv_framework.types import SimulationParams, Trajectory


@dataclass(frozen=True)
class RefitOptions:
    """iterations: Adam steps per start; velocity_lr (m/s per step), param_lr (normalised
    units per step) and coefficient_lr (in units of the coefficient's scale, see ``refit``):
    step sizes; settle: extra steps, before those, in which the first start that brings its
    own velocity change (a flight-path regression's estimate, which ``refit_starts`` puts
    first; its multiples follow unsettled) moves only the shared parameters, its coefficient
    held.

    Why settle: the regression reads a body force off the free flight, but the identified
    materials were biased to make up for its absence. At the exact wind of wind-1 (full suite)
    the collision went so wrong that the window fitted 11x worse than the run
    (0.0186 against 0.0017 m^2), and a joint refit pulled the wind from 2.5 down to 1.5 m/s^2
    before the materials could follow. With the wind held, 20 steps moved the second body's
    density from 332 to 651 kg/m^3 and reached 0.0015 m^2 (CPU check, 2026-11-22, code 7860a80).

    polish: further steps, after those, that leave the best point found only for a better one:
    a step that does not lower the loss is taken back, and the next, from the best point along
    its gradient's signs, is half as long (backtracking). Why: Adam's
    steps are about one learning rate per coordinate whatever the gradient, 0.02 m/s of
    velocity moves a body 10 mm over half a second, and on the control scenes of the full suite
    the run's identified state fitted to 0.1-2 mm^2. There every refit step made the fit worse:
    the refits of control-1's gravity ended at their starts (loss 2.5e-6 m^2), while the
    model identified afresh fitted to 5e-8 m^2, and such differences of optimisation, not of
    physics, decided which model won."""

    iterations: int = 8
    velocity_lr: float = 0.02
    param_lr: float = 0.01
    coefficient_lr: float = 0.15
    settle: int = 0
    polish: int = 0
    #: every start of the refits asked for at once descends in lockstep (``descent``); False:
    #: one after another (the same results on warp-mpm's CPU path; for timing the batch)
    together: bool = True

    def __post_init__(self) -> None:
        if self.iterations < 1:
            raise ValueError(f"refit iterations={self.iterations}: must be >= 1")
        if self.settle < 0:
            raise ValueError(f"refit settle={self.settle}: must be >= 0")
        if self.polish < 0:
            raise ValueError(f"refit polish={self.polish}: must be >= 0")


@dataclass
class Fit:
    """A refitted model: ``params`` with ``theta`` applied; ``loss`` over the fit frames (m^2);
    ``starts`` holds (theta, loss) of every start; ``n_params`` counts free scalars."""

    name: str
    candidate: Candidate | None
    params: SimulationParams
    theta: torch.Tensor
    loss: float
    n_params: int
    starts: list[tuple[list[float], float]] = field(default_factory=list)
    trajectory: Trajectory | None = None
    history: list[float] = field(default_factory=list)
    #: the refitted free parameters without the candidate's effect (for a null: ``params``)
    shared: SimulationParams | None = None
    #: where the refit started if not from the run's identified state: the model (a candidate's
    #: name, or "null") whose shared parameters it continued from (``converge_null``,
    #: ``converge_candidates``)
    started_from: str | None = None
    #: whether the fit came from identifying the model afresh (``reidentify``) rather than
    #: from a refit of the run's identified state
    reidentified: bool = False
    #: the simulator's message (object, frame, substep) where the prediction over all frames
    #: diverged for every start; ``trajectory`` is then None (see ``predict``)
    diverged: str | None = None
    #: then the prediction up to the frame before the divergence (None if that failed too),
    #: so that the frames it reached, the fit frames among them, still have errors
    reached: Trajectory | None = None

    @property
    def refit_diverged(self) -> bool:
        """Whether no start of the refit got through the fit frames (``diverged_refit``), as
        opposed to a refit whose prediction over all frames diverged (``predict``)."""
        return is_refit_divergence(self.diverged)


#: how ``Fit.diverged`` begins where the refit itself diverged (``diverged_refit``); where only
#: the prediction did, it is the simulator's own message (``predict``)
REFIT_DIVERGED = "refit diverged"


def is_refit_divergence(diverged: str | None) -> bool:
    """Whether a ``Fit.diverged`` message (or diagnosis.json's ``diverged``) says that the
    refit itself diverged, not only its prediction."""
    return diverged is not None and diverged.startswith(REFIT_DIVERGED)


def count_free(vector: ParameterVector) -> int:
    """Free scalars of ``vector`` (the parameter count of the information criterion)."""
    leaves = [*vector.velocity.values(), *vector.normalized.values()]
    return sum(v.numel() for v in leaves)  # a vector term parameter counts as 3


@dataclass(frozen=True)
class RefitRequest:
    """One refit of ``refit_together``: ``candidate`` (None: the null model) from ``starts``
    (coefficient vector, initial-velocity change per object or None; default: zero and none),
    the free parameters starting at ``base`` (default: the run's identified values)."""

    candidate: Candidate | None
    starts: list[tuple[torch.Tensor, dict | None]] | None = None
    base: SimulationParams | None = None


def refit(
    ctx: RunContext,
    candidate: Candidate | None,
    *,
    fit_frames: list[int],
    starts: list[tuple[torch.Tensor, dict | None]] | None = None,
    base: SimulationParams | None = None,
    options: RefitOptions = RefitOptions(),
) -> Fit:
    """Refit the run's free parameters (plus ``candidate``'s coefficients) on ``fit_frames``.

    Each of ``starts`` (coefficient vector, initial-velocity change per object or None;
    default: zero and none) begins a fit; the first start that brings a velocity change (an
    empty one too) settles the shared parameters first (``RefitOptions.settle``). The
    coefficient is optimised as theta = scale * u with scale the larger of |start| and the
    candidate's natural step, so one learning rate suits coefficients of any unit. Returns the
    best start whose prediction over all frames succeeds (``predict``); a start whose rollouts
    all diverge is skipped, and where every start's does, the model is kept with that
    divergence as evidence (``diverged_refit``). The free parameters start at ``base``
    (default: the run's identified values). The starts descend together
    (``descent.descend_together``).
    """
    request = RefitRequest(candidate, starts, base)
    return refit_together(ctx, [request], fit_frames=fit_frames, options=options)[0]


def refit_together(
    ctx: RunContext,
    requests: list[RefitRequest],
    *,
    fit_frames: list[int],
    options: RefitOptions = RefitOptions(),
) -> list[Fit]:
    """``refit`` of each request, every start of every request descending in the same batched
    rollouts (``descent.descend_together``); one Fit per request, in order."""
    plans = []
    for request in requests:
        starts = request.starts or [
            (torch.zeros(0) if request.candidate is None else request.candidate.zero(), None)
        ]
        plans.append((request, starts, _start_descents(ctx, request, starts, options)))
    every = [d for *_, descents in plans for d in descents]
    for batch in [every] if options.together else [[d] for d in every]:
        descend_together(ctx, batch, fit_frames=fit_frames)
    return [_best_of(ctx, request, starts, descents) for request, starts, descents in plans]


def _start_descents(
    ctx: RunContext, request: RefitRequest, starts: list, options: RefitOptions
) -> list[Descent]:
    """A descent per start of ``request``; the first start that brings its own velocity change
    (the flight-path regression's) settles the shared parameters first."""
    descents, settled = [], False
    for start, velocity_change in starts:
        settle = 0
        if request.candidate is not None and velocity_change is not None and not settled:
            settle, settled = options.settle, True
        vector = _start_vector(ctx, request.base, velocity_change)
        candidate = request.candidate
        if candidate is not None:
            theta_start = candidate.clamp(start.detach().float())
            scale = torch.maximum(theta_start.abs(), candidate.step)
            u = (theta_start / scale).clone().requires_grad_(True)
        else:
            scale, u = torch.ones(0), torch.zeros(0, requires_grad=True)
        rates = (options.velocity_lr, options.param_lr, options.coefficient_lr)
        descents.append(
            start_descent(
                candidate,
                vector,
                u,
                scale,
                settle=settle,
                iterations=options.iterations,
                polish=options.polish,
                learning_rates=rates,
            )
        )
    return descents


def _best_of(ctx: RunContext, request: RefitRequest, starts: list, descents: list) -> Fit:
    """The request's Fit from its starts' descents: the best that predicts (``predict``), or
    ``diverged_refit`` where no start got through the fit frames."""
    ends, failures = [], []
    for d in descents:
        if d.best is None:  # not even its first rollout succeeded
            failures.append(
                d.failure
                or SimulationDiverged(
                    object_id=-1,
                    frame=-1,
                    substep=-1,
                    reason="the loss at the start is not finite",
                    advice="lower the refit learning rates or raise the simulator's substeps",
                )
            )
            continue
        ends.append(_fit_of(d))
    if not ends:
        return diverged_refit(ctx, request.candidate, starts[0], failures[0], base=request.base)
    best = predict(ctx, sorted(ends, key=lambda f: f.loss))  # stable: the first start on ties
    best.starts = [(end.theta.tolist(), end.loss) for end in ends]
    return best


def _fit_of(d: Descent) -> Fit:
    """A descent's best point as a Fit."""
    restore(d.vector, d.u, d.best)
    candidate = d.candidate
    theta = (d.u * d.scale).detach() if candidate is not None else torch.zeros(0)
    return Fit(
        "null" if candidate is None else candidate.name,
        candidate,
        assemble(d.vector, candidate, d.u, d.scale).detached(),
        theta,
        d.best_loss,
        count_free(d.vector) + (candidate.dim if candidate is not None else 0),
        history=d.history,
        shared=d.vector.physical().detached(),
    )


def diverged_refit(
    ctx: RunContext,
    candidate: Candidate | None,
    start: tuple[torch.Tensor, dict | None],
    exc: SimulationDiverged,
    *,
    base: SimulationParams | None = None,
) -> Fit:
    """The model of a refit none of whose starts got through the fit frames: at its first
    ``start``, with an infinite fit loss, no trajectory, ``diverged`` the simulator's place
    of the first start's divergence (``exc``) and ``reached`` its rollout up to the frame
    before.

    The rule of ``predict``, applied one step earlier: a model the simulator cannot carry
    (a discovered law's refit can blow up on a control scene) must not end the whole
    diagnosis, so it is kept as evidence that cannot be accepted (``decide.frame_errors``: the
    frames it did not reach are infinitely wrong, so it fails the held-out test and the
    information criterion) and the report gives the reason. No refitted shared parameters
    (``shared`` None): no other model may continue from a state that was never fitted.
    """
    theta, velocity_change = start
    vector = _start_vector(ctx, base, velocity_change)
    if candidate is not None:
        theta = candidate.clamp(theta.detach().float())
        params = candidate.apply(vector.physical(), theta)
    else:
        theta, params = torch.zeros(0), vector.physical()
    fit = Fit(
        "null" if candidate is None else candidate.name,
        candidate,
        params.detached(),
        theta,
        math.inf,
        count_free(vector) + (candidate.dim if candidate is not None else 0),
    )
    fit.diverged = (
        f"{REFIT_DIVERGED} at object {exc.object_id}, frame {exc.frame}, substep {exc.substep}"
        f" ({exc.reason})"
    )
    fit.reached = _reached(ctx, fit.params, exc)
    return fit


def _reached(ctx: RunContext, params: SimulationParams, exc: SimulationDiverged):
    """The rollout of ``params`` up to the frame before the one it diverged in (``exc``), the
    frames the simulator passed; None if that diverges too."""
    try:
        return ctx.rollout(params, frames=max(exc.frame - 1, 0))
    except SimulationDiverged:
        return None


def _start_vector(
    ctx: RunContext, base: SimulationParams | None, velocity_change: dict | None
) -> ParameterVector:
    """The free parameters at ``base`` (default: the run's identified values) with a start's
    initial-velocity change per object added."""
    vector = ctx.parameter_vector(base)
    if velocity_change is not None:
        with torch.no_grad():
            for k, dv in velocity_change.items():
                vector.velocity[k].add_(dv)
    return vector


def predict(ctx: RunContext, ranked: list[Fit]) -> Fit:
    """The first of ``ranked`` (best fit first) whose rollout over all frames succeeds, with
    that rollout as its ``trajectory``; if every one diverges, the first, with ``diverged``
    and ``reached`` set instead.

    A refit simulates only up to the last fit frame, so a start can fit those frames well and
    blow up after them (outside-quadratic_drag of a GPU diagnose-suite: object 2, frame 18).
    One model's prediction must not end the whole diagnosis: a start that fits a little worse
    but predicts is taken instead, and a model none of whose starts predicts is kept with its
    divergence as evidence (``decide.frame_errors`` counts the frames it did not reach as
    infinitely wrong, so such a candidate cannot be accepted).
    """
    failures = []
    for fit in ranked:
        try:
            fit.trajectory = ctx.rollout(fit.params)
            return fit
        except SimulationDiverged as exc:
            failures.append(exc)
    best, exc = ranked[0], failures[0]
    best.diverged = str(exc)
    best.reached = _reached(ctx, best.params, exc)  # the frames before the divergence
    return best


def replaces(new: Fit, old: Fit) -> bool:
    """Whether ``new`` should replace ``old`` as a model's fit: the lower fit loss, except that a
    fit whose prediction over all frames succeeds beats one whose prediction diverged (the
    decision cannot accept a diverging candidate, and a diverging null leaves the candidates'
    future errors nothing finite to be compared with)."""
    if (new.diverged is None) != (old.diverged is None):
        return new.diverged is None
    return new.loss < old.loss


def converge_null(
    ctx: RunContext, null: Fit, fits: list[Fit], *, fit_frames: list[int], options: RefitOptions
) -> Fit:
    """The null refit, continued from the best candidate refit with its effect switched off.

    A candidate's refit also moves the shared parameters (velocities, material), and may find
    shared values that fit better even without its effect: those values belong to the null
    model too, so a null that did not reach them is under-converged, and every candidate would
    win the held-out test against it by optimisation alone (without this step, three of six
    controls of the full suite were rejected by the information criterion only). The null
    becomes the better of itself and a refit begun at the best switched-off candidate
    (``replaces``).
    """
    # a null whose prediction diverged is continued from the best candidate state whatever
    # its fit loss: one that predicts every frame replaces it (``replaces``)
    best_loss, best_fit = (math.inf if null.diverged else null.loss), None
    # independent rollouts, so together (``RunContext.rollout_losses``); a diverged one is
    # inf and never the best
    switched_off = [fit for fit in fits if fit.shared is not None]
    losses = ctx.rollout_losses([fit.shared for fit in switched_off], fit_frames)
    for fit, loss in zip(switched_off, losses):
        if loss < best_loss:
            best_loss, best_fit = loss, fit
    if best_fit is None:
        return null
    # a refit that diverges keeps its divergence (``diverged_refit``) and replaces nothing
    warm = refit(ctx, None, fit_frames=fit_frames, base=best_fit.shared, options=options)
    if not replaces(warm, null):
        return null
    warm.started_from = best_fit.name
    return warm


def converge_candidates(
    ctx: RunContext, null: Fit, fits: list[Fit], *, fit_frames: list[int], options: RefitOptions
) -> list[Fit]:
    """Each candidate refit that fits worse than the best model found, continued from that
    model's shared parameters (its effect switched off) with its own refitted coefficients
    (settled first, then jointly); ``started_from`` names where.

    The comparison is of laws, not of optimisation luck. The null starts from the run's
    identification, which the curriculum made for the model without the effect (110 steps on
    wind-1), and ``converge_null`` continues it; each candidate gets its refit from a state
    biased against it. Two signs that optimisation rather than the law decided a full suite
    without this step: a candidate contains the null (its coefficients at zero), so at its
    optimum it fits at least as well, yet 31 of 101 candidate refits fitted worse, even when
    continued from the null alone; and linear and quadratic drag, hard to tell apart, were
    named the wrong way round on three of four drag scenes. The mirror of ``converge_null``:
    every model may start from the best state any model found. A continued candidate replaces
    its refit only where it fits better (or predicts all frames where that refit's prediction
    diverged, see ``replaces``).
    """
    # the best state is one that predicts every frame: a diverged fit's shared parameters
    # blow up after the fit frames, and a diverged fit is continued whatever its loss
    source = min([null, *fits], key=lambda f: (f.diverged is not None, f.loss))
    if source.shared is None:
        return fits

    def continued(fit: Fit) -> bool:
        settled = fit.loss <= source.loss and fit.diverged is None
        return not (fit.candidate is None or fit is source or settled)

    behind = [fit for fit in fits if continued(fit)]
    # the continued refits are independent: they descend together
    requests = [
        RefitRequest(fit.candidate, [(fit.theta, {})], source.shared)  # {}: settle first
        for fit in behind
    ]
    warms = refit_together(ctx, requests, fit_frames=fit_frames, options=options)
    warm_of = {id(fit): warm for fit, warm in zip(behind, warms)}
    converged = []
    for fit in fits:
        warm = warm_of.get(id(fit))
        if warm is not None and replaces(warm, fit):  # not where it diverged again
            warm.started_from = source.name
            warm.starts = fit.starts + warm.starts
            converged.append(warm)
        else:
            converged.append(fit)
    return converged
