"""Stability across grid resolution (diagnose/grid_stability.py, grid_resolution.py): before an
effect is named it is refitted with the null on a second grid; it must pass the held-out test
and the information criterion there, and its coefficients must agree between the grids within
the tolerance times their intervals' combined half-width.

The decision is driven through stubbed refits that return a chosen coefficient per grid (a term
whose fitted value depends on the grid becomes a "discrepancy" with the reason); one small
warp-mpm run shows a real concealed linear drag refitted at a coarser grid staying stable.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

from mosiv_framework.diagnose.candidates import _term_candidate
from mosiv_framework.diagnose.decide import (
    DecideOptions,
    Evidence,
    apply_interval_test,
    decide,
    verdict,
)
from mosiv_framework.diagnose.diagnosis import BUDGETS, resolve_budget
from mosiv_framework.diagnose.grid_resolution import (
    Resolution,
    second_grid,
    second_resolution,
    stiffness_ratio,
)
from mosiv_framework.diagnose.grid_stability import (
    GRID_REASON,
    GridHooks,
    GridOptions,
    check_grid,
    coefficient_agreement,
    exponent_agreement,
    grid_lines,
    grid_summary,
)
from mosiv_framework.diagnose.model import Fit
from mosiv_framework.errors import ConfigError
from mosiv_framework.simulation import MPMOptions
from mosiv_framework.terms import LinearDrag, Wind
from mosiv_framework.testing.shapes import block, default_params
from mosiv_framework.types import World

# shared fakes of the diagnosis tests; --import-mode=importlib leaves this folder off sys.path
HERE = Path(__file__).resolve().parent
if str(HERE) not in sys.path:
    sys.path.insert(0, str(HERE))
from diagnose_fakes import one_body_context  # noqa: E402

FIT = list(range(1, 8))
HELD = list(range(8, 12))
WORLD = World((-0.4, -0.4, 0.0), (0.4, 0.4, 0.6), gravity=(0.0, 0.0, -9.8), fps=30.0)


class _Steps:
    """``DiagnosisSteps`` without a disk: every step computed, its name recorded."""

    def __init__(self):
        self.names = []

    def get(self, name, compute):
        self.names.append(name)
        return compute()


def _plan(ctx, *, starts=2, iterations=8, polish=4):
    from mosiv_framework.diagnose.model import RefitOptions

    return SimpleNamespace(
        ctx=ctx,
        fit_frames=FIT,
        heldout=HELD,
        refit_options=RefitOptions(iterations=iterations, polish=polish),
        budget=SimpleNamespace(starts=starts),
        steps=_Steps(),
        say=lambda message, level=None: None,
    )


# ---------------------------------------------------------------- the decision, stubbed refits


def _stub_context():
    """The RunContext members the check reads before any refit: the simulator's resolution,
    the scene, the particles (2 cm apart) and the recipe's stiffness cap."""
    particles = block((-0.1, -0.1, 0.1), (0.1, 0.1, 0.3), spacing=0.02, object_id=1)
    return SimpleNamespace(
        simulator=SimpleNamespace(options=MPMOptions(grid=24, substeps=30)),
        simulator_name="fake",
        world=WORLD,
        particles=particles,
        recipe=OmegaConf.create({"identify": {"stiffness_cfl": 0.5}}),
        params=default_params(particles),
    )


class _StubModels:
    """Refits that return the coefficients asked for at each grid, and error tables in which
    the candidate beats the null by ``drop`` of its error on the held-out frames at the
    second grid (a clear win by default)."""

    def __init__(self, theta_by_grid: dict, *, drop: float = 0.75, interval_half: float = 0.05):
        self.theta_by_grid, self.drop, self.half = theta_by_grid, drop, interval_half
        self.calls = []

    def context(self, ctx, resolution):
        return SimpleNamespace(grid=resolution.grid, substeps=resolution.substeps)

    def refit(self, ctx, candidate, *, fit_frames, starts, base, options):
        self.calls.append((ctx.grid, None if candidate is None else candidate.name, starts))
        if candidate is None:
            return Fit("null", None, base, torch.zeros(0), 4e-6, 6, trajectory="rolled out")
        theta = torch.tensor(self.theta_by_grid[(candidate.name, ctx.grid)])
        return Fit(candidate.name, candidate, base, theta, 1e-6, 6 + candidate.dim, trajectory="r")

    def interval(self, ctx, fit, *, fit_frames):
        theta = fit.theta.tolist()
        return [t - self.half for t in theta], [t + self.half for t in theta]

    def errors(self, ctx, fit):
        rng = np.random.default_rng(len(fit.name))
        table = 4e-6 * (1.0 + 0.05 * rng.random((2, 12)))
        return table if fit.name == "null" else (1.0 - self.drop) * table

    def hooks(self) -> GridHooks:
        return GridHooks(
            context=self.context, refit=self.refit, interval=self.interval, errors=self.errors
        )


