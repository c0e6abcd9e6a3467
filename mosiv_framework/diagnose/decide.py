"""Step 4 of a diagnosis: accept a candidate only on evidence that extra parameters cannot game.

Every model (the null and each candidate) was refitted on the fit frames only. A candidate is
accepted when it passes all of these tests (docs/DIAGNOSIS.md explains the rule and the suite
results it was chosen on):

- held-out: on the frames no refit saw (held-out blocks of the observed window and the future
  frames) its Chamfer error is lower than the refitted null's by more than ``z`` bootstrap
  standard deviations, resampling (object, time block) units;
- effect size: that drop is at least ``min_drop`` of the null's held-out error. A model that
  is not exactly the generator's leaves a small systematic residual that any extra coefficient
  absorbs a little of, consistently across views and blocks; missing physics worth naming
  explains a large share of the error;
- information criterion: on the fit frames, BIC = n log(mean excess error) + p log n is lower
  with the candidate than without by more than ``bic_margin`` (p free parameters; the excess
  error is the Chamfer above frame 0's, which no dynamics can remove; n counts (object, time
  block) units, the units the bootstrap resamples, because errors of consecutive frames of a
  smooth path are correlated);
- interval (``require_nonzero``): the candidate's 95 % coefficient interval excludes "absent"
  (zero) on some coefficient, i.e. the effect is there at all;
- own effect (``min_effect``, off by default): the candidate's effect on the fit frames (its
  model against the same parameters with the effect off, ``effect``) reaches that many
  resolution floors (``floor``); it is always recorded.

Among accepted candidates, one that contains another accepted one as a special case (a wind
along g is a change of gravity's magnitude: ``candidates.SPECIAL_CASES``) is named only if it
explains at least ``min_drop`` of the null's held-out error beyond the special case; otherwise
the special case, with fewer coefficients, ranks first (``prefer_special_cases``).

Then the physical-evidence tests (``physical``): a body force's coefficient must agree across
objects, and every candidate must beat a per-object smooth correction of the null (the
nuisance model) on the held-out frames.

Verdicts: "missing physics" (a candidate passed every test), "discrepancy" (a candidate
improved the model but a generic per-object correction explains as much, or its coefficient
differs between objects, or refitted on a second grid it loses or its coefficient moves
(``grid_stability``): the model differs from the recording, but no physical effect explains
it), "unexplained" (the residual is above the noise floor and no candidate improved the
model), "no missing physics" (the residual is at noise level).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from mosiv_framework.diagnose.context import RunContext
from mosiv_framework.diagnose.effect import resolved
from mosiv_framework.diagnose.locate import object_residuals
from mosiv_framework.diagnose.model import Fit

VERDICTS = ("missing physics", "discrepancy", "unexplained", "no missing physics")


@dataclass(frozen=True)
class DecideOptions:
    """The decision rule. Every threshold here must be chosen on a development set (suite
    entries re-decided with ``mosiv diagnose-suite --replay``), never on the scenes it is
    reported on.

    bootstrap: resamples; block: frames per time block; z: bootstrap standard deviations
    the held-out drop must exceed; min_drop: the smallest held-out drop (fraction of the
    null's error) worth naming; bic_margin: how far below the null's a candidate's BIC must
    lie; seed: resampling seed; require_nonzero: see the module docstring; nuisance_degree,
    nuisance_min_drop, consistency_level: the physical-evidence tests (``physical``)."""

    bootstrap: int = 200
    block: int = 2
    z: float = 2.0
    min_drop: float = 0.2
    bic_margin: float = 0.0
    seed: int = 0
    #: accept only a term whose 95 % coefficient interval excludes zero on some coefficient
    require_nonzero: bool = True
    #: accept only a term whose own effect on the fit frames reaches this many resolution
    #: floors (``effect.resolved``); 0, the default, records the effect without testing it
    min_effect: float = 0.0
    #: degree of the nuisance model's per-object time polynomial (0: no nuisance test)
    nuisance_degree: int = 2
    #: the smallest held-out drop over the nuisance model (fraction of its error) that wins;
    #: the effect-size margin the null is beaten by (``min_drop``)
    nuisance_min_drop: float = 0.2
    #: chi-square level of the test that a body force's coefficient agrees across objects
    consistency_level: float = 0.95
    #: a standard deviation, relative to the pooled coefficient, that the agreement test adds
    #: to each object's estimate (``physical.agreement``): another engine's bodies differ by
    #: a few percent. At 0.05 two objects' single coefficients may differ by about 14 %
    consistency_tolerance: float = 0.05
    #: whether the grid-stability check (``grid_stability``) also requires the information
    #: criterion at the second grid, or only the held-out test and the coefficients' agreement
    grid_bic: bool = True
    #: how a held-out drop summarises the (object, time block) units (``bootstrap_drop``):
    #: "log", one minus the geometric mean of their error ratios, every unit weighing alike;
    #: "sum", one minus the ratio of the summed errors, which the largest errors decide (the
    #: last frames of predictions that have all left the recording)
    heldout_statistic: str = "log"


#: the held-out statistics ``bootstrap_drop`` offers
HELDOUT_STATISTICS = ("log", "sum")
#: added to each unit's error (m^2) before a log ratio: a unit both models predict exactly
#: (frame 0's lifted state) counts as a tie, not as 0/0
LOG_RATIO_FLOOR_M2 = 1e-10


def frame_errors(ctx: RunContext, fit_or_traj) -> np.ndarray:
    """[K, T] Chamfer error (m^2) per object and frame of a fit's (or trajectory's) rollout.

    A fit whose prediction diverged (``model.Fit.diverged``) has no trajectory: its errors are
    those of the frames it reached (``Fit.reached``) and infinite after, the error of a
    prediction that does not exist. So the held-out test can never pass a diverging candidate,
    and a diverging null counts against itself, while the fit frames keep their errors for the
    information criterion."""
    if isinstance(fit_or_traj, Fit) and fit_or_traj.trajectory is None:
        table = np.full((len(ctx.object_ids), ctx.n_frames), math.inf)
        if fit_or_traj.reached is not None:
            n = min(fit_or_traj.reached.n_frames, ctx.n_frames)
            table[:, :n] = _chamfer_table(ctx, fit_or_traj.reached, n)
        return table
    traj = fit_or_traj.trajectory if isinstance(fit_or_traj, Fit) else fit_or_traj
    return _chamfer_table(ctx, traj, ctx.n_frames)


def _chamfer_table(ctx: RunContext, traj, frames: int) -> np.ndarray:
    res = object_residuals(ctx, traj, frames)
    return np.stack([res[k].chamfer for k in ctx.object_ids])


def bootstrap_drop(
    null: np.ndarray,
    cand: np.ndarray,
    *,
    block: int,
    resamples: int,
    seed: int,
    statistic: str = "log",
) -> tuple[float, float]:
    """Relative drop of the error over [K, F] held-out errors and its bootstrap standard
    deviation over (object, time block) units.

    Args:
        null, cand: the two models' errors (m^2), the reference first.
        block: frames per time block.
        resamples, seed: the bootstrap's draws and seed.
        statistic: "log": 1 - exp(mean over units of log(null / cand)), the geometric mean
            of the units' error ratios, so a unit counts by the factor it changes, not by its
            size; "sum": 1 - sum(cand) / sum(null), which the largest units decide.

    Returns:
        (drop, spread); spread is infinite with fewer than two units.
    """
    if statistic not in HELDOUT_STATISTICS:
        raise ValueError(f"statistic {statistic!r}: valid: {', '.join(HELDOUT_STATISTICS)}")
    k, f = null.shape
    blocks = [list(range(s, min(s + block, f))) for s in range(0, f, block)]
    units = [(i, b) for i in range(k) for b in blocks]
    sums = np.array([[null[i, b].sum(), cand[i, b].sum()] for i, b in units])

    if statistic == "sum":

        def drop_of(pick: np.ndarray) -> float:
            return 1.0 - sums[pick, 1].sum() / max(sums[pick, 0].sum(), 1e-300)

    else:  # each unit's log ratio once; a resample averages the drawn units' ratios
        ratios = np.log((sums[:, 0] + LOG_RATIO_FLOOR_M2) / (sums[:, 1] + LOG_RATIO_FLOOR_M2))

        def drop_of(pick: np.ndarray) -> float:
            return 1.0 - math.exp(-float(ratios[pick].mean()))

    drop = drop_of(np.arange(len(units)))
    if len(units) < 2:  # one unit has no spread to measure: no evidence either way
        return float(drop), math.inf
    rng = np.random.default_rng(seed)
    draws = [drop_of(rng.integers(0, len(units), len(units))) for _ in range(resamples)]
    return float(drop), float(np.std(draws))


def bic(errors: np.ndarray, floor: np.ndarray, n_params: int, *, block: int = 1) -> float:
    """n log(mean excess Chamfer) + p log n over [K, F] fit-frame errors (``floor`` [K, 1]),
    with n = K x ceil(F / block) independent (object, time block) units."""
    excess = np.clip(errors - floor, 1e-14, None)
    n = excess.shape[0] * math.ceil(excess.shape[1] / block)
    return n * math.log(float(excess.mean())) + n_params * math.log(n)


@dataclass
class Evidence:
    """The evidence for one candidate against the refitted null model."""

    name: str
    heldout_drop: float
    heldout_spread: float
    delta_bic: float
    passes_heldout: bool
    passes_bic: bool
    fit_loss: float
    n_new: int
    #: the candidate's refitted coefficients (None in a replay, which refits nothing)
    theta: list[float] | None = None
    #: the model ("null" or a candidate) whose shared parameters the refit was continued from
    started_from: str | None = None
    #: [lower, upper] per coefficient (95 %), computed for candidates passing the first tests
    interval: list[list[float]] | None = None
    #: the interval test (``require_nonzero``); True where not required or not computed
    passes_interval: bool = True
    #: whether the model was identified afresh rather than refitted (``reidentify``)
    reidentified: bool = False
    #: candidates that contain this one as a special case (``candidates.SPECIAL_CASES``)
    special_case_of: tuple[str, ...] = ()
    #: theta as the recipe would write it (``Candidate.physical``); a replay copies it from the
    #: file (None where an unversioned file did not record it)
    value: dict | None = None
    #: the effect's own size (``effect.summarise_effect``), measured for candidates passing
    #: the first tests
    effect: dict | None = None
    #: the effect test (``min_effect``); True where not required or not measured
    passes_effect: bool = True
    #: where the candidate's refit or prediction diverged (``model.Fit.diverged``): the
    #: simulator's place and message, the reason its held-out test failed
    diverged: str | None = None
    #: the coefficient per object and its agreement (``physical.consistency``)
    consistency: dict | None = None
    passes_consistency: bool = True
    #: held-out drop and spread against the nuisance model (``physical.judge_physical``)
    nuisance_drop: float | None = None
    nuisance_spread: float | None = None
    passes_nuisance: bool = True
    #: the check at a second grid resolution (``grid_stability.check_candidate``'s record)
    grid: dict | None = None
    #: its outcome; True where it did not run (off, or the candidate was not accepted)
    passes_grid: bool = True

    @property
    def explains(self) -> bool:
        """Whether the candidate improves the model (every test but the physical ones)."""
        return (
            self.passes_heldout and self.passes_bic and self.passes_interval and self.passes_effect
        )

    @property
    def accepted(self) -> bool:
        return (
            self.explains and self.passes_consistency and self.passes_nuisance and self.passes_grid
        )

    def to_json(self) -> dict:
        return {
            "name": self.name,
            # an infinite or undefined number (a diverged prediction, one resampling unit) is
            # written as null: diagnosis.json stays strict JSON
            "heldout_drop": finite_or_none(self.heldout_drop),
            "heldout_spread": finite_or_none(self.heldout_spread),
            "delta_bic": finite_or_none(self.delta_bic),
            "passes_heldout": self.passes_heldout,
            "passes_bic": self.passes_bic,
            "accepted": self.accepted,
            # infinite where the refit diverged (``model.diverged_refit``); None in a replay of
            # such a file
            "fit_loss_m2": None if self.fit_loss is None else finite_or_none(self.fit_loss),
            "new_coefficients": self.n_new,
            "theta": self.theta,
            "started_from": self.started_from,
            "interval": self.interval,
            "passes_interval": self.passes_interval,
            "reidentified": self.reidentified,
            "special_case_of": list(self.special_case_of),
            "value": self.value,
            "effect": self.effect,
            "passes_effect": self.passes_effect,
            "diverged": self.diverged,
            "consistency": self.consistency,
            "passes_consistency": self.passes_consistency,
            "nuisance_drop": None
            if self.nuisance_drop is None
            else finite_or_none(self.nuisance_drop),
            "nuisance_spread": None
            if self.nuisance_spread is None
            else finite_or_none(self.nuisance_spread),
            "passes_nuisance": self.passes_nuisance,
            "grid": self.grid,
            "passes_grid": self.passes_grid,
        }


def finite_or_none(x: float) -> float | None:
    """``x`` as a float, or None for a number JSON cannot hold (a diverged prediction's inf)."""
    return float(x) if math.isfinite(x) else None


def decide(
    ctx: RunContext,
    null: Fit,
    fits: list[Fit],
    *,
    fit_frames: list[int],
    heldout_frames: list[int],
    options: DecideOptions = DecideOptions(),
) -> tuple[list[Evidence], dict[str, np.ndarray]]:
    """Evidence per candidate fit, best first (see ``rank_evidence``); also returns the
    [K, T] error tables by model name (``null`` included)."""
    errors = {"null": frame_errors(ctx, null)}
    for fit in fits:
        errors[fit.name] = frame_errors(ctx, fit)
    evidence = weigh(
        errors,
        null_parameters=null.n_params,
        candidates=[(fit.name, fit.n_params - null.n_params, fit.loss) for fit in fits],
        fit_frames=fit_frames,
        heldout_frames=heldout_frames,
        options=options,
        special_cases={
            fit.name: fit.candidate.special_case_of for fit in fits if fit.candidate is not None
        },
    )
    by_name = {fit.name: fit for fit in fits}
    for e in evidence:
        e.theta = by_name[e.name].theta.tolist()
        e.started_from = by_name[e.name].started_from
        e.reidentified = by_name[e.name].reidentified
        e.diverged = by_name[e.name].diverged
        candidate = by_name[e.name].candidate
        e.value = candidate.physical(by_name[e.name].theta) if candidate is not None else None
    return evidence, errors


def weigh(
    errors: dict[str, np.ndarray],
    *,
    null_parameters: int,
    candidates: list[tuple[str, int, float]],
    fit_frames: list[int],
    heldout_frames: list[int],
    options: DecideOptions,
    special_cases: dict[str, tuple[str, ...]] | None = None,
) -> list[Evidence]:
    """The three tests on [K, T] error tables (m^2) by model name, ``null`` among them, for each
    candidate (name, new coefficients, fit loss m^2); best first. ``special_cases`` maps a
    candidate to the candidates containing it (see ``prefer_special_cases``). Also what a
    replay of a saved diagnosis runs (``replay.py``)."""
    special_cases = special_cases or {}
    null = errors["null"]
    floor = null[:, :1]  # frame 0 is the lifted state: identical for every model
    bic_null = bic(null[:, fit_frames], floor, null_parameters, block=options.block)
    evidence = []
    # a null whose prediction diverged (``frame_errors``) is compared only on the held-out
    # frames it reached: against its infinite errors every candidate would drop them by 100 %
    # with no spread, and a control whose null blows up would name whatever keeps it stable
    judged = [f for f in heldout_frames if np.isfinite(null[:, f]).all()]
    for name, n_new, fit_loss in candidates:
        held = errors[name][:, heldout_frames]
        if np.isfinite(held).all() and judged:
            drop, spread = bootstrap_drop(
                null[:, judged],
                errors[name][:, judged],
                block=options.block,
                resamples=options.bootstrap,
                seed=options.seed,
                statistic=options.heldout_statistic,
            )
        else:  # its prediction diverged, or no held-out frame is left to judge it on
            drop, spread = -math.inf, math.inf
        n_params = null_parameters + n_new
        delta = bic(errors[name][:, fit_frames], floor, n_params, block=options.block) - bic_null
        evidence.append(
            Evidence(
                name,
                drop,
                spread,
                delta,
                passes_heldout=drop > 0 and drop > options.z * spread and drop >= options.min_drop,
                # a criterion that could not be computed (a fit frame a prediction did not
                # reach: infinite, or NaN for two) is no evidence for the candidate
                passes_bic=math.isfinite(delta) and delta < -options.bic_margin,
                fit_loss=fit_loss,
                n_new=n_new,
                special_case_of=tuple(special_cases.get(name, ())),
            )
        )
    return rank_evidence(evidence, min_drop=options.min_drop)


def excludes_zero(interval: list[list[float]]) -> bool:
    """Whether a [lower, upper]-per-coefficient box leaves out the zero vector ("absent")."""
    return any(lower > 0.0 or upper < 0.0 for lower, upper in interval)


def apply_interval_test(
    evidence: list[Evidence], intervals: dict[str, list[list[float]]], options: DecideOptions
) -> list[Evidence]:
    """Record each candidate's interval (name -> [lower, upper] per coefficient) and, under
    ``require_nonzero``, fail the candidates whose interval includes zero; re-ranked. A
    candidate without an interval (it failed an earlier test, or a replayed file did not
    record one) is left as it was."""
    for e in evidence:
        if e.name in intervals:
            e.interval = [list(map(float, pair)) for pair in intervals[e.name]]
            e.passes_interval = not options.require_nonzero or excludes_zero(e.interval)
    return rank_evidence(evidence, min_drop=options.min_drop)


def apply_effect_test(
    evidence: list[Evidence],
    effects: dict[str, dict],
    floor: dict | None,
    options: DecideOptions,
) -> list[Evidence]:
    """Record each candidate's own effect (name -> ``effect.summarise_effect``) and, where
    ``min_effect`` > 0, fail those whose effect on the fit frames is below ``min_effect``
    resolution floors (``floor``: ``floor.summarise_floor``); re-ranked. A candidate without a
    measured effect, or a diagnosis without a floor, is left as it was."""
    for e in evidence:
        if e.name in effects:
            e.effect = effects[e.name]
            e.passes_effect = options.min_effect <= 0 or resolved(
                e.effect, floor, factor=options.min_effect
            )
    return rank_evidence(evidence, min_drop=options.min_drop)


def rank_evidence(evidence: list[Evidence], *, min_drop: float = 0.0) -> list[Evidence]:
    """Accepted candidates first, ordered by the information criterion (lowest delta BIC), then
    the rejected ones by held-out drop.

    Among candidates that all pass both tests, held-out drops often differ by less than their
    bootstrap spread (e.g. quadratic drag vs material damping on a drag scene), so ranking by
    drop picks at random; BIC charges each extra coefficient, so of two equally good
    explanations the one with fewer parameters wins. Then ``prefer_special_cases``."""
    accepted = sorted((e for e in evidence if e.accepted), key=lambda e: e.delta_bic)
    rejected = sorted(
        (e for e in evidence if not e.accepted), key=lambda e: e.heldout_drop, reverse=True
    )
    return prefer_special_cases(accepted, min_drop=min_drop) + rejected


def prefer_special_cases(accepted: list[Evidence], *, min_drop: float) -> list[Evidence]:
    """``accepted`` (best first) with each special case moved ahead of an accepted candidate
    that contains it, unless the general one's held-out drop exceeds the special case's by at
    least ``min_drop`` (the effect-size test, applied to what the extra coefficients add)."""
    order = list(accepted)
    # each move puts a special case ahead of a more general model; the relation has no cycles,
    # so a pass without moves comes after at most len(order)^2 moves
    for _ in range(len(order) ** 2 + 1):
        move = next(
            (
                (i, j)
                for i, general in enumerate(order)
                for j in range(i + 1, len(order))
                if general.name in order[j].special_case_of
                and general.heldout_drop - order[j].heldout_drop < min_drop
            ),
            None,
        )
        if move is None:
            break
        i, j = move
        order.insert(i, order.pop(j))
    return order


def apply_physical_tests(
    evidence: list[Evidence],
    errors: dict[str, np.ndarray],
    consistencies: dict[str, dict | None],
    heldout_frames: list[int],
    options: DecideOptions,
) -> list[Evidence]:
    """Record and apply the physical-evidence tests (``physical.judge_physical``) to every
    candidate that improves the model, against ``errors["nuisance"]`` (if present) and the
    candidates' ``consistencies`` (name -> ``physical.consistency``); re-ranked."""
    from mosiv_framework.diagnose.physical import judge_physical

    nuisance = errors.get("nuisance") if options.nuisance_degree > 0 else None
    null = errors["null"]
    judged = [f for f in heldout_frames if np.isfinite(null[:, f]).all()]
    for e in evidence:
        e.consistency = consistencies.get(e.name, e.consistency)
        if not e.explains or e.name not in errors:
            continue
        (
            e.passes_consistency,
            e.passes_nuisance,
            e.nuisance_drop,
            e.nuisance_spread,
            e.consistency,
        ) = judge_physical(nuisance, errors[e.name], judged, e.consistency, options)
    return rank_evidence(evidence, min_drop=options.min_drop)


def verdict(significant: bool, evidence: list[Evidence]) -> str:
    if evidence and evidence[0].accepted:
        return VERDICTS[0]
    if not significant:
        return VERDICTS[3]
    return VERDICTS[1] if any(e.explains for e in evidence) else VERDICTS[2]
