"""Stability across grid resolution: an effect is named only if a second grid finds it too.

A model that is not the recording's generator leaves a residual that depends on how the model
is discretised, and an extra coefficient can absorb a share of it: numerical damping that
changes with the cell size reads as a drag, a contact smeared over a cell as a restitution.
Such a coefficient is a property of the grid, not of the recording. So before an effect that
passed every other test is named, the null model and the effect are refitted at a second
resolution (``grid_resolution``: ``diagnose.grid_factor`` times the grid, substeps scaled and
raised until the fitted materials are stable there), from their refitted states at the first
grid, with the diagnosis's refit budget, and the effect must

(a) still pass the held-out test and the information criterion against the null there (the
    same rule, ``decide.weigh``), and
(b) give the same physical quantity on both grids: every coefficient (a wind's acceleration
    vector, a drag's coefficient, a discovered law's coefficients) within ``tolerance`` times
    the combined 95 % half-width sqrt(h1^2 + h2^2) of its intervals at the two grids
    (``interval.coefficient_interval`` at each); for a drag law also the speed exponent fitted
    to the null's residual accelerations at each grid (``equivalence.drag_from_samples``),
    within the same multiple of its intervals' combined half-width plus the exponent scan's
    step.

An effect that fails is not named: with no other accepted candidate the verdict is
"discrepancy" (the model differs from the recording, but no physical effect explains it) and
the reason, ``GRID_REASON``, is written with the check's record in diagnosis.json and the
report. Cost: the null refitted once at the second grid, then one refit and one interval per
effect checked (the accepted candidates, best first, until one is stable).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import torch

from mosiv_framework.diagnose.decide import (
    DecideOptions,
    Evidence,
    finite_or_none,
    frame_errors,
    rank_evidence,
    weigh,
)
from mosiv_framework.diagnose.equivalence import DRAG_TERMS, drag_from_samples, prefer_drag_form
from mosiv_framework.diagnose.grid_resolution import (
    Resolution,
    context_at,
    second_grid,
    second_resolution,
    simulator_resolution,
)
from mosiv_framework.diagnose.interval import coefficient_interval
from mosiv_framework.diagnose.kinematics import run_samples
from mosiv_framework.diagnose.model import Fit, refit
from mosiv_framework.errors import ConfigError
from mosiv_framework.expression import NAME as EXPRESSION
from mosiv_framework.recipes.schema import grid_option_problems

#: the reason a candidate that failed the check is not named
GRID_REASON = "not stable across grid resolution"
#: the test's name among a candidate's failed tests (``formula.failed_tests``' wording)
GRID_TEST = "stability across grid resolution"
#: the second grid over the first, unless the recipe sets ``diagnose.grid_factor``
DEFAULT_FACTOR = 0.75
#: agreement tolerance, in combined 95 % half-widths, unless set by ``diagnose.grid_tolerance``
DEFAULT_TOLERANCE = 1.0
#: step of the drag-exponent scan (``equivalence.DRAG_EXPONENTS``): the exponent's resolution
EXPONENT_STEP = 0.01
#: the fewest backtracking steps (``model.RefitOptions.polish``) that end each refit at the
#: second grid. Both refits start at the first grid's optimum, where Adam's first steps (about
#: 15 % of each coefficient) overshoot: on the small wind scene six of them never beat the
#: start, and the second grid "found" the first grid's coefficients to the last digit
GRID_POLISH = 8


@dataclass(frozen=True)
class GridOptions:
    """check: whether the check runs (the budget's ``grid_check``, or the recipe's);
    factor: the second grid over the run's; tolerance: the agreement bound in combined 95 %
    half-widths (see the module docstring)."""

    check: bool = False
    factor: float = DEFAULT_FACTOR
    tolerance: float = DEFAULT_TOLERANCE

    def __post_init__(self) -> None:
        problems = grid_option_problems(
            {"grid_check": self.check, "grid_factor": self.factor, "grid_tolerance": self.tolerance}
        )
        if problems:
            raise ConfigError(problems)


def grid_options(plan) -> GridOptions:
    """The check's options for a diagnosis (``diagnosis._Plan``): on where its budget's
    ``grid_check`` is; the factor and tolerance from the recipe's ``diagnose`` section. With
    the check on, the second grid is checked now (``second_grid``), before any refit."""
    section = plan.ctx.recipe.get("diagnose", None)
    values = {} if section is None else dict(section)
    factor, tolerance = values.get("grid_factor"), values.get("grid_tolerance")
    options = GridOptions(
        check=bool(plan.budget.grid_check),
        factor=DEFAULT_FACTOR if factor is None else factor,
        tolerance=DEFAULT_TOLERANCE if tolerance is None else tolerance,
    )
    if options.check:
        ctx = plan.ctx
        second_grid(simulator_resolution(ctx), options.factor, ctx.world, ctx.particles)
    return options


@dataclass(frozen=True)
class GridHooks:
    """What the check computes with: the context at another resolution, the refit, the
    coefficient interval and the per-frame error table (the diagnosis's own by default;
    tests replace them to drive the decision)."""

    context: Callable = context_at
    refit: Callable = refit
    interval: Callable = coefficient_interval
    errors: Callable = frame_errors
    resolution: Callable = second_resolution


@dataclass
class _Second:
    """The second grid's context, resolutions and refitted null, once per diagnosis."""

    ctx: object
    first: Resolution
    second: Resolution
    null: Fit | None = None
    errors: dict = field(default_factory=dict)


