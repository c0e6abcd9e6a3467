"""Unit tests of the diagnosis's decision: held-out drops, BIC, verdicts, ranking, coefficient
intervals and diverged predictions, on synthetic error tables with known answers (no
simulator)."""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from mosiv_framework.diagnose.decide import Evidence, bic, bootstrap_drop, verdict
from mosiv_framework.diagnose.hypothesise import bic_gain
from mosiv_framework.diagnose.interval import IntervalOptions, linearised_bootstrap

# shared fakes of the diagnosis tests; --import-mode=importlib leaves this folder off sys.path
HERE = Path(__file__).resolve().parent
if str(HERE) not in sys.path:
    sys.path.insert(0, str(HERE))
from diagnose_fakes import _diverged, _elastic_pair_params  # noqa: E402


def test_bootstrap_drop_is_significant_only_for_a_consistent_improvement():
    rng = np.random.default_rng(0)
    null = 1.0 + 0.1 * rng.random((2, 8))
    better = 0.5 * null
    drop, spread = bootstrap_drop(null, better, block=2, resamples=300, seed=0)
    assert drop == pytest.approx(0.5)
    assert spread < 1e-9  # every unit improves by exactly half
    noisy = null * (1.0 + 0.3 * rng.standard_normal(null.shape))
    drop, spread = bootstrap_drop(null, noisy, block=2, resamples=300, seed=0)
    assert abs(drop) < 2 * spread


def test_the_log_drop_weighs_every_unit_by_its_factor_not_its_size():
    """Two objects, 8 held-out frames: a candidate that halves the error of the first six
    frames, where the errors are small, and is 20 % worse on the last two, where every
    prediction has left the recording (errors 1000x larger). Summed, the last frames decide
    (a negative drop); the geometric mean of the (object, block) ratios counts three units
    halved against one 1.2x worse: 1 - (0.5^3 x 1.2)^(1/4) per object."""
    null = np.concatenate([np.full((2, 6), 1e-6), np.full((2, 2), 1e-3)], axis=1)
    cand = np.concatenate([np.full((2, 6), 0.5e-6), np.full((2, 2), 1.2e-3)], axis=1)
    summed, _ = bootstrap_drop(null, cand, block=2, resamples=50, seed=0, statistic="sum")
    assert summed == pytest.approx(1 - (6 * 0.5e-6 + 2 * 1.2e-3) / (6e-6 + 2e-3), rel=1e-9)
    assert summed < 0
    logged, spread = bootstrap_drop(null, cand, block=2, resamples=300, seed=0)
    # within the log-ratio floor (1e-10 m^2 on units of 1e-6)
    assert logged == pytest.approx(1 - (0.5**3 * 1.2) ** 0.25, rel=1e-4)
    assert 0 < spread < logged
    with pytest.raises(ValueError, match="statistic 'mean': valid: log, sum"):
        bootstrap_drop(null, cand, block=2, resamples=5, seed=0, statistic="mean")


def test_bic_penalises_a_parameter_that_buys_nothing():
    errors = np.full((2, 5), 2e-5)
    floor = np.full((2, 1), 1e-5)
    n = errors.size
    assert bic(errors, floor, 5) - bic(errors, floor, 4) == pytest.approx(math.log(n))
    # counted in (object, 2-frame block) units the same errors are 2 x 3 observations
    assert bic(errors, floor, 5, block=2) - bic(errors, floor, 4, block=2) == pytest.approx(
        math.log(6)
    )
    assert bic(errors / 2, floor / 2, 4, block=2) - bic(errors, floor, 4, block=2) == (
        pytest.approx(-6 * math.log(2))
    )
    assert bic_gain(0.0, n=n, dim=1) == pytest.approx(-math.log(n))
    # explaining half the residual with one coefficient from 10 residuals is worth it
    assert bic_gain(0.5, n=n, dim=1) == pytest.approx(n * math.log(2) - math.log(n))