def _found(ctx, names=("wind",), theta=(2.5, 0.0, 0.0)):
    """A diagnosis's findings with each named candidate accepted at grid 24 (wind first)."""
    terms = {"wind": Wind(), "linear_drag": LinearDrag()}
    evidence, fits = [], []
    for i, name in enumerate(names):
        candidate = _term_candidate(terms[name])
        th = torch.tensor(theta[: candidate.dim])
        fits.append(Fit(name, candidate, ctx.params, th, 1e-6, 6 + candidate.dim))
        fits[-1].shared = ctx.params
        e = Evidence(name, 0.75, 0.02, -20.0 + 5 * i, True, True, 1e-6, candidate.dim)
        e.theta, e.interval = th.tolist(), [[t - 0.05, t + 0.05] for t in th.tolist()]
        evidence.append(e)
    null = Fit("null", None, ctx.params, torch.zeros(0), 4e-6, 6)
    return {"evidence": evidence, "fits": fits, "null": null, "equivalent": {}}


def _check(found, models, ctx, *, options=None):
    options = GridOptions(check=True) if options is None else options
    plan = _plan(ctx)
    location = SimpleNamespace(regimes=None)
    out = check_grid(plan, location, DecideOptions(bootstrap=100), found, options, models.hooks())
    return out, plan


def test_a_coefficient_stable_across_grids_is_named():
    ctx = _stub_context()
    models = _StubModels({("wind", 18): [2.49, 0.01, -0.01]})
    out, plan = _check(_found(ctx), models, ctx)
    record = out["evidence"][0].grid
    assert out["evidence"][0].accepted and verdict(True, out["evidence"]) == "missing physics"
    assert out["accepted"].name == "wind" and out["interval"][0][0] == pytest.approx(2.45)
    assert record["stable"] and record["reason"] is None and record["failed"] == []
    # the second grid is 0.75 x 24 cells, its substeps scaled with it (30 x 18 / 24 = 22.5)
    assert record["grid"] == [24, 18] and record["substeps"] == [30, 23]
    # both models refitted there, the effect from its first grid's coefficients, settled
    assert [(g, n) for g, n, _ in models.calls] == [(18, None), (18, "wind")]
    first_start = models.calls[1][2][0]
    assert first_start[0].tolist() == [2.5, 0.0, 0.0] and first_start[1] == {}
    assert plan.steps.names == ["grid-wind", "grid-null"]
    c = record["coefficients"][0]
    assert c["difference"] == pytest.approx(-0.01, abs=1e-6)
    assert c["allowed"] == pytest.approx(math.hypot(0.05, 0.05), rel=1e-4)
    assert grid_summary([e.to_json() for e in out["evidence"]])["reason"] is None


