"""Unit tests of the diagnosis's candidates and screening: the plasticity candidate, the
ladder screen, the centroid regression and the probes of a flat loss, on fake runs with known
answers (no simulator)."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from mosiv_framework.diagnose.hypothesise import bic_gain

# shared fakes of the diagnosis tests; --import-mode=importlib leaves this folder off sys.path
HERE = Path(__file__).resolve().parent
if str(HERE) not in sys.path:
    sys.path.insert(0, str(HERE))
from diagnose_fakes import _elastic_pair_params, _FakeContext, _OneByOneLosses  # noqa: E402

# --------------------------------------------------------------------------------------------
# plasticity candidate


def _plasticity_candidate(k=1):
    from mosiv_framework.diagnose.candidates import PLASTIC_REGIMES, PLASTICITY_LADDER, Candidate

    return Candidate(
        "plasticity",
        "plasticity",
        ["yield_decades_below_bound"],
        ["decade"],
        torch.tensor([0.0]),
        torch.tensor([5.0]),
        torch.tensor([0.25]),
        PLASTIC_REGIMES,
        "test",
        base={"object": k},
        ladder=PLASTICITY_LADDER,
    )


def test_plasticity_candidate_turns_the_elastic_body_into_plasticine_and_back():
    """theta decades below the plasticine bound set the yield stress; ``without`` restores the
    elastic body exactly, and the other body is never touched."""
    from mosiv_framework.laws import get_law

    params = _elastic_pair_params()
    c = _plasticity_candidate()
    theta = torch.tensor([2.5], requires_grad=True)
    plastic = c.apply(params, theta)
    assert plastic.objects[1].family == "plasticine"
    bound = get_law("plasticine").param("yield_stress").upper
    assert float(plastic.objects[1].values["yield_stress"].detach()) == pytest.approx(
        bound * 10**-2.5
    )
    assert float(plastic.objects[1].values["E"]) == 5e4
    assert plastic.objects[2] is params.objects[2]
    # differentiable in theta: d yield / d theta = -ln(10) yield
    plastic.objects[1].values["yield_stress"].backward()
    assert float(theta.grad) == pytest.approx(-math.log(10) * bound * 10**-2.5, rel=1e-5)
    back = c.without(plastic, theta.detach())
    assert back.objects[1].family == "elastic"
    assert set(back.objects[1].values) == set(params.objects[1].values)
    assert c.physical(torch.tensor([2.0])) == {"object": 1, "yield_stress": pytest.approx(1e4)}
    get_law("plasticine").validate(
        {
            n: float(v.detach())
            for n, v in plastic.objects[1].values.items()
            if n not in ("rho", "friction")
        }
    )


def test_ladder_screen_picks_the_lowest_rung_and_scores_it():
    """A candidate with a ladder is probed at each rung (no gradient): the rung with the lowest
    loss is the predicted coefficient; a ladder that never beats the base predicts nothing."""
    from mosiv_framework.diagnose.hypothesise import _screen_ladder

    c = _plasticity_candidate()

    class FakeContext(_OneByOneLosses):
        identified = _elastic_pair_params()
        object_ids = [1, 2]

        def __init__(self, losses):
            self.losses = losses  # yield stress (Pa) -> loss

        def rollout(self, params, *, frames):
            return float(params.objects[1].values["yield_stress"])

        def loss(self, yield_stress, frames):
            return torch.tensor(self.losses(yield_stress))

    # the loss is lowest near 1e4 Pa (theta = 2)
    ctx = FakeContext(lambda y: 1.0 + (math.log10(y) - 4.0) ** 2)
    result = _screen_ladder(ctx, c, base=5.0, n=10, fit_frames=[1, 2])
    assert result.allowed and result.theta.tolist() == [1.75]
    assert result.drop_fraction == pytest.approx(1 - (1.0 + 0.25**2) / 5.0)
    assert result.score == pytest.approx(bic_gain(result.drop_fraction, n=10, dim=1))
    flat = _screen_ladder(FakeContext(lambda y: 6.0), c, base=5.0, n=10, fit_frames=[1, 2])
    assert flat.drop_fraction == 0.0 and flat.theta.tolist() == [0.0]
    assert flat.score == -math.inf


# --------------------------------------------------------------------------------------------
# regression and probes


def test_regression_drop_scores_the_model_at_the_regression_estimate():
    """The screen's second estimate of a candidate's worth: the loss at its regression estimate
    (coefficients and velocity change together), relative to what the velocity change alone
    reaches; a diverged rollout earns nothing."""

    from mosiv_framework.diagnose.candidates import build_candidates
    from mosiv_framework.diagnose.hypothesise import regression_drop
    from mosiv_framework.errors import SimulationDiverged

    wind_true = torch.tensor([0.0, 2.5, 0.0])
    v_true = torch.tensor([0.3, 0.0, 0.0])

    class FakeContext(_FakeContext):
        diverge = False

        def rollout(self, params, *, frames):
            if self.diverge:
                raise SimulationDiverged(object_id=1, frame=1, substep=0, reason="", advice="")
            return params

        def loss(self, params, frames):
            wind = params.terms.get("wind", {}).get("acceleration", torch.zeros(3))
            v = params.initial_velocity[1]
            return 0.1 + ((wind - wind_true) ** 2).sum() + ((v - v_true) ** 2).sum()

    ctx = FakeContext(frozenset({"wind"}))
    wind = next(c for c in build_candidates(ctx)[0] if c.name == "wind")
    exact = (wind_true, {1: v_true.clone()})
    reference = float(ctx.loss(ctx.identified, [1]))  # 0.1 + 6.25 + 0.09
    assert regression_drop(ctx, wind, exact, reference=reference, fit_frames=[1, 2]) == (
        pytest.approx((reference - 0.1) / reference)
    )
    # credit is relative to the reference: a velocity change alone reaching 0.1 + 6.25 leaves
    # the wind 6.25 / 6.35 of it
    only_wind = reference - 0.09
    assert regression_drop(ctx, wind, exact, reference=only_wind, fit_frames=[1, 2]) == (
        pytest.approx((only_wind - 0.1) / only_wind)
    )
    worse = (torch.tensor([0.0, -5.0, 0.0]), None)  # farther than no wind at all
    assert regression_drop(ctx, wind, worse, reference=reference, fit_frames=[1]) == 0.0
    ctx.diverge = True
    assert regression_drop(ctx, wind, exact, reference=reference, fit_frames=[1]) == 0.0


def test_regression_estimate_reads_only_the_fit_frames():
    """The centroid regression that starts a refit must not see held-out frames: a held-out
    block carrying something else (here a 5 cm jump) leaves the estimate exact."""
    from types import SimpleNamespace

    from mosiv_framework.diagnose.candidates import build_candidates
    from mosiv_framework.diagnose.hypothesise import regression_estimate

    ctx = _FakeContext(frozenset({"wind"}))
    wind = next(c for c in build_candidates(ctx)[0] if c.name == "wind")
    time_s = np.arange(10)[:, None] / ctx.fps
    wind_true, dv_true = np.array([0.0, 2.5, 0.0]), np.array([0.1, 0.0, -0.05])
    centroid = 0.5 * wind_true * time_s**2 + dv_true * time_s  # r(t) of a steady wind
    centroid[4:6] += 0.05
    residuals = {1: SimpleNamespace(centroid=centroid, sim_velocity=np.zeros((10, 3)))}
    regimes = {1: ["free_flight"] * 10}

    theta, dv0 = regression_estimate(ctx, wind, residuals, regimes, [1, 2, 3, 6, 7, 8, 9])
    assert np.allclose(theta.numpy(), wind_true, atol=1e-3)
    assert np.allclose(dv0[1].numpy(), dv_true, atol=1e-4)
    theta_all, _ = regression_estimate(ctx, wind, residuals, regimes, list(range(1, 10)))
    assert np.abs(theta_all.numpy() - wind_true).max() > 0.1


def test_regression_gain_is_strong_for_the_true_body_force_only():
    """A steady sideways wind in the flight paths: the wind's columns explain them where a
    velocity change cannot (large BIC gain); on a path a velocity change explains, with a
    little noise, the wind buys nothing beyond its parameter cost."""
    from types import SimpleNamespace

    from mosiv_framework.diagnose.candidates import build_candidates
    from mosiv_framework.diagnose.hypothesise import REGRESSION_SLOT_GAIN, regression_gain

    ctx = _FakeContext(frozenset({"wind"}))
    wind = next(c for c in build_candidates(ctx)[0] if c.name == "wind")
    time_s = np.arange(8)[:, None] / ctx.fps
    rng = np.random.default_rng(0)
    noise = 1e-4 * rng.standard_normal((8, 3))
    regimes = {1: ["free_flight"] * 8}
    fit = [1, 2, 3, 4, 5, 6, 7]

    def gain(centroid):
        residuals = {1: SimpleNamespace(centroid=centroid, sim_velocity=np.zeros((8, 3)))}
        return regression_gain(ctx, wind, residuals, regimes, fit)

    windy = 0.5 * np.array([0.0, 2.5, 0.0]) * time_s**2 + 0.1 * time_s + noise
    drifting = np.array([0.1, 0.0, -0.05]) * time_s + noise
    assert gain(windy) > 10 * REGRESSION_SLOT_GAIN
    assert gain(drifting) < REGRESSION_SLOT_GAIN


def test_a_strong_regression_left_out_by_the_score_gets_one_extra_refit():
    from types import SimpleNamespace

    from mosiv_framework.diagnose.hypothesise import Screen, choose_refits

    def screen_(name, score, gain=None, drop=0.1):
        return Screen(
            SimpleNamespace(name=name), True, [], torch.zeros(1), drop, score, regression_gain=gain
        )

    ranked = [
        screen_("a", 3.0),
        screen_("b", 2.0, gain=4.0),
        screen_("c", 1.0, gain=50.0),
        screen_("d", 0.5, gain=80.0),
    ]
    assert [s.candidate.name for s in choose_refits(ranked, 2)] == ["a", "b", "d"]
    # already among the best-scored: no extra refit
    assert [s.candidate.name for s in choose_refits(ranked, 4)] == ["a", "b", "c", "d"]
    # weak regressions earn nothing
    assert [s.candidate.name for s in choose_refits(ranked[:2], 1)] == ["a"]


def test_a_candidate_flat_at_zero_is_probed_at_multiples_of_its_step():
    """A bounce does nothing to the loss until the restitution is large enough, so the
    gradient at zero is exactly 0; the screen then probes a few coefficients instead of
    dropping the candidate (restitution was otherwise never refitted on its own scenes)."""

    from mosiv_framework.diagnose.candidates import build_candidates
    from mosiv_framework.diagnose.hypothesise import screen

    class FakeContext(_FakeContext):
        def simulate(self, params, *, frames):
            return params

        rollout = simulate

        def loss(self, params, frames):
            e = params.terms.get("ground_restitution", {}).get("coefficient", torch.tensor(0.0))
            # flat below 0.2, best at 0.6
            return 1.0 - torch.relu(e - 0.2) * 2.0 + 4.0 * torch.relu(e - 0.6)

    ctx = FakeContext(frozenset({"ground_restitution"}), ground_height=0.0)
    bounce = next(c for c in build_candidates(ctx)[0] if c.name == "ground_restitution")
    (result,) = screen(ctx, [bounce], flagged_regimes=["ground_contact"], fit_frames=[1, 2])
    assert result.drop_fraction > 0 and "no descent direction at 0" in result.note
    probed = float(result.theta[0])
    assert 0.2 < probed <= 1.0
    assert result.drop_fraction == pytest.approx(
        1.0 - float(ctx.loss(bounce.apply(ctx.identified, result.theta), [1]))
    )


def test_the_screen_walks_out_along_the_descent_direction_when_the_loss_keeps_falling():
    """A bounce lowers the loss slowly at small restitution and fast at large. Where the loss
    curves down, the probe's quadratic model has no minimum; where it curves up but keeps
    falling, the model's minimum is too close. Either way the screen rolls out longer
    steps and starts the refit near the lowest, not a step or two (0.01) from zero."""
    from mosiv_framework.diagnose.candidates import build_candidates
    from mosiv_framework.diagnose.hypothesise import screen

    shapes = {
        "concave": lambda e: 1.0 - 0.05 * e - 0.9 * e**2,  # lowest at the bound e = 1
        # convex, still falling at the bound: a quadratic model from the probe stops near 0.025
        "convex": lambda e: 1.0 / (1.0 + 20.0 * e),
    }
    for name, loss_of in shapes.items():

        class FakeContext(_FakeContext):
            def simulate(self, params, *, frames):
                return params

            rollout = simulate

            def loss(self, params, frames, loss_of=loss_of):
                zero = torch.tensor(0.0)
                return loss_of(params.terms.get("ground_restitution", {}).get("coefficient", zero))

        ctx = FakeContext(frozenset({"ground_restitution"}), ground_height=0.0)
        bounce = next(c for c in build_candidates(ctx)[0] if c.name == "ground_restitution")
        (result,) = screen(ctx, [bounce], flagged_regimes=["ground_contact"], fit_frames=[1, 2])
        theta = float(result.theta[0])
        assert theta >= 0.3, name  # the rungs: 0.0316, 0.1, 0.316, 1.0
        assert result.drop_fraction == pytest.approx(1.0 - float(loss_of(result.theta[0]))), name
        assert "walked" in result.note, name


def test_the_regression_estimate_is_scored_in_the_batch_of_the_probe_and_walk():
    """The model at the regression estimate rolls out with the candidate's probe and walk in
    one batch, and its drop is the one ``regression_drop`` gives alone."""
    from types import SimpleNamespace

    from mosiv_framework.diagnose.candidates import build_candidates
    from mosiv_framework.diagnose.hypothesise import (
        FALLBACK_RUNGS,
        _velocity_only_loss,
        regression_drop,
        regression_estimate,
        screen,
    )

    wind_true = torch.tensor([0.0, 2.5, 0.0])

    class FakeContext(_FakeContext):
        batches: list[int] = []

        def simulate(self, params, *, frames):
            return params

        rollout = simulate

        def loss(self, params, frames):
            wind = params.terms.get("wind", {}).get("acceleration", torch.zeros(3))
            v = params.initial_velocity[1]
            return 0.1 + ((wind - wind_true) ** 2).sum() + ((v - 0.2) ** 2).sum()

        def rollout_losses(self, params_list, fit_frames):
            self.batches.append(len(params_list))
            return super().rollout_losses(params_list, fit_frames)

    ctx = FakeContext(frozenset({"wind"}))
    wind = next(c for c in build_candidates(ctx)[0] if c.name == "wind")
    time_s = np.arange(10)[:, None] / ctx.fps
    centroid = 0.5 * wind_true.numpy() * time_s**2 + np.array([0.1, 0.0, 0.0]) * time_s
    residuals = {1: SimpleNamespace(centroid=centroid, sim_velocity=np.zeros((10, 3)))}
    regimes = {1: ["free_flight"] * 10}
    fit = list(range(1, 10))
    (result,) = screen(
        ctx,
        [wind],
        flagged_regimes=["free_flight"],
        fit_frames=fit,
        residuals=residuals,
        regimes=regimes,
    )
    # one batch: the probe, its walk out to the bound and the regression model (the gradient
    # at zero and the velocity-only reference are rolled out before it)
    assert ctx.batches[-1] == 1 + (FALLBACK_RUNGS - 1) + 1
    regression = regression_estimate(ctx, wind, residuals, regimes, fit)
    base = float(ctx.loss(ctx.identified, fit))
    reference = _velocity_only_loss(ctx, base, residuals, regimes, fit)
    alone = regression_drop(ctx, wind, regression, reference=reference, fit_frames=fit)
    assert alone > 0.5
    assert f"regression drop {alone:.3g}" in result.note
    assert result.drop_fraction >= alone
