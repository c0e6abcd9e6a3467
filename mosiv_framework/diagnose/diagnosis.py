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

import logging
import time
from dataclasses import dataclass
from pathlib import Path

import torch

# BUDGETS is imported for the callers that read the named budgets from here
from mosiv_framework.diagnose.budget import BUDGETS, Budget, reidentifies, resolve_budget  # noqa: F401
from mosiv_framework.diagnose.candidates import build_candidates
from mosiv_framework.diagnose.context import RunContext, load_run
from mosiv_framework.diagnose.decide import (
    DecideOptions,
    apply_effect_test,
    apply_interval_test,
    apply_physical_tests,
    decide,
    frame_errors,
    verdict,
)
from mosiv_framework.diagnose.effect import measure_effect
from mosiv_framework.diagnose.equivalence import equivalents, prefer_drag_form, told_from_lead
from mosiv_framework.diagnose.floor import resolution_floor, summarise_floor
from mosiv_framework.diagnose.formula import (
    discover_law,
    expression_candidate,
    expression_starts,
    failed_tests,
    formula_record,
    law_to_test,
    run_velocity_change,
    scene_up,
)
from mosiv_framework.diagnose.grid_stability import check_grid, grid_options
from mosiv_framework.diagnose.hypothesise import choose_refits, regression_estimate, screen
from mosiv_framework.diagnose.interval import coefficient_interval
from mosiv_framework.diagnose.kinematics import run_samples
from mosiv_framework.diagnose.locate import locate
from mosiv_framework.diagnose.model import (
    RefitOptions,
    RefitRequest,
    converge_candidates,
    converge_null,
    refit,
    refit_together,
    replaces,
)
from mosiv_framework.diagnose.physical import consistency, nuisance_errors
from mosiv_framework.diagnose.reidentify import ReidentifyOptions, reidentify_together
from mosiv_framework.diagnose.report import write_report
from mosiv_framework.diagnose.steps import DiagnosisSteps, diagnosis_key
from mosiv_framework.errors import ConfigError, SimulationDiverged

log = logging.getLogger(__name__)

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


def _better(fit, fresh):
    """``fit`` or the model re-identified afresh (``fresh``; a SimulationDiverged where that
    failed), whichever fits the fit frames better (or predicts all frames where the other
    diverged: ``model.replaces``)."""
    if isinstance(fresh, SimulationDiverged):
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


@dataclass
class _Plan:
    """What every phase of one diagnosis shares: the loaded run, the budget, the frame split,
    the saved steps and the clock its progress messages give the time of."""

    ctx: RunContext
    budget: Budget
    fit_frames: list[int]
    heldout: list[int]
    steps: DiagnosisSteps
    t_start: float

    @property
    def frames(self) -> dict:
        """The frame split as the report records it."""
        return {
            "fit": self.fit_frames,
            "heldout": self.heldout,
            "observed": self.ctx.observed_frames,
        }

    @property
    def refit_options(self) -> RefitOptions:
        return RefitOptions(
            iterations=self.budget.iterations,
            settle=self.budget.settle,
            polish=self.budget.polish,
            velocity_lr=self.budget.velocity_lr,
            together=self.budget.together,
        )

    def say(self, message: str, *, level: int = logging.INFO) -> None:
        """A progress message with the seconds since the diagnosis began."""
        log.log(level, "%s [%.0f s]", message, time.perf_counter() - self.t_start)


def _plan(run_dir, budget: str | Budget, simulator_overrides: dict | None) -> _Plan:
    """Load the run, resolve the budget against its recipe, split its frames and open the
    saved steps under a key of all of these."""
    t_start = time.perf_counter()
    ctx = load_run(run_dir, simulator_overrides=simulator_overrides)
    budget = resolve_budget(budget, ctx.recipe.get("diagnose", None))
    fit_frames, heldout = split_frames(ctx.observed_frames, ctx.n_frames, budget.heldout_fraction)
    key = diagnosis_key(
        ctx.run_dir,
        budget=budget.__dict__,
        fit_frames=fit_frames,
        heldout=heldout,
        recipe=ctx.recipe,
        simulator_overrides=simulator_overrides,
    )
    steps = DiagnosisSteps(ctx.run_dir, key)
    return _Plan(ctx, budget, fit_frames, heldout, steps, t_start)