def test_a_coefficient_that_depends_on_the_grid_makes_a_discrepancy_with_the_reason():
    ctx = _stub_context()
    models = _StubModels({("wind", 18): [2.1, 0.0, 0.0]})  # 0.4 off: beyond 0.07
    out, _ = _check(_found(ctx), models, ctx)
    e = out["evidence"][0]
    assert e.explains and not e.passes_grid and not e.accepted
    assert verdict(True, out["evidence"]) == "discrepancy" and out["accepted"] is None
    assert e.grid["reason"] == GRID_REASON
    assert e.grid["failed"] == ["coefficients differ between the grids: acceleration.x"]
    as_json = [x.to_json() for x in out["evidence"]]
    assert as_json[0]["passes_grid"] is False and as_json[0]["accepted"] is False
    summary = grid_summary(as_json)
    assert summary == {"checked": {"wind": False}, "unstable": ["wind"], "reason": GRID_REASON}
    text = "\n".join(grid_lines(as_json))
    assert f"`wind` is not named: {GRID_REASON}" in text and "| acceleration.x |" in text
    # the tests at both grids, for the reader who asks why the second grid disagreed
    first, second = as_json[0], as_json[0]["grid"]
    row = next(line for line in text.splitlines() if line.startswith("| wind | ") and "%" in line)
    assert f"{first['heldout_drop']:.1%} / {second['heldout_drop']:.1%}" in row
    assert f"{first['delta_bic']:.3g} / {second['delta_bic']:.3g}" in row


def test_losing_the_held_out_test_at_the_second_grid_fails_the_check():
    ctx = _stub_context()
    models = _StubModels({("wind", 18): [2.5, 0.0, 0.0]}, drop=0.02)  # same value, no win
    out, _ = _check(_found(ctx), models, ctx)
    e = out["evidence"][0]
    assert not e.accepted and verdict(True, out["evidence"]) == "discrepancy"
    assert "held-out test at the second grid" in e.grid["failed"]
    assert all(c["agrees"] for c in e.grid["coefficients"])


def test_a_refit_that_diverges_at_the_second_grid_fails_the_check_with_its_place():
    """No start of the effect's refit at the second grid got through the fit frames
    (``model.diverged_refit``): the check fails with the simulator's place of the divergence,
    and nothing is weighed or compared there."""
    ctx = _stub_context()
    models = _StubModels({("wind", 18): [2.5, 0.0, 0.0]})
    stub_refit = models.refit
    reason = "refit diverged at object 1, frame 3, substep 2 (non-finite position)"

    def diverges(ctx, candidate, **kwargs):
        fit = stub_refit(ctx, candidate, **kwargs)
        if candidate is not None:
            fit.loss, fit.trajectory, fit.diverged = math.inf, None, reason
        return fit

    models.refit = diverges
    out, _ = _check(_found(ctx), models, ctx)
    e = out["evidence"][0]
    assert e.explains and not e.passes_grid and not e.accepted
    assert verdict(True, out["evidence"]) == "discrepancy" and out["accepted"] is None
    assert e.grid["failed"] == [f"at the second grid: {reason}"]
    assert e.grid["reason"] == GRID_REASON and "coefficients" not in e.grid


def test_the_next_accepted_candidate_is_checked_when_the_first_is_unstable():
    ctx = _stub_context()
    models = _StubModels({("wind", 18): [1.0, 0.0, 0.0], ("linear_drag", 18): [2.5]})
    found = _found(ctx, names=("wind", "linear_drag"))
    out, plan = _check(found, models, ctx)
    assert [e.name for e in out["evidence"]] == ["linear_drag", "wind"]
    assert out["accepted"].name == "linear_drag" and out["evidence"][0].grid["stable"]
    assert plan.steps.names == ["grid-wind", "grid-null", "grid-linear_drag"]
    # the null was refitted at the second grid once; a later call repeats no check
    assert [n for _, n, _ in models.calls] == [None, "wind", "linear_drag"]
    again = check_grid(
        plan, None, DecideOptions(bootstrap=100), out, GridOptions(check=True), models.hooks()
    )
    assert len(models.calls) == 3 and again["accepted"].name == "linear_drag"


def test_the_check_off_leaves_the_findings_alone():
    ctx = _stub_context()
    models = _StubModels({("wind", 18): [2.1, 0.0, 0.0]})
    found = _found(ctx)
    out, _ = _check(found, models, ctx, options=GridOptions(check=False))
    assert out is found and models.calls == [] and out["evidence"][0].accepted