def half_width(interval: list[list[float]] | None, i: int) -> float:
    """Half the width of coefficient ``i``'s [lower, upper] (infinite where unknown)."""
    if not interval or interval[i] is None or None in interval[i]:
        return math.inf
    lower, upper = interval[i]
    return 0.5 * (float(upper) - float(lower))


def coefficient_agreement(
    names: list[str],
    first: tuple[list[float], list | None],
    second: tuple[list[float], list | None],
    tolerance: float,
) -> list[dict]:
    """Per coefficient: its value at each grid (``first``, ``second``: theta and its
    [lower, upper] pairs), the difference, the allowed difference (``tolerance`` times
    sqrt(h1^2 + h2^2) of the 95 % half-widths; infinite where an interval is unbounded; a
    second grid without an interval counts the first's half-width twice) and whether it
    agrees."""
    out = []
    for i, name in enumerate(names):
        a, b = float(first[0][i]), float(second[0][i])
        h1 = half_width(first[1], i)
        h2 = h1 if second[1] is None else half_width(second[1], i)
        allowed = tolerance * math.hypot(h1, h2)
        out.append(
            {
                "name": name,
                "first": a,
                "second": b,
                "difference": b - a,
                "allowed": finite_or_none(allowed),
                "agrees": bool(abs(b - a) <= allowed),
            }
        )
    return out


def exponent_agreement(first: dict | None, second: dict | None, tolerance: float) -> dict | None:
    """The drag exponents fitted at the two grids (``equivalence.drag_exponent`` records)
    and whether they agree (see the module docstring); None where the first grid fitted none.
    A second grid that fits none (too few samples) does not agree."""
    if first is None:
        return None
    out = {"first": first["exponent"], "first_interval": first["interval"], "second": None}
    if second is None:
        return {**out, "agrees": False}
    h1 = 0.5 * (first["interval"][1] - first["interval"][0])
    h2 = 0.5 * (second["interval"][1] - second["interval"][0])
    allowed = tolerance * math.hypot(h1, h2) + EXPONENT_STEP
    difference = second["exponent"] - first["exponent"]
    return {
        **out,
        "second": second["exponent"],
        "second_interval": second["interval"],
        "difference": difference,
        "allowed": allowed,
        "agrees": bool(abs(difference) <= allowed + 1e-12),
    }


def grid_verdict(
    weighed: Evidence | None,
    coefficients: list[dict],
    exponent: dict | None,
    diverged: str | None = None,
    *,
    require_bic: bool = True,
) -> dict:
    """The check's outcome from its parts: the effect's evidence against the null at the
    second grid (``weighed``), the ``coefficient_agreement``, the ``exponent_agreement``
    and where the refit there diverged; ``require_bic``: whether the information criterion
    at the second grid counts (``DecideOptions.grid_bic``). {"stable", "failed": the tests
    failed, "reason"}."""
    failed = []
    if diverged is not None:
        failed.append(f"at the second grid: {diverged}")
    if weighed is not None and not weighed.passes_heldout:
        failed.append("held-out test at the second grid")
    if require_bic and weighed is not None and not weighed.passes_bic:
        failed.append("information criterion at the second grid")
    differ = [c["name"] for c in coefficients if not c["agrees"]]
    if differ:
        failed.append(f"coefficients differ between the grids: {', '.join(differ)}")
    if exponent is not None and not exponent["agrees"]:
        failed.append("drag exponent differs between the grids")
    return {"stable": not failed, "failed": failed, "reason": None if not failed else GRID_REASON}


