"""The refits' descents run together (``diagnose.descent.descend_together``): every start of
every refit rolls out in one batched differentiable simulation per step. On warp-mpm's CPU
path a batched member's trajectory and gradients are its single rollout's bit for bit, so the
refits must come out exactly as when each start descends alone."""

from __future__ import annotations

import sys
from pathlib import Path

import torch

# shared fakes of the diagnosis tests; --import-mode=importlib leaves this folder off sys.path
HERE = Path(__file__).resolve().parent
if str(HERE) not in sys.path:
    sys.path.insert(0, str(HERE))
from diagnose_fakes import spy_batches, windy_block_context  # noqa: E402

FIT = [1, 2, 3, 4]


def _windy_context():
    """The one-block windy scene of ``windy_block_context`` over the fit frames."""
    return windy_block_context(max(FIT) + 1)


def _requests(ctx):
    from mosiv_framework.diagnose.candidates import build_candidates
    from mosiv_framework.diagnose.model import RefitRequest

    candidates = {c.name: c for c in build_candidates(ctx)[0]}
    wind, drag = candidates["wind"], candidates["linear_drag"]
    return [
        # two starts, the first settling the shared parameters
        RefitRequest(wind, [(torch.tensor([0.0, 1.5, 0.0]), {}), (wind.zero(), None)]),
        RefitRequest(drag, [(drag.zero(), None)]),
        RefitRequest(None),
    ]


def _summary(fits) -> list[tuple]:
    return [(f.name, f.theta.tolist(), f.loss, f.starts, f.history) for f in fits]


def test_refits_descending_together_equal_each_start_alone(monkeypatch):
    from mosiv_framework.diagnose.model import RefitOptions, RefitRequest, refit_together

    options = RefitOptions(iterations=3, settle=2, polish=2)
    ctx = _windy_context()
    batches = spy_batches(monkeypatch, ctx.simulator)
    together = refit_together(ctx, _requests(ctx), fit_frames=FIT, options=options)
    # four starts: all four in a batch while they all go, then fewer as they end
    assert batches[0] == 4 and batches == sorted(batches, reverse=True) and len(batches) > 3

    monkeypatch.setattr(ctx.simulator, "rollout_batch", None)  # any batched call fails now
    wind_request, drag_request, null_request = _requests(ctx)

    def alone(request):
        return refit_together(ctx, [request], fit_frames=FIT, options=options)[0]

    assert _summary([together[1]]) == _summary([alone(drag_request)])
    assert _summary([together[2]]) == _summary([alone(null_request)])
    # the wind's two starts, each descending alone, end where they ended together
    wind = wind_request.candidate
    ends = [alone(RefitRequest(wind, [start])) for start in wind_request.starts]
    assert [tuple(s) for s in together[0].starts] == [tuple(e.starts[0]) for e in ends]
    best = min(ends, key=lambda f: f.loss)
    assert together[0].history == best.history and together[0].loss == best.loss
    assert together[0].theta.abs().max() > 0.1  # the wind refit moved the coefficient


def test_models_identified_afresh_together_equal_each_alone(monkeypatch):
    """``reidentify_together``: the models share the run's schedule, so they step in lockstep,
    one batched rollout per step, and each ends exactly where it ends alone."""
    from mosiv_framework.diagnose import reidentify as module
    from mosiv_framework.diagnose.candidates import build_candidates

    ctx = _windy_context()
    # the run's start (pipeline.start_vector) needs a whole recipe: start from the identified
    # state instead, frames 0-2 counted as free flight
    monkeypatch.setattr(module, "fresh_vector", lambda ctx: (ctx.parameter_vector(), 3))
    candidates = {c.name: c for c in build_candidates(ctx)[0]}
    models = [
        (None, None),
        (candidates["wind"], torch.tensor([0.0, 1.0, 0.0])),
        (candidates["linear_drag"], None),
    ]
    options = module.ReidentifyOptions(velocity_iterations=3, param_iterations=4)
    batches = spy_batches(monkeypatch, ctx.simulator)
    together = module.reidentify_together(ctx, models, fit_frames=FIT, options=options)
    assert batches and set(batches) == {3}  # every step of both phases, all three at once

    monkeypatch.setattr(ctx.simulator, "rollout_batch", None)  # any batched call fails now
    for (candidate, start), fit in zip(models, together):
        alone = module.reidentify(ctx, candidate, fit_frames=FIT, start=start, options=options)
        assert fit.reidentified and alone.reidentified
        assert fit.history == alone.history and len(fit.history) == 3 + 1 + 4 + 1
        assert fit.loss == alone.loss and torch.equal(fit.theta, alone.theta)