def test_agreement_is_measured_in_the_intervals_combined_half_width():
    rows = coefficient_agreement(
        ["a", "b"], ([1.0, 2.0], [[0.9, 1.1], [1.0, math.inf]]), ([1.13, 9.0], None), 1.0
    )
    # a: 0.13 within hypot(0.1, 0.1) (no second interval: the first's twice); b: unbounded
    assert rows[0]["agrees"] and rows[0]["allowed"] == pytest.approx(0.1414, abs=1e-4)
    assert rows[1]["agrees"] and rows[1]["allowed"] is None
    tight = coefficient_agreement(["a"], ([1.0], [[0.9, 1.1]]), ([1.2], [[1.15, 1.25]]), 1.0)
    assert not tight[0]["agrees"]  # 0.2 > hypot(0.1, 0.05)
    loose = coefficient_agreement(["a"], ([1.0], [[0.9, 1.1]]), ([1.2], [[1.15, 1.25]]), 2.0)
    assert loose[0]["agrees"]
    first = {"exponent": 1.0, "interval": [0.9, 1.1]}
    assert exponent_agreement(first, {"exponent": 1.05, "interval": [0.95, 1.15]}, 1.0)["agrees"]
    assert not exponent_agreement(first, {"exponent": 2.0, "interval": [1.9, 2.1]}, 1.0)["agrees"]
    assert not exponent_agreement(first, None, 1.0)["agrees"]
    assert exponent_agreement(None, first, 1.0) is None


# --------------------------------------------------------- the second resolution and options


def test_substeps_scale_with_the_grid_and_rise_for_stiff_fitted_materials():
    ctx = _stub_context()
    first = Resolution(24, 30)
    soft = second_resolution(
        first, 1.5, world=WORLD, particles=ctx.particles, fitted=[ctx.params], cfl=0.5
    )
    assert soft == Resolution(36, 45)
    assert stiffness_ratio([ctx.params], 36, 45, WORLD, 0.5) <= 1.0
    stiff = default_params(ctx.particles, overrides={1: {"E": 5e6}})
    raised = second_resolution(
        first, 1.5, world=WORLD, particles=ctx.particles, fitted=[stiff], cfl=0.5
    )
    assert raised.grid == 36 and raised.substeps > 45
    assert stiffness_ratio([stiff], 36, raised.substeps, WORLD, 0.5) <= 1.0
    assert stiffness_ratio([stiff], 36, raised.substeps - 1, WORLD, 0.5) > 1.0


def test_a_second_grid_finer_than_the_particles_or_too_coarse_is_refused():
    particles = _stub_context().particles  # 2 cm apart: at most 0.8 / 0.02 = 40 cells
    with pytest.raises(ConfigError) as finer:
        second_grid(Resolution(24, 30), 2.0, WORLD, particles)
    text = str(finer.value)
    assert "diagnose.grid_factor=2" in text and "come apart" in text and "0.33 to 1.67" in text
    with pytest.raises(ConfigError, match="fewer than the simulator's 8"):
        second_grid(Resolution(24, 30), 0.25, WORLD, particles)
    with pytest.raises(ConfigError, match="the run's own grid"):
        second_grid(Resolution(24, 30), 1.01, WORLD, particles)


@pytest.mark.parametrize(
    "key, value, message",
    [
        ("grid_factor", 1.0, "diagnose.grid_factor=1.0: valid values are numbers from 0.25 to 4"),
        ("grid_factor", 5.0, "diagnose.grid_factor=5.0: valid values are numbers from 0.25 to 4"),
        ("grid_tolerance", -1.0, "diagnose.grid_tolerance=-1.0: valid values are positive"),
    ],
)
def test_recipe_grid_options_are_validated_naming_key_and_valid_values(key, value, message):
    from pathlib import Path

    from mosiv_framework.recipes import load_recipe

    recipe = Path(__file__).resolve().parents[1] / "recipes" / "diagnose_small.yaml"
    with pytest.raises(ConfigError) as err:
        load_recipe(recipe, [f"diagnose.{key}={value}"])
    assert message in str(err.value)
    with pytest.raises(ConfigError, match="diagnose.grid_factor=1"):
        GridOptions(check=True, factor=1)
    with pytest.raises(ConfigError, match="diagnose.grid_check='yes'"):
        GridOptions(check="yes")


def test_the_check_is_on_in_the_full_budget_and_a_recipe_switches_it():
    assert BUDGETS["full"].grid_check and not BUDGETS["small"].grid_check
    assert not resolve_budget("full", {"grid_check": False}).grid_check
    assert resolve_budget("small", {"grid_check": True}).grid_check