def test_a_small_consistent_held_out_gain_is_not_worth_naming():
    """Two candidates against the null on [2 objects, 20 frames] error tables: one removes 7 %
    of every held-out frame's error (significant against its spread, as a control's gravity
    change was on a full suite), the other 40 %. Only the second passes the effect-size test."""
    from mosiv_framework.diagnose.decide import DecideOptions, weigh

    rng = np.random.default_rng(1)
    null = 1e-4 * (1.0 + 0.1 * rng.random((2, 20)))
    null[:, 0] = 1e-6  # frame 0: the floor every model shares
    fit, held = list(range(1, 12)), list(range(12, 20))
    small, large = null.copy(), null.copy()
    small[:, 1:] *= 0.93
    large[:, 1:] *= 0.60
    errors = {"null": null, "small": small, "large": large}
    candidates = [("small", 1, 0.0), ("large", 1, 0.0)]
    evidence = weigh(
        errors,
        null_parameters=6,
        candidates=candidates,
        fit_frames=fit,
        heldout_frames=held,
        options=DecideOptions(),
    )
    by_name = {e.name: e for e in evidence}
    assert by_name["small"].heldout_drop > 10 * by_name["small"].heldout_spread
    assert not by_name["small"].accepted and by_name["large"].accepted
    assert evidence[0].name == "large"
    # without the effect-size test the small gain would pass the held-out test too
    loose = weigh(
        errors,
        null_parameters=6,
        candidates=candidates,
        fit_frames=fit,
        heldout_frames=held,
        options=DecideOptions(min_drop=0.0),
    )
    assert all(e.passes_heldout for e in loose)


def test_verdicts():
    def ev(explains=True, nuisance=True, consistent=True):
        return Evidence(
            "wind", 0.5, 0.05, -10.0, explains, True, 1e-6, 3,
            passes_nuisance=nuisance, passes_consistency=consistent,
        )  # fmt: skip

    assert verdict(True, [ev()]) == "missing physics"
    # improves the model, but a smooth per-object correction does as well: a discrepancy
    assert verdict(True, [ev(nuisance=False)]) == "discrepancy"
    assert verdict(True, [ev(consistent=False)]) == "discrepancy"
    assert verdict(True, [ev(explains=False)]) == "unexplained"
    assert verdict(False, []) == "no missing physics"


def test_accepted_candidates_are_ranked_by_information_criterion():
    """Two accepted explanations whose held-out drops lie within each other's spread: the one
    BIC prefers (fewer coefficients for the same fit) ranks first; rejected ones follow."""
    from mosiv_framework.diagnose.decide import Evidence, rank_evidence

    def ev(name, drop, spread, delta, n_new, accepted=True):
        return Evidence(name, drop, spread, delta, accepted, accepted, 1.0, n_new)

    ranked = rank_evidence(
        [
            ev("rejected", 0.9, 0.01, 5.0, 1, accepted=False),
            ev("wind", 0.52, 0.2, -3.6, 3),
            ev("gravity", 0.50, 0.2, -9.0, 1),
        ]
    )
    assert [e.name for e in ranked] == ["gravity", "wind", "rejected"]


def test_a_special_case_is_preferred_unless_the_general_term_adds_a_real_drop():
    """A gravity change is a wind along g. Of the two, both accepted, the wind ranks first by
    BIC but is named only if its extra coefficients add at least ``min_drop`` of the null's
    held-out error to the drop; a candidate that is not a special case keeps its BIC rank."""
    from mosiv_framework.diagnose.decide import Evidence, prefer_special_cases, rank_evidence

    def ev(name, drop, delta, n_new, within=()):
        return Evidence(name, drop, 0.01, delta, True, True, 1.0, n_new, special_case_of=within)

    # a kept gravity-1 entry: wind -29.5 BIC with drop 0.976, gravity -23.5 with 0.937
    ranked = rank_evidence(
        [ev("wind", 0.976, -29.5, 3), ev("gravity", 0.937, -23.5, 1, ("wind",))], min_drop=0.2
    )
    assert [e.name for e in ranked] == ["gravity", "wind"]
    # a wind that explains much more than the gravity change keeps its place
    ranked = rank_evidence(
        [ev("wind", 0.95, -29.5, 3), ev("gravity", 0.60, -12.0, 1, ("wind",))], min_drop=0.2
    )
    assert [e.name for e in ranked] == ["wind", "gravity"]
    # unrelated candidates are left in BIC order
    order = [ev("drag", 0.9, -20.0, 1), ev("gravity", 0.89, -10.0, 1, ("wind",))]
    assert prefer_special_cases(order, min_drop=0.2) == order


# --------------------------------------------------------------------------------------------
# coefficient interval