def grid_starts(fit: Fit, count: int) -> list[tuple[torch.Tensor, dict | None]]:
    """Starts of the effect's refit at the second grid: its first grid's coefficients, the
    shared parameters settled there first with the coefficients held (an empty velocity change,
    ``model.refit``), then half and one and a half times them, up to ``count``."""
    theta = fit.theta.detach().float()
    starts = [(theta, {}), (0.5 * theta, None), (1.5 * theta, None)]
    return starts[: max(1, count)]


def grid_refit_options(plan):
    """The diagnosis's refit options with at least ``GRID_POLISH`` backtracking steps."""
    options = plan.refit_options
    return replace(options, polish=max(options.polish, GRID_POLISH))


def _shared(fit: Fit):
    """The fit's free parameters without its effect (its refit's ``shared``)."""
    if fit.shared is not None:
        return fit.shared
    return fit.params if fit.candidate is None else fit.candidate.without(fit.params, fit.theta)


def _second(plan, found: dict, options: GridOptions, hooks: GridHooks, state: dict) -> _Second:
    """The second grid (``state["second"]``, made once): its resolution for the materials of
    every refitted model, its context and the null refitted there (a saved step)."""
    if "second" in state:
        return state["second"]
    ctx = plan.ctx
    first = simulator_resolution(ctx)
    fitted = [f.params for f in [found["null"], *found["fits"]]]
    cfl = float(ctx.recipe.identify.get("stiffness_cfl", 0.0) or 0.0)
    second = hooks.resolution(
        first, options.factor, world=ctx.world, particles=ctx.particles, fitted=fitted, cfl=cfl
    )
    plan.say(
        f"grid check: refitting at grid {second.grid} with {second.substeps} substeps "
        f"(the run's: {first.grid}, {first.substeps})"
    )
    ctx2 = hooks.context(ctx, second)
    null = found["null"]
    null2 = plan.steps.get(
        "grid-null",
        lambda: hooks.refit(
            ctx2,
            None,
            fit_frames=plan.fit_frames,
            starts=[(torch.zeros(0), None)],
            base=_shared(null),
            options=grid_refit_options(plan),
        ),
    )
    state["second"] = _Second(ctx2, first, second, null2, {"null": hooks.errors(ctx2, null2)})
    return state["second"]


def check_candidate(
    plan, location, rule: DecideOptions, found: dict, name: str, options, hooks, state
) -> dict:
    """The check of one accepted candidate (see the module docstring): its record, JSON-ready,
    with the grids, substeps, the evidence at the second grid, the coefficients' and (drag)
    exponent's agreement and ``grid_verdict``'s outcome."""
    fit = next(f for f in found["fits"] if f.name == name)
    first = next(e for e in found["evidence"] if e.name == name)
    grid = _second(plan, found, options, hooks, state)
    record = {
        "name": name,
        "factor": options.factor,
        "tolerance": options.tolerance,
        "grid": [grid.first.grid, grid.second.grid],
        "substeps": [grid.first.substeps, grid.second.substeps],
    }
    fit2 = hooks.refit(
        grid.ctx,
        fit.candidate,
        fit_frames=plan.fit_frames,
        starts=grid_starts(fit, plan.budget.starts),
        base=_shared(fit),
        options=grid_refit_options(plan),
    )
    if fit2.refit_diverged:  # no start got through the fit frames (``model.diverged_refit``)
        return {**record, **grid_verdict(None, [], None, diverged=fit2.diverged)}
    errors = {**grid.errors, name: hooks.errors(grid.ctx, fit2)}
    weighed = weigh(
        errors,
        null_parameters=grid.null.n_params,
        candidates=[(name, fit2.n_params - grid.null.n_params, fit2.loss)],
        fit_frames=plan.fit_frames,
        heldout_frames=plan.heldout,
        options=rule,
    )[0]
    interval = None
    if fit2.trajectory is not None:
        lower, upper = hooks.interval(grid.ctx, fit2, fit_frames=plan.fit_frames)
        interval = [[float(lo), float(hi)] for lo, hi in zip(lower, upper)]
    theta2 = fit2.theta.tolist()
    coefficients = coefficient_agreement(
        fit.candidate.coefficient_names,
        (fit.theta.tolist(), first.interval),
        (theta2, interval),
        options.tolerance,
    )
    exponent = _exponents(plan, location, found, grid, name, options.tolerance)
    from mosiv_framework.diagnose.report import saved_table  # report imports this module

    return {
        **record,
        "theta": [fit.theta.tolist(), theta2],
        "interval": [first.interval, interval],
        "value": [fit.candidate.physical(fit.theta), fit.candidate.physical(fit2.theta)],
        "heldout_drop": finite_or_none(weighed.heldout_drop),
        "heldout_spread": finite_or_none(weighed.heldout_spread),
        "delta_bic": finite_or_none(weighed.delta_bic),
        "passes_heldout": weighed.passes_heldout,
        "passes_bic": weighed.passes_bic,
        "diverged": fit2.diverged,
        "coefficients": coefficients,
        "drag_exponent": exponent,
        # what a replay re-decides the check from (``regrade_grid_check``), in mm^2
        "frame_errors_mm2": {k: saved_table(v) for k, v in errors.items()},
        "null_parameters": grid.null.n_params,
        "new_coefficients": fit2.n_params - grid.null.n_params,
        "fit_loss_m2": finite_or_none(fit2.loss),
        **grid_verdict(weighed, coefficients, exponent, require_bic=rule.grid_bic),
    }