# ------------------------------------------------------------------ a real run at two grids


FPS = 24.0
DRAG = 1.5


def _thrown_context():
    """A RunContext of one block thrown without gravity under a concealed linear drag
    (warp-mpm, grid 16, 10 substeps), identified without it and 0.1 m/s off."""
    world = World((0.0, 0.0, 0.0), (1.5, 1.5, 1.5), (0.0, 0.0, 0.0), None, FPS)
    p = block((0.2, 0.7, 0.4), (0.32, 0.82, 0.52), spacing=0.03, object_id=1)
    terms = {"linear_drag": {"coefficient": DRAG}}
    truth = default_params(p, velocities={1: (2.0, 0.0, 1.0)}, terms=terms)
    identified = default_params(p, velocities={1: (1.9, 0.05, 1.05)})
    return one_body_context(world, p, truth, identified, n_frames=12, observed_frames=8)


def test_a_real_concealed_drag_stays_stable_at_a_coarser_grid():
    from mosiv_framework.diagnose.equivalence import drag_from_samples
    from mosiv_framework.diagnose.hypothesise import regression_estimate
    from mosiv_framework.diagnose.interval import coefficient_interval
    from mosiv_framework.diagnose.kinematics import run_samples
    from mosiv_framework.diagnose.locate import object_residuals
    from mosiv_framework.diagnose.model import refit

    ctx = _thrown_context()
    plan = _plan(ctx, starts=1, iterations=25, polish=10)
    candidate = _term_candidate(LinearDrag())
    regimes = {1: ["free_flight"] * 12}
    # the refit starts where the diagnosis's do: the free-flight regression's coefficient and
    # initial-velocity change (from the run's 0.1 m/s error alone the two trade off)
    residuals = object_residuals(ctx, ctx.identified_rollout(), ctx.n_frames)
    start = regression_estimate(ctx, candidate, residuals, regimes, FIT)
    null = refit(ctx, None, fit_frames=FIT, options=plan.refit_options)
    fit = refit(ctx, candidate, fit_frames=FIT, starts=[start], options=plan.refit_options)
    rule = DecideOptions(bootstrap=100)
    evidence, _ = decide(ctx, null, [fit], fit_frames=FIT, heldout_frames=HELD, options=rule)
    lower, upper = coefficient_interval(ctx, fit, fit_frames=FIT)
    evidence = apply_interval_test(evidence, {fit.name: list(zip(lower, upper))}, rule)
    assert evidence[0].accepted, evidence[0]
    drag = drag_from_samples(run_samples(ctx, null.trajectory, frames=FIT, regimes=regimes))
    found = {"evidence": evidence, "fits": [fit], "null": null, "equivalent": {"drag": drag}}
    out = check_grid(plan, SimpleNamespace(regimes=regimes), rule, found, GridOptions(check=True))
    record = out["evidence"][0].grid
    assert record["grid"] == [16, 12] and record["substeps"] == [10, 8]
    assert record["stable"], record["failed"]
    assert out["accepted"] is fit and verdict(True, out["evidence"]) == "missing physics"
    first, second = record["theta"][0][0], record["theta"][1][0]
    assert first == pytest.approx(DRAG, rel=0.05) and second == pytest.approx(DRAG, rel=0.05)
    assert record["drag_exponent"]["agrees"]
    print(
        f"\nlinear drag {first:.4f} (grid 16) {second:.4f} (grid 12), allowed "
        f"{record['coefficients'][0]['allowed']:.4f}; exponent "
        f"{record['drag_exponent']['first']} / {record['drag_exponent']['second']}; "
        f"held-out drop at grid 12 {record['heldout_drop']:.3f}, dBIC {record['delta_bic']:.1f}"
    )