def _select_candidates(ctx: RunContext) -> tuple[list, list[str]]:
    """The built-in candidates the recipe's ``diagnose`` section allows (``terms``, if given)
    and does not exclude (``exclude``), and why each other one was skipped."""
    section = ctx.recipe.get("diagnose", None)
    allowed = list(section.terms) if section is not None and section.terms else None
    excluded = set(section.exclude) if section is not None else set()
    candidates, skipped = build_candidates(ctx)
    if allowed is not None:
        skipped += [
            f"{c.name}: not in the recipe's diagnose.terms"
            for c in candidates
            if c.name not in allowed
        ]
        candidates = [c for c in candidates if c.name in allowed]
    skipped += [
        f"{c.name}: in the recipe's diagnose.exclude" for c in candidates if c.name in excluded
    ]
    candidates = [c for c in candidates if c.name not in excluded]
    return candidates, skipped


def _screen_candidates(plan: _Plan, location, candidates: list) -> list:
    """The screening of ``candidates`` in the flagged regimes, best first (a saved step)."""
    plan.say(f"screening {len(candidates)} candidate effects in regimes {location.flagged_regimes}")
    return plan.steps.get(
        "screen",
        lambda: screen(
            plan.ctx,
            candidates,
            flagged_regimes=location.flagged_regimes,
            fit_frames=plan.fit_frames,
            residuals=location.residuals,
            regimes=location.regimes,
        ),
    )


def _refit_models(plan: _Plan, location, kept: list) -> tuple:
    """(null, fits): the null model and each kept candidate refitted from the run's identified
    state, all their starts descending together (``refit_together``), each a saved step."""
    ctx, options = plan.ctx, plan.refit_options
    plan.say(f"refitting the null model and {[s.candidate.name for s in kept]}")
    null_start = regression_estimate(
        ctx, None, location.residuals, location.regimes, plan.fit_frames
    )
    requests = {"refit-null": RefitRequest(None, null_starts(null_start))}
    for s in kept:
        starts = refit_starts(s, plan.budget.starts, far_start=plan.budget.far_start)
        requests[f"refit-{s.candidate.name}"] = RefitRequest(s.candidate, starts)
    null, *fits = plan.steps.get_many(
        list(requests),
        lambda names: refit_together(
            ctx, [requests[n] for n in names], fit_frames=plan.fit_frames, options=options
        ),
    )
    return null, fits


def _identify_afresh(plan: _Plan, null, fits: list, kept: list) -> tuple:
    """(null, fits), each replaced by the model identified afresh on the fit frames with the
    run's schedule where that fits better (``_better``), each a saved step."""
    ctx, fit_frames = plan.ctx, plan.fit_frames
    schedule = ReidentifyOptions.from_recipe(ctx.recipe.identify)
    # step name -> (the refitted model, the candidate, its coefficients' start); the null
    # first, then the candidates the budget identifies afresh, at their places in ``fits``
    models = {"fresh-null": (null, None, None)}
    places = []
    for place, (fit, s) in enumerate(zip(fits, kept)):
        if reidentifies(plan.budget, s.candidate.name):
            models[f"fresh-{s.candidate.name}"] = (fit, s.candidate, refit_starts(s, 1)[0][0])
            places.append(place)
    which = "the null model and each candidate" if places else "the null model"
    plan.say(f"identifying {which} afresh on the fit frames")

    def afresh(names: list[str]) -> list:
        wanted = [models[n] for n in names]
        fresh = reidentify_together(
            ctx,
            [(c, start) for _, c, start in wanted],
            fit_frames=fit_frames,
            options=schedule,
            together=plan.budget.together,
        )
        return [_better(fit, new) for (fit, _, _), new in zip(wanted, fresh)]

    null, *fresh_fits = plan.steps.get_many(list(models), afresh)
    fits = list(fits)  # the candidates not identified afresh keep their refits
    for place, fit in zip(places, fresh_fits):
        fits[place] = fit
    fresh = [f.name for f in [null, *fits] if f.reidentified]
    plan.say(f"identified afresh, better than refitted: {fresh or 'none'}")
    return null, fits


def _converge_models(plan: _Plan, null, fits: list) -> tuple:
    """(null, fits) after ``_converge`` (a saved step), with what moved said."""
    null, fits = plan.steps.get(
        "converged",
        lambda: _converge(
            plan.ctx, null, fits, fit_frames=plan.fit_frames, options=plan.refit_options
        ),
    )
    continued = [f"{f.name} from {f.started_from}" for f in fits if f.started_from]
    if continued:
        plan.say(f"refitted again from the best model's shared parameters: {continued}")
    if null.started_from is not None:
        plan.say(f"the null model refitted again from {null.started_from}'s shared parameters")
    for fit in [null, *fits]:  # kept as evidence (``model.predict``), not a crash
        if fit.diverged is not None:
            plan.say(
                f"the prediction of {fit.name} diverged: {fit.diverged}", level=logging.WARNING
            )
    return null, fits