def regrade_grid_check(
    record: dict, fit_frames: list[int], heldout_frames: list[int], rule: DecideOptions
) -> dict:
    """A saved check's record (``check_candidate``) decided again under ``rule`` from its
    second grid's saved error tables, without refitting (``replay``); a record saved without
    them, or whose refit diverged, keeps its outcome."""
    tables = record.get("frame_errors_mm2")
    if not tables or record.get("diverged") is not None:
        return record
    name = record["name"]
    from mosiv_framework.diagnose.report import loaded_table  # report imports this module

    weighed = weigh(
        {k: loaded_table(v) for k, v in tables.items()},  # mm^2: the tests are scale-free
        null_parameters=record["null_parameters"],
        candidates=[(name, record["new_coefficients"], record["fit_loss_m2"])],
        fit_frames=fit_frames,
        heldout_frames=heldout_frames,
        options=rule,
    )[0]
    verdict = grid_verdict(
        weighed,
        record.get("coefficients", []),
        record.get("drag_exponent"),
        require_bic=rule.grid_bic,
    )
    return {
        **record,
        "heldout_drop": finite_or_none(weighed.heldout_drop),
        "heldout_spread": finite_or_none(weighed.heldout_spread),
        "delta_bic": finite_or_none(weighed.delta_bic),
        "passes_heldout": weighed.passes_heldout,
        "passes_bic": weighed.passes_bic,
        **verdict,
    }


def _exponents(plan, location, found, grid: _Second, name: str, tolerance: float):
    """A drag law's ``exponent_agreement``: the exponent fitted to the null's residual
    accelerations at each grid; None for another candidate, or where the first grid fitted
    none."""
    first = (found.get("equivalent") or {}).get("drag")
    if name not in DRAG_TERMS or first is None:
        return None
    second = None
    if grid.null.trajectory is not None:
        samples = run_samples(
            grid.ctx, grid.null.trajectory, frames=plan.fit_frames, regimes=location.regimes
        )
        second = drag_from_samples(samples)
    return exponent_agreement(first, second, tolerance)


def apply_grid_checks(
    evidence: list[Evidence], checks: dict[str, dict], rule: DecideOptions, drag: dict | None
) -> list[Evidence]:
    """Each checked candidate's record and outcome (name -> ``check_candidate`` record) on
    its evidence; re-ranked as the diagnosis ranks (``rank_evidence``, then the drag form's
    preference, ``equivalence.prefer_drag_form``)."""
    for e in evidence:
        if e.name in checks:
            e.grid = checks[e.name]
            e.passes_grid = bool(checks[e.name]["stable"])
    return prefer_drag_form(rank_evidence(evidence, min_drop=rule.min_drop), drag)


def check_grid(
    plan, location, rule: DecideOptions, found: dict, options: GridOptions, hooks=None
) -> dict:
    """``found`` (``diagnosis._investigate``'s, or ``_test_formula``'s) after the check: the
    accepted candidates, best first, are checked (each a saved step) until one is stable or
    none is accepted; checks made before (``found["grid_checks"]``) are applied again, not
    repeated. ``evidence``, ``accepted``, ``interval`` and the discovered law's ``formula``
    record follow the outcome."""
    if not options.check or not found.get("evidence"):
        return found
    hooks = hooks or GridHooks()
    checks = dict(found.get("grid_checks") or {})
    state = found.setdefault("grid_state", {})
    drag = (found.get("equivalent") or {}).get("drag")
    evidence = apply_grid_checks(found["evidence"], checks, rule, drag)
    while evidence and evidence[0].accepted and evidence[0].name not in checks:
        name = evidence[0].name
        plan.say(f"grid check of {name}")
        checks[name] = plan.steps.get(
            f"grid-{name}",
            lambda name=name: check_candidate(
                plan, location, rule, found, name, options, hooks, state
            ),
        )
        outcome = "stable" if checks[name]["stable"] else "; ".join(checks[name]["failed"])
        plan.say(f"grid check of {name}: {outcome}")
        evidence = apply_grid_checks(evidence, checks, rule, drag)
    return {**found, **_outcome(found, evidence), "grid_checks": checks}