def _line_design(frames: int, objects: int, accel: float, rng, noise: float):
    """Residual paths x_k(t) = dv_k t + a t^2 / 2 + noise; columns: a, then each dv_k."""
    t = np.arange(1, frames + 1) / 30.0
    jac = np.zeros((objects * frames, 1 + objects))
    jac[:, 0] = np.tile(0.5 * t**2, objects)
    for k in range(objects):
        jac[k * frames : (k + 1) * frames, 1 + k] = t
    truth = np.concatenate([[accel], rng.normal(0.0, 0.1, objects)])
    residual = jac @ truth + noise * rng.standard_normal(objects * frames)
    unit = np.repeat(np.arange(objects), frames) * frames + np.tile(np.arange(frames) // 2, objects)
    return jac, residual, unit, truth


def test_linearised_bootstrap_covers_the_truth_at_about_95_percent():
    rng = np.random.default_rng(11)
    options = IntervalOptions(bootstrap=200, seed=0)
    hits, trials, widths = 0, 60, []
    for _ in range(trials):
        jac, residual, unit, truth = _line_design(8, 2, 2.5, rng, noise=1e-3)
        # the "fit" is the least-squares estimate; the bootstrap sees the residual left by it
        fit = np.linalg.lstsq(jac, residual, rcond=None)[0]
        lo, hi = linearised_bootstrap(
            jac, residual - jac @ fit, unit, n_coefficients=1, options=options
        )
        hits += int(fit[0] + lo[0] <= truth[0] <= fit[0] + hi[0])
        widths.append(hi[0] - lo[0])
    assert hits / trials >= 0.85
    # honest, not vacuous: at most 3x the width of the exact 95 % interval of this design
    jac = _line_design(8, 2, 2.5, rng, noise=1e-3)[0]
    exact = 2 * 1.96 * 1e-3 * math.sqrt(np.linalg.inv(jac.T @ jac)[0, 0])
    assert np.mean(widths) < 3 * exact


def test_linearised_bootstrap_reports_an_unidentifiable_coefficient_as_unbounded():
    rng = np.random.default_rng(2)
    jac, residual, unit, _ = _line_design(6, 2, 1.0, rng, noise=1e-3)
    jac[:, 0] = jac[:, 1] + jac[:, 2]  # the coefficient is a sum of the velocity columns
    lo, hi = linearised_bootstrap(jac, residual, unit, n_coefficients=1, options=IntervalOptions())
    assert lo[0] == -math.inf and hi[0] == math.inf


def test_the_interval_test_fails_a_term_whose_interval_includes_absent():
    """Intervals are recorded for every candidate that has one; only under
    ``require_nonzero`` does a candidate whose interval box holds zero fail, and the next
    accepted candidate takes its place."""
    from mosiv_framework.diagnose.decide import (
        DecideOptions,
        Evidence,
        apply_interval_test,
        excludes_zero,
    )

    assert excludes_zero([[0.5, 1.0]]) and excludes_zero([[-0.1, 0.1], [-2.0, -1.0]])
    assert not excludes_zero([[0.0, 18.9]]) and not excludes_zero([[-0.1, 0.1], [-1.0, 2.0]])

    def evidence():
        return [
            Evidence("damping", 0.56, 0.05, -6.0, True, True, 1.0, 1),
            Evidence("drag", 0.40, 0.05, -3.0, True, True, 1.0, 1),
            Evidence("wind", 0.05, 0.05, 2.0, False, False, 1.0, 3),
        ]

    intervals = {"damping": [[0.0, 18.9]], "drag": [[0.8, 1.1]]}
    kept = apply_interval_test(evidence(), intervals, DecideOptions(require_nonzero=False))
    assert [e.name for e in kept][:2] == ["damping", "drag"] and kept[0].accepted
    assert kept[0].interval == [[0.0, 18.9]] and kept[2].interval is None

    strict = apply_interval_test(evidence(), intervals, DecideOptions())
    assert DecideOptions().require_nonzero  # on by default
    assert [e.name for e in strict] == ["drag", "damping", "wind"]
    assert strict[0].accepted and not strict[1].accepted and not strict[1].passes_interval


# --------------------------------------------------------------------------------------------
# diverging predictions


def _moving_targets(n_frames: int, objects=(1, 2), points: int = 4):
    """Per object, ``points`` points moving at 1 cm per frame along x."""
    rng = np.random.default_rng(0)
    t = torch.arange(n_frames, dtype=torch.float32)[:, None, None]
    out = {}
    for k in objects:
        base = torch.tensor(rng.random((points, 3)), dtype=torch.float32)[None] * 0.05
        out[k] = base + 0.01 * t * torch.tensor([1.0, 0.0, 0.0])
    return out


def _trajectory(targets, drift: float, frames: int | None = None):
    """The targets, each frame t shifted by ``drift * t`` (m) along y; ``frames`` first."""
    from mosiv_framework.types import Trajectory

    ids = sorted(targets)
    n = next(iter(targets.values())).shape[0] if frames is None else frames
    t = torch.arange(n, dtype=torch.float32)[:, None, None]
    moved = [targets[k][:n] + drift * t * torch.tensor([0.0, 1.0, 0.0]) for k in ids]
    object_ids = torch.cat([torch.full((targets[k].shape[1],), k) for k in ids])
    return Trajectory(torch.cat(moved, dim=1), object_ids, 24.0)


def test_the_decision_rejects_a_diverged_prediction_and_survives_a_diverged_null():
    """A candidate exact on every frame it reached, but whose prediction diverged, is not
    accepted and the report says why; against a null whose own prediction diverged, a
    candidate that predicts every frame is still judged (and here accepted), and the saved
    diagnosis stays strict JSON that replays to the same decision."""
    from types import SimpleNamespace

    from mosiv_framework.diagnose.decide import DecideOptions, decide, verdict
    from mosiv_framework.diagnose.model import Fit
    from mosiv_framework.diagnose.replay import replay_diagnosis
    from mosiv_framework.diagnose.report import _block_means, _markdown, saved_table

    n_frames, fit_frames, held = 12, list(range(1, 8)), list(range(8, 12))
    targets = _moving_targets(n_frames)
    ctx = SimpleNamespace(targets=targets, object_ids=[1, 2], n_frames=n_frames, fps=24.0)
    params = _elastic_pair_params()

    def fit(name, n_params, *, drift, reached=None):
        f = Fit(name, None, params, torch.zeros(n_params - 6), 1e-6, n_params)
        if reached is None:
            f.trajectory = _trajectory(targets, drift)
        else:  # diverged at frame ``reached``
            f.diverged = str(_diverged(reached))
            f.reached = _trajectory(targets, drift, frames=reached)
        return f

    good = fit("good", 7, drift=2e-4)
    boom = fit("boom", 7, drift=0.0, reached=9)  # exact until it blew up in frame 9
    worse = fit("worse", 7, drift=5e-3)  # predicts every frame, all of them worse than the null
    options = DecideOptions(bootstrap=50)

    for null in (fit("null", 6, drift=2e-3), fit("null", 6, drift=2e-3, reached=10)):
        evidence, errors = decide(
            ctx,
            null,
            [boom, good, worse],
            fit_frames=fit_frames,
            heldout_frames=held,
            options=options,
        )
        by_name = {e.name: e for e in evidence}
        # judged on the frames the null reached, not handed the ones it did not
        assert by_name["worse"].heldout_drop < 0 and not by_name["worse"].passes_heldout
        assert not by_name["boom"].accepted and not by_name["boom"].passes_heldout
        assert "at frame 9" in by_name["boom"].diverged
        assert by_name["boom"].passes_bic  # its fit frames were fine: only its future failed
        assert evidence[0].name == "good" and evidence[0].accepted
        assert verdict(True, evidence) == "missing physics"
        assert np.isinf(errors["boom"][:, 9:]).all() and np.isfinite(errors["boom"][:, :9]).all()

        saved = json.loads(
            json.dumps(
                {
                    "rule": dict(options.__dict__),
                    "evidence": [e.to_json() for e in evidence],
                    "frames": {"fit": fit_frames, "heldout": held, "observed": 8},
                    "null_parameters": 6,
                    "where": {"significant": True},
                    "frame_errors_mm2": {name: saved_table(e) for name, e in errors.items()},
                    "errors": {name: _block_means(e, 8) for name, e in errors.items()},
                    "accepted": {"name": "good"},
                },
                allow_nan=False,  # no Infinity / NaN tokens
            )
        )
        assert saved["errors"]["boom"]["future_cd_mm2"] is None
        assert next(e for e in saved["evidence"] if e["name"] == "boom")["heldout_drop"] is None
        replayed = replay_diagnosis(saved)
        assert replayed["accepted"] == {"name": "good"}
        assert [e["name"] for e in replayed["evidence"]][0] == "good"

    # the null's divergence and the rejected candidate's are both told in the report
    where = {
        "object": 1,
        "signal_to_noise": 9.0,
        "noise_floor_m": 1e-3,
        "jitter_m": 1e-3,
        "targets_tracked": True,
        "sampling_m": 0.0,
        "onset_frame": 3,
        "window": [3, 7],
        "regimes": ["free_flight"],
        "direction_fraction": {"x": 1.0},
    }
    text = _markdown(
        {
            **saved,
            "verdict": "missing physics",
            "where": where,
            "accepted": None,
            "screening": [],
            "null_diverged": null.diverged,
        }
    )
    told = "was not accepted: its prediction diverged (simulation diverged in object 2 at frame"
    assert f"`boom` {told} 9, substep 1" in text
    null_told = "The null model's prediction diverged (simulation diverged in object 2 at frame"
    assert f"{null_told} 10, substep 1" in text