def _physical(plan: _Plan, location, null, fits: list, evidence, errors, rule) -> tuple:
    """(evidence, samples): the physical-evidence tests (``physical``) on ``evidence``, with the
    nuisance model's table added to ``errors``; the residual-acceleration samples of the
    null on the fit frames, which the equivalences and the discovery read too."""
    ctx = plan.ctx
    traj = null.trajectory if null.trajectory is not None else ctx.identified_rollout()
    samples = run_samples(ctx, traj, frames=plan.fit_frames, regimes=location.regimes)
    consistencies = {
        f.name: consistency(
            f.candidate,
            samples,
            level=rule.consistency_level,
            tolerance=rule.consistency_tolerance,
        )
        for f in fits
    }
    if rule.nuisance_degree > 0:
        table = nuisance_errors(ctx, null.trajectory, plan.fit_frames, rule.nuisance_degree)
        if table is not None:
            errors["nuisance"] = table
    evidence = apply_physical_tests(evidence, errors, consistencies, plan.heldout, rule)
    return evidence, samples


def _judge(plan: _Plan, location, null, fits: list, rule: DecideOptions) -> dict:
    """The evidence for each candidate against the null (``decide``), the interval test on
    those passing the held-out and BIC tests, then the own-effect test on those still
    standing; also the error tables, the null's resolution floor and the accepted fit with
    its interval."""
    ctx = plan.ctx
    evidence, model_errors = decide(
        ctx, null, fits, fit_frames=plan.fit_frames, heldout_frames=plan.heldout, options=rule
    )
    floor_raw = resolution_floor(ctx, null.params)
    # every candidate that passed the held-out and BIC tests gets its interval (recorded,
    # and tested where the rule requires it to exclude zero)
    by_name = {f.name: f for f in fits}
    bounds = {
        e.name: coefficient_interval(ctx, by_name[e.name], fit_frames=plan.fit_frames)
        for e in evidence
        if e.passes_heldout and e.passes_bic
    }
    evidence = apply_interval_test(
        evidence, {n: [list(p) for p in zip(*b)] for n, b in bounds.items()}, rule
    )
    # and every candidate still standing has its own effect measured against the floor
    effects = {
        e.name: measure_effect(ctx, by_name[e.name], plan.frames) for e in evidence if e.accepted
    }
    floor = summarise_floor(floor_raw, plan.frames)
    evidence = apply_effect_test(
        evidence, {n: v for n, v in effects.items() if v is not None}, floor, rule
    )
    evidence, samples = _physical(plan, location, null, fits, evidence, model_errors, rule)
    forms = equivalents(evidence, model_errors, samples, ctx.world.gravity, plan.heldout, rule)
    evidence = prefer_drag_form(evidence, forms.get("drag"))
    accepted = by_name[evidence[0].name] if evidence and evidence[0].accepted else None
    return {
        "samples": samples,
        "equivalent": forms,
        "evidence": evidence,
        "errors": model_errors,
        "resolution_floor": floor_raw,
        "accepted": accepted,
        "interval": bounds[accepted.name] if accepted is not None else None,
    }


def _investigate(plan: _Plan, location, rule: DecideOptions) -> dict:
    """Steps 2-4 on a significant residual: candidates, screening, refits, decision."""
    candidates, skipped = _select_candidates(plan.ctx)
    screens = _screen_candidates(plan, location, candidates)
    kept = choose_refits(screens, plan.budget.max_candidates)
    null, fits = _refit_models(plan, location, kept)
    if plan.budget.reidentify != "none":
        null, fits = _identify_afresh(plan, null, fits, kept)
    null, fits = _converge_models(plan, null, fits)
    return {
        "screens": screens,
        "fits": fits,
        "skipped_candidates": skipped,
        "null": null,
        **_judge(plan, location, null, fits, rule),
    }