def _diagnosis_file(models) -> dict:
    """diagnosis.json of the stubbed check with ``models`` at the second grid: the wind
    accepted at the first grid (a quarter of the null's error on every frame there)."""
    from mosiv_framework.diagnose.formats import DIAGNOSIS_FORMAT
    from mosiv_framework.diagnose.report import MM2, saved_table

    ctx = _stub_context()
    out, _ = _check(_found(ctx), models, ctx)
    null = models.errors(ctx, Fit("null", None, None, torch.zeros(0), 0.0, 6))
    return {
        "format": DIAGNOSIS_FORMAT,
        "verdict": verdict(True, out["evidence"]),
        "where": {"significant": True},
        "frames": {"fit": FIT, "heldout": HELD},
        "rule": dict(DecideOptions(bootstrap=100).__dict__),
        "null_parameters": 6,
        "evidence": [e.to_json() for e in out["evidence"]],
        "frame_errors_mm2": {
            "null": saved_table(null * MM2),
            "wind": saved_table(0.25 * null * MM2),
        },
        "accepted": None,
    }


def test_a_replay_keeps_the_recorded_outcome_of_the_grid_check():
    from mosiv_framework.diagnose.replay import replay_diagnosis

    saved = _diagnosis_file(_StubModels({("wind", 18): [2.1, 0.0, 0.0]}))
    replayed = replay_diagnosis(saved)
    assert replayed["verdict"] == "discrepancy" and replayed["accepted"] is None
    assert replayed["evidence"][0]["passes_heldout"] and not replayed["evidence"][0]["passes_grid"]
    assert replayed["evidence"][0]["grid"]["reason"] == GRID_REASON


class _HeldOutOnlyModels(_StubModels):
    """At the second grid the effect barely changes the fit frames (a coarser grid's own
    error dominates them) but cuts the held-out error by three quarters."""

    def errors(self, ctx, fit):
        null = super().errors(ctx, Fit("null", None, None, torch.zeros(0), 0.0, 6))
        null = null + 1e-6 * np.arange(null.shape[1])  # errors grow away from frame 0
        if fit.name == "null":
            return null
        table = null.copy()
        table[:, FIT] *= 0.98
        table[:, HELD] *= 0.25
        return table


def test_the_information_criterion_at_the_second_grid_is_a_switch_of_the_rule():
    """``DecideOptions.grid_bic``: on (the default) an effect that wins only on the held-out
    frames at the second grid fails the check; off, held-out test and agreeing coefficients
    make it stable."""
    ctx = _stub_context()
    models = _HeldOutOnlyModels({("wind", 18): [2.5, 0.0, 0.0]})
    out, _ = _check(_found(ctx), models, ctx)
    record = out["evidence"][0].grid
    assert record["passes_heldout"] and not record["passes_bic"]
    assert record["failed"] == ["information criterion at the second grid"]
    plan = _plan(ctx)
    off = check_grid(
        plan,
        SimpleNamespace(regimes=None),
        DecideOptions(bootstrap=100, grid_bic=False),
        _found(ctx),
        GridOptions(check=True),
        models.hooks(),
    )
    assert off["evidence"][0].grid["stable"] and off["accepted"].name == "wind"


def test_a_replay_decides_the_grid_check_again_from_the_second_grids_tables():
    """The check's record keeps the second grid's error tables, so ``--replay`` with another
    ``grid_bic`` re-decides it without refitting; a record without them keeps its outcome."""
    from mosiv_framework.diagnose.replay import replay_diagnosis

    saved = _diagnosis_file(_HeldOutOnlyModels({("wind", 18): [2.5, 0.0, 0.0]}))
    assert saved["verdict"] == "discrepancy"
    grid = saved["evidence"][0]["grid"]
    assert set(grid["frame_errors_mm2"]) == {"null", "wind"}
    assert replay_diagnosis(saved)["verdict"] == "discrepancy"  # the rule it ran with
    replayed = replay_diagnosis(saved, DecideOptions(bootstrap=100, grid_bic=False))
    assert replayed["verdict"] == "missing physics"
    assert replayed["accepted"]["name"] == "wind"
    assert replayed["evidence"][0]["grid"]["delta_bic"] == pytest.approx(grid["delta_bic"])
    del grid["frame_errors_mm2"]  # a record from before the tables were kept
    kept = replay_diagnosis(saved, DecideOptions(bootstrap=100, grid_bic=False))
    assert kept["verdict"] == "discrepancy"