def test_one_after_another_gives_the_same_refits_without_a_batch(monkeypatch):
    """``diagnose.together: false`` (RefitOptions.together): every start descends alone, with
    the results of the lockstep descents; the recipe key reaches the budget."""
    from omegaconf import OmegaConf

    from mosiv_framework.diagnose.budget import resolve_budget
    from mosiv_framework.diagnose.model import RefitOptions, refit_together

    options = RefitOptions(iterations=2, settle=1)
    ctx = _windy_context()
    together = refit_together(ctx, _requests(ctx), fit_frames=FIT, options=options)
    monkeypatch.setattr(ctx.simulator, "rollout_batch", None)  # any batched call fails now
    one_by_one = RefitOptions(iterations=2, settle=1, together=False)
    apart = refit_together(ctx, _requests(ctx), fit_frames=FIT, options=one_by_one)
    assert _summary(apart) == _summary(together)
    assert resolve_budget("full").together
    assert not resolve_budget("full", OmegaConf.create({"together": False})).together


def test_a_refit_step_keeps_every_stiffness_inside_the_stability_limit():
    """After each step of a refit (``keep_in_bounds``) the P-wave speed at the current Poisson
    ratio stays below the simulator's limit, as in identification."""
    import math

    from mosiv_framework.diagnose.descent import keep_in_bounds
    from mosiv_framework.pipeline.params import ParameterVector

    limit = 15.0  # m/s
    vector = ParameterVector.create(
        {1: "elastic"},
        {1: torch.zeros(3)},
        values={1: {"E": 1e6, "nu": 0.44}},
        ground_friction=None,
    )
    vector.wave_speed_limit = limit  # given to create, the start would already be held to it
    keep_in_bounds(vector, None, torch.zeros(0), 1.0)
    p = {n: float(v) for n, v in vector.physical().objects[1].values.items()}
    speed = math.sqrt(p["E"] * (1 - p["nu"]) / ((1 + p["nu"]) * (1 - 2 * p["nu"])) / p["rho"])
    assert abs(speed - limit) <= 1e-4 * limit and abs(p["nu"] - 0.44) < 1e-6


def test_a_long_descent_says_how_far_it_has_gone(monkeypatch, caplog):
    """A refit that takes minutes (a CPU, a large scene) logs its step, the descents still
    going and the lowest loss, here at every step (interval 0)."""
    import logging

    from mosiv_framework.diagnose import descent
    from mosiv_framework.diagnose.model import RefitOptions, refit_together

    monkeypatch.setattr(descent, "PROGRESS_INTERVAL_S", 0.0)
    ctx = _windy_context()
    options = RefitOptions(iterations=2, settle=1, polish=1)
    with caplog.at_level(logging.INFO, logger=descent.__name__):
        fits = refit_together(ctx, _requests(ctx)[1:], fit_frames=FIT, options=options)
    lines = [r.getMessage() for r in caplog.records if r.name == descent.__name__]
    # one line before each pass: the steps, the polish and the last pass that only scores
    total = int(lines[0].split(" of ")[1].split(",")[0])
    assert len(lines) == total >= 3
    for step, line in enumerate(lines):
        assert line.startswith(f"descending: step {step} of {total}, 2 of 2 descents going")
    assert lines[0].endswith("lowest loss inf m^2")  # nothing rolled out yet
    lowest = float(lines[-1].split("lowest loss ")[1].split(" ")[0])
    best_before_last = min(min(f.history[:-1]) for f in fits)
    assert abs(lowest - best_before_last) <= 1e-3 * best_before_last