def _outcome(found: dict, evidence: list[Evidence]) -> dict:
    """``found``'s evidence, accepted fit, its interval (lower and upper lists) and the
    discovered law's record, as the ranked ``evidence`` has them."""
    top = evidence[0] if evidence and evidence[0].accepted else None
    by_name = {f.name: f for f in found["fits"]}
    out = {"evidence": evidence, "accepted": None, "interval": None}
    if top is not None:
        out["accepted"] = by_name[top.name]
        if top.interval is not None:
            out["interval"] = tuple(list(side) for side in zip(*top.interval))
    formula = found.get("formula")
    law = next((e for e in evidence if e.name == EXPRESSION), None)
    if formula and formula.get("tested") and law is not None and not law.passes_grid:
        failed = [*formula.get("failed", []), GRID_TEST]
        out["formula"] = {**formula, "accepted": False, "failed": failed}
    return out


def grid_summary(evidence: list[dict]) -> dict | None:
    """diagnosis.json's ``grid_stability``: which candidates the check ran on, which were
    stable, and the reason an unstable one was not named; None where it ran on none."""
    checked = [e for e in evidence if e.get("grid")]
    if not checked:
        return None
    unstable = [e["name"] for e in checked if not e["grid"]["stable"]]
    return {
        "checked": {e["name"]: bool(e["grid"]["stable"]) for e in checked},
        "unstable": unstable,
        "reason": GRID_REASON if unstable else None,
    }


def grid_lines(evidence: list[dict]) -> list[str]:
    """diagnosis.md's section on the check: per candidate checked, the grids, the
    coefficients at each with the allowed difference, the tests at the second grid and the
    outcome."""
    checked = [e for e in evidence if e.get("grid")]
    if not checked:
        return []
    lines = [
        "## Stability across grid resolution",
        "",
        "Before an effect is named, the null model and the effect are refitted on a second "
        "grid; the effect must pass the held-out test and the information criterion there, and "
        "each coefficient must agree between the grids within the stated multiple of the "
        "combined 95 % half-widths.",
        "",
        "| candidate | grid (substeps) | coefficient | first grid | second grid | difference "
        "| allowed | agrees |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for e in checked:
        g = e["grid"]
        where = f"{g['grid'][0]} ({g['substeps'][0]}) -> {g['grid'][1]} ({g['substeps'][1]})"
        for c in g.get("coefficients", []):
            allowed = "unbounded" if c["allowed"] is None else f"{c['allowed']:.3g}"
            lines.append(
                f"| {e['name']} | {where} | {c['name']} | {c['first']:.4g} | {c['second']:.4g} "
                f"| {c['difference']:.3g} | {allowed} | {'yes' if c['agrees'] else 'no'} |"
            )
    lines += ["", *_test_lines(checked), ""]
    for e in checked:
        g = e["grid"]
        if g["stable"]:
            lines.append(f"- `{e['name']}`: stable across grid resolution.")
        else:
            lines.append(f"- `{e['name']}` is not named: {GRID_REASON} ({'; '.join(g['failed'])}).")
    return lines + [""]


def _test_lines(checked: list[dict]) -> list[str]:
    """The held-out drop and delta BIC of each checked candidate at both grids: why an effect
    that wins at the run's grid can still fail at the second one."""

    def number(value, form: str) -> str:
        return "-" if value is None else format(value, form)

    lines = [
        "| candidate | held-out drop, first / second grid | delta BIC, first / second grid |",
        "|---|---|---|",
    ]
    for e in checked:
        g = e["grid"]
        drops = f"{number(e.get('heldout_drop'), '.1%')} / {number(g.get('heldout_drop'), '.1%')}"
        bics = f"{number(e.get('delta_bic'), '.3g')} / {number(g.get('delta_bic'), '.3g')}"
        lines.append(f"| {e['name']} | {drops} | {bics} |")
    return lines
