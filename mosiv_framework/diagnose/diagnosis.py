"""``mosiv diagnose RUN``: locate -> hypothesise -> model -> decide -> report (docs/DIAGNOSIS.md).

The frames of the run are split three ways: fit frames (the observed window minus held-out
blocks) on which every model is refitted, the held-out blocks (short runs of observed frames
spread over the window) and the future frames (after the observed window); the last two
together are what the decision judges models on, frames none of the compared refits saw.

"Model" has two routes per model (the null and each kept candidate): a refit from the run's
identified state (``model.refit``) and, in the full budget, an identification from scratch
with the run's schedule (``reidentify``); the better fit of the two is kept, then every model
may continue from the best state any model found (``model.converge_*``). The evidence
includes each standing candidate's own effect (``effect``) against the null's resolution floor
(``floor``).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace
from pathlib import Path

import torch

from mosiv_framework.diagnose.candidates import build_candidates
from mosiv_framework.diagnose.context import load_run
from mosiv_framework.diagnose.decide import (
    DecideOptions,
    apply_effect_test,
    apply_interval_test,
    decide,
    frame_errors,
    verdict,
)
from mosiv_framework.diagnose.effect import measure_effect
from mosiv_framework.diagnose.floor import resolution_floor, summarise_floor
from mosiv_framework.diagnose.hypothesise import choose_refits, regression_estimate, screen
from mosiv_framework.diagnose.interval import coefficient_interval
from mosiv_framework.diagnose.locate import locate
from mosiv_framework.diagnose.model import (
    RefitOptions,
    converge_candidates,
    converge_null,
    refit,
    replaces,
)
from mosiv_framework.diagnose.reidentify import ReidentifyOptions, reidentify
from mosiv_framework.diagnose.report import write_report
from mosiv_framework.diagnose.steps import DiagnosisSteps, diagnosis_key
from mosiv_framework.errors import ConfigError, SimulationDiverged

#: multiples of the screening's estimates that further refit starts begin at
START_FACTORS = (1.0, 0.5, 1.5, 2.0, 0.25)


def refit_starts(screen_result, count: int, *, far_start: bool = False) -> list:
    """Up to ``count`` (coefficient, initial-velocity change) starts: the regression estimate
    (if any, with the velocity change it implies), the probe's, then multiples of the first;
    with ``far_start``, one more at the far end of the screening's walk for a candidate that
    has no regression estimate (a contact or material effect).

    Why the far start: the screening reads the loss at the run's identified state, which made
    up for the missing effect; there ground_restitution-1's loss was lowest near e = 0.17, and
    every start near it ended there, while a refit begun at e = 0.9 reached 0.96 (concealed:
    0.9; docs/RESULTS.md)."""
    starts = [] if screen_result.regression is None else [screen_result.regression]
    starts.append((screen_result.theta, None))
    starts += [(f * starts[0][0], starts[0][1]) for f in START_FACTORS[1:]]
    starts = starts[:count]
    if far_start and screen_result.regression is None and screen_result.far is not None:
        starts.append((screen_result.far, None))
    return starts


def null_starts(regression) -> list:
    """Starts of the null refit: the run's identified state itself, and the initial-velocity
    change the centroid regression implies (if any).

    Every candidate's starts include the identified state (its probe start keeps the run's
    velocities), so the null must too: a null begun only from the regression start can end
    worse than the run it refits, and every candidate would then "win" against it (seen on a
    control scene of the full suite, where a zero viscosity was accepted)."""
    starts = [(torch.zeros(0), None)]
    if regression is not None:
        starts.append((torch.zeros(0), regression[1]))
    return starts


@dataclass(frozen=True)
class Budget:
    """How much a diagnosis may compute: candidates refitted, refit iterations and starts,
    bootstrap resamples, the fraction of the observed window held out, the steps a
    regression start settles the shared parameters first (``RefitOptions.settle``),
    whether every model is also identified afresh with the run's schedule (``reidentify``;
    the better of that and its refit is kept), the backtracking steps that end every
    refit (``RefitOptions.polish``), the refit's initial-velocity step (m/s per step) and
    whether contact and material candidates get a start at the far end of the screening's
    walk (``refit_starts``). A recipe's ``diagnose`` section may set max_candidates,
    bootstrap, starts, iterations, polish, far_start and (as ``refit_velocity_lr``)
    velocity_lr."""

    max_candidates: int
    iterations: int
    starts: int
    bootstrap: int
    heldout_fraction: float = 0.25
    settle: int = 0
    reidentify: bool = False
    polish: int = 0
    velocity_lr: float = RefitOptions.velocity_lr
    far_start: bool = False


BUDGETS = {
    # the small budget fits the whole observed window (as the run did) and judges on the
    # future frames only: short windows leave too few fitted frames to tell effects apart
    "small": Budget(max_candidates=3, iterations=6, starts=2, bootstrap=200, heldout_fraction=0.0),
    # four candidates: wind ranked fourth in the screen of wind-1 of the full suite and was
    # never refitted with three
    "full": Budget(
        max_candidates=4,
        iterations=20,
        starts=3,
        bootstrap=1000,
        settle=20,
        reidentify=True,
        polish=10,
    ),
}


def split_frames(
    observed: int, n_frames: int, heldout_fraction: float, *, block: int = 2
) -> tuple[list, list]:
    """(fit frames, held-out frames) of a run observing frames 0 .. ``observed`` - 1 of
    ``n_frames``.

    Held out: every future frame, plus about ``heldout_fraction`` of the observed window as
    blocks of ``block`` frames spread evenly over it, so that flight, impact and landing each
    keep fitted frames and are each tested. (A single block at the end of the window held out
    exactly the frames where late effects such as ground friction act: their refit could not
    improve the fitted frames, and the information criterion, computed on those, could never
    favour them, on the full suite.) Without 2 future frames, the last observed
    frames make up the difference: a prediction is then tested on the only frames after the fit.
    """
    window = list(range(1, observed))
    future = list(range(observed, n_frames))
    tail = max(0, 2 - len(future))
    tail_frames = window[len(window) - tail :] if tail else []
    inner = window[: len(window) - tail]
    held = set(tail_frames)
    if heldout_fraction > 0 and inner:
        n_blocks = max(1, round(heldout_fraction * len(inner) / block))
        for i in range(n_blocks):
            first = round((i + 1) * len(inner) / (n_blocks + 1)) - block // 2
            held.update(inner[max(0, first) : max(0, first) + block])
    fit = [t for t in window if t not in held]
    if len(fit) < 2:
        raise ConfigError(
            f"the run observes {observed} of {n_frames} frames; a diagnosis needs 2 fitted "
            f"and 2 held-out frames (it would hold out {len(held)} observed frames): observe "
            f"more frames or lower the held-out fraction"
        )
    return fit, sorted(held) + future


def resolve_budget(budget: str | Budget, section=None) -> Budget:
    """The budget named (or given), with what the recipe's ``diagnose`` ``section`` sets."""
    if isinstance(budget, str):
        if budget not in BUDGETS:
            raise ConfigError(f"budget {budget!r} is unknown; valid: {sorted(BUDGETS)}")
        budget = BUDGETS[budget]
    if section is None:
        return budget
    keys = {  # recipe key: (budget field, type)
        "max_candidates": ("max_candidates", int),
        "bootstrap": ("bootstrap", int),
        "starts": ("starts", int),
        "iterations": ("iterations", int),
        "polish": ("polish", int),
        "refit_velocity_lr": ("velocity_lr", float),
        "far_start": ("far_start", bool),
    }
    return replace(
        budget,
        **{
            field: kind(section[key])
            for key, (field, kind) in keys.items()
            if section.get(key) is not None
        },
    )