def _test_formula(plan: _Plan, location, rule: DecideOptions, found: dict, discovered) -> dict:
    """``found`` with the discovered law as one more candidate (an ``expression``): refitted
    from the null's state at the discovered coefficients (and identified afresh in the full
    budget), every model converged again with it, and all judged anew (``_judge``); its
    record (``found["formula"]``) gives the law tested and the refitted one with intervals."""
    ctx = plan.ctx
    law, reason = law_to_test(ctx, found["samples"], discovered)
    candidate = None if law is None else expression_candidate(
        law, up=scene_up(ctx.world), ground_height=ctx.world.ground_height
    )  # fmt: skip
    if candidate is None:
        return {**found, "formula": {"tested": None, "skipped": [reason] if reason else []}}
    plan.say(f"testing the discovered law as a model: {law['formula']}")
    null = found["null"]
    fit_frames = plan.fit_frames
    dv = run_velocity_change(ctx, candidate, null.trajectory, location.regimes, fit_frames)
    fit = plan.steps.get(
        "refit-expression",
        lambda: refit(
            ctx,
            candidate,
            fit_frames=fit_frames,
            starts=expression_starts(candidate, plan.budget.starts, dv),
            base=null.shared,
            options=plan.refit_options,
        ),
    )
    if reidentifies(plan.budget, candidate.name):
        schedule = ReidentifyOptions.from_recipe(ctx.recipe.identify)
        fit = plan.steps.get(
            "fresh-expression",
            lambda: _better(
                fit,
                reidentify_together(
                    ctx,
                    [(candidate, candidate.base["start"])],
                    fit_frames=plan.fit_frames,
                    options=schedule,
                )[0],
            ),
        )
    null, fits = plan.steps.get(
        "converged-expression",
        lambda: _converge(
            ctx, null, [*found["fits"], fit], fit_frames=plan.fit_frames,
            options=plan.refit_options,
        ),
    )  # fmt: skip
    judged = _judge(plan, location, null, fits, rule)
    mine = next(f for f in fits if f.name == candidate.name)
    evidence = next(e for e in judged["evidence"] if e.name == candidate.name)
    refitted = formula_record(candidate, mine.theta, evidence.interval)
    record = {
        "tested": law["formula"],
        "refitted": None if mine.refit_diverged else refitted,  # ``model.diverged_refit``
        "accepted": evidence.accepted,
        "failed": failed_tests(evidence),
        "diverged": mine.diverged,
    }
    return {**found, **judged, "null": null, "fits": fits, "formula": record}


def diagnose_run(
    run_dir: str | Path,
    *,
    budget: str | Budget = "small",
    simulator_overrides: dict | None = None,
) -> dict:
    """Diagnose a finished run folder; writes diagnosis.json / diagnosis.md there and returns
    the diagnosis as a dict. Progress is logged (INFO) by this module's logger.

    Args:
        run_dir: a folder written by ``mosiv run``.
        budget: a name of ``BUDGETS`` or a ``Budget``; the recipe's ``diagnose`` section may
            change it (``resolve_budget``).
        simulator_overrides: simulator options replacing the recipe's (e.g. the device).
    """
    plan = _plan(run_dir, budget, simulator_overrides)
    ctx, grid = plan.ctx, grid_options(plan)  # a bad diagnose.grid_factor fails before refits
    plan.say(f"locating the mismatch over {ctx.observed_frames} observed frames")
    location = plan.steps.get("locate", lambda: locate(ctx))
    before = frame_errors(ctx, ctx.identified_rollout())
    rule = DecideOptions(bootstrap=plan.budget.bootstrap)
    result = {
        "run_dir": str(ctx.run_dir.root),
        "frames": plan.frames,
        "location": location.summary,
        "budget": plan.budget.__dict__,
        "rule": dict(rule.__dict__),
    }
    found = {"screens": [], "fits": [], "evidence": [], "errors": {}, "accepted": None}
    if location.significant:
        found = check_grid(plan, location, rule, _investigate(plan, location, rule), grid)
        result.update(
            resolution_floor=found["resolution_floor"],
            skipped_candidates=found["skipped_candidates"],
            null=found["null"],
        )
    if location.significant and verdict(True, found["evidence"]) != "missing physics":
        # what no candidate explains, as a formula of the objects' state (``discover``),
        # then that formula as a model, judged like the library terms (``formula``)
        result["discovered"] = discover_law(ctx, found["samples"])
        found = _test_formula(plan, location, rule, found, result["discovered"])
        found = check_grid(plan, location, rule, found, grid)
        result["formula"] = found["formula"]
        result["skipped_candidates"] += found["formula"].get("skipped", [])
    result["verdict"] = verdict(location.significant, found["evidence"])
    result["equivalent"] = told_from_lead(found.get("equivalent"), found["evidence"])
    result["screening"] = [s.to_json() for s in found["screens"]]
    result["evidence"] = [e.to_json() for e in found["evidence"]]
    result["fits"] = found["fits"]
    result["accepted"] = found["accepted"]
    result["interval"] = found.get("interval")
    result["errors"] = {"identified": before, **found["errors"]}
    result["time_s"] = time.perf_counter() - plan.t_start
    result["resumed_steps"] = plan.steps.resumed
    if plan.steps.resumed:
        plan.say(f"resumed from the saved steps {plan.steps.resumed}")
    summary = write_report(ctx, location, result)
    plan.steps.clear()
    accepted = summary.get("accepted")
    plan.say(f"verdict: {summary['verdict']}" + (f" ({accepted['name']})" if accepted else ""))
    return summary