def _better(fit, ctx, candidate, start, fit_frames, schedule):
    """``fit`` or the model re-identified afresh, whichever fits the fit frames better (or
    predicts all frames where the other diverged: ``model.replaces``)."""
    try:
        fresh = reidentify(ctx, candidate, fit_frames=fit_frames, start=start, options=schedule)
    except SimulationDiverged:
        return fit
    if replaces(fresh, fit):
        fresh.starts = fit.starts + fresh.starts
        return fresh
    return fit


def _converge(ctx, null, fits, *, fit_frames, options):
    """(null, fits) after every model may start from the best state any model found: the null
    from the candidates' shared parameters, then each candidate that still fits worse from the
    best model's, then the null once more if those moved the shared parameters further."""
    null = converge_null(ctx, null, fits, fit_frames=fit_frames, options=options)
    fits = converge_candidates(ctx, null, fits, fit_frames=fit_frames, options=options)
    if any(f.started_from for f in fits):
        null = converge_null(ctx, null, fits, fit_frames=fit_frames, options=options)
    return null, fits


def diagnose_run(
    run_dir: str | Path,
    *,
    budget: str | Budget = "small",
    simulator_overrides: dict | None = None,
    say=print,
) -> dict:
    """Diagnose a finished run folder; writes diagnosis.json / diagnosis.md there and returns
    the diagnosis as a dict."""
    t_start = time.perf_counter()
    report = say

    def say(message: str) -> None:
        report(f"{message} [{time.perf_counter() - t_start:.0f} s]")

    ctx = load_run(run_dir, simulator_overrides=simulator_overrides)
    section = ctx.recipe.get("diagnose", None)
    budget = resolve_budget(budget, section)
    allowed_names = list(section.terms) if section is not None and section.terms else None
    excluded_names = set(section.exclude) if section is not None else set()
    fit_frames, heldout = split_frames(ctx.observed_frames, ctx.n_frames, budget.heldout_fraction)
    key = diagnosis_key(
        ctx.run_dir,
        budget=budget.__dict__,
        fit_frames=fit_frames,
        heldout=heldout,
        recipe=ctx.recipe,
        simulator_overrides=simulator_overrides,
    )
    steps = DiagnosisSteps(ctx.run_dir, key, say=say)

    say(f"locating the mismatch over {ctx.observed_frames} observed frames")
    location = steps.get("locate", lambda: locate(ctx))
    before = frame_errors(ctx, ctx.identified_rollout())
    result = {
        "run_dir": str(ctx.run_dir.root),
        "frames": {"fit": fit_frames, "heldout": heldout, "observed": ctx.observed_frames},
        "location": location.summary,
        "budget": budget.__dict__,
    }
    screens, fits, evidence, errors, accepted = [], [], [], {"identified": before}, None
    rule = DecideOptions(bootstrap=budget.bootstrap)
    result["rule"] = dict(rule.__dict__)
    if location.significant:
        candidates, skipped = build_candidates(ctx)
        if allowed_names is not None:
            skipped += [
                f"{c.name}: not in the recipe's diagnose.terms"
                for c in candidates
                if c.name not in allowed_names
            ]
            candidates = [c for c in candidates if c.name in allowed_names]
        skipped += [
            f"{c.name}: in the recipe's diagnose.exclude"
            for c in candidates
            if c.name in excluded_names
        ]
        candidates = [c for c in candidates if c.name not in excluded_names]
        say(f"screening {len(candidates)} candidate effects in regimes {location.flagged_regimes}")
        screens = steps.get(
            "screen",
            lambda: screen(
                ctx,
                candidates,
                flagged_regimes=location.flagged_regimes,
                fit_frames=fit_frames,
                residuals=location.residuals,
                regimes=location.regimes,
            ),
        )
        kept = choose_refits(screens, budget.max_candidates)
        refit_options = RefitOptions(
            iterations=budget.iterations,
            settle=budget.settle,
            polish=budget.polish,
            velocity_lr=budget.velocity_lr,
        )
        say(f"refitting the null model and {[s.candidate.name for s in kept]}")
        null_start = regression_estimate(
            ctx, None, location.residuals, location.regimes, fit_frames
        )
        null = steps.get(
            "refit-null",
            lambda: refit(
                ctx,
                None,
                fit_frames=fit_frames,
                starts=null_starts(null_start),
                options=refit_options,
            ),
        )
        fits = [
            steps.get(
                f"refit-{s.candidate.name}",
                lambda s=s: refit(
                    ctx,
                    s.candidate,
                    fit_frames=fit_frames,
                    starts=refit_starts(s, budget.starts, far_start=budget.far_start),
                    options=refit_options,
                ),
            )
            for s in kept
        ]
        if budget.reidentify:
            say("identifying the null model and each candidate afresh on the fit frames")
            schedule = ReidentifyOptions.from_recipe(ctx.recipe.identify)
            null = steps.get(
                "fresh-null", lambda: _better(null, ctx, None, None, fit_frames, schedule)
            )
            fits = [
                steps.get(
                    f"fresh-{s.candidate.name}",
                    lambda fit=fit, s=s: _better(
                        fit, ctx, s.candidate, refit_starts(s, 1)[0][0], fit_frames, schedule
                    ),
                )
                for fit, s in zip(fits, kept)
            ]
            fresh = [f.name for f in [null, *fits] if f.reidentified]
            say(f"identified afresh, better than refitted: {fresh or 'none'}")
        null, fits = steps.get(
            "converged",
            lambda: _converge(ctx, null, fits, fit_frames=fit_frames, options=refit_options),
        )
        continued = [f"{f.name} from {f.started_from}" for f in fits if f.started_from]
        if continued:
            say(f"refitted again from the best model's shared parameters: {continued}")
        if null.started_from is not None:
            say(f"the null model refitted again from {null.started_from}'s shared parameters")
        for fit in [null, *fits]:  # kept as evidence (``model.predict``), not a crash
            if fit.diverged is not None:
                say(f"the prediction of {fit.name} diverged: {fit.diverged}")
        evidence, model_errors = decide(
            ctx,
            null,
            fits,
            fit_frames=fit_frames,
            heldout_frames=heldout,
            options=rule,
        )
        errors.update(model_errors)
        result["resolution_floor"] = resolution_floor(ctx, null.params)
        # every candidate that passed the held-out and BIC tests gets its interval (recorded,
        # and tested where the rule requires it to exclude zero)
        by_name = {f.name: f for f in fits}
        bounds = {
            e.name: coefficient_interval(ctx, by_name[e.name], fit_frames=fit_frames)
            for e in evidence
            if e.passes_heldout and e.passes_bic
        }
        evidence = apply_interval_test(
            evidence, {n: [list(p) for p in zip(*b)] for n, b in bounds.items()}, rule
        )
        # and every candidate still standing has its own effect measured against the floor
        effects = {
            e.name: measure_effect(ctx, by_name[e.name], result["frames"])
            for e in evidence
            if e.accepted
        }
        floor = summarise_floor(result["resolution_floor"], result["frames"])
        evidence = apply_effect_test(
            evidence, {n: v for n, v in effects.items() if v is not None}, floor, rule
        )
        if evidence and evidence[0].accepted:
            accepted = by_name[evidence[0].name]
            accepted_interval = bounds[accepted.name]
        result["skipped_candidates"] = skipped
        result["null"] = null
    result["verdict"] = verdict(location.significant, evidence)
    result["screening"] = [s.to_json() for s in screens]
    result["evidence"] = [e.to_json() for e in evidence]
    result["fits"] = fits
    result["accepted"] = accepted
    result["interval"] = accepted_interval if accepted is not None else None
    result["errors"] = errors
    result["time_s"] = time.perf_counter() - t_start
    result["resumed_steps"] = steps.resumed
    if steps.resumed:
        say(f"resumed from the saved steps {steps.resumed}")
    summary = write_report(ctx, location, result)
    steps.clear()
    say(
        f"verdict: {summary['verdict']}"
        + (f" ({summary['accepted']['name']})" if summary.get("accepted") else "")
    )
    return summary
