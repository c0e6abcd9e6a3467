"""Unit tests of the diagnosis's parts on synthetic signals with known answers (no simulator)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from mosiv_framework.diagnose import split_frames
from mosiv_framework.diagnose.changepoint import hinge_change_point, mean_shift_change_point
from mosiv_framework.diagnose.decide import Evidence, bic, bootstrap_drop, verdict
from mosiv_framework.diagnose.hypothesise import bic_gain
from mosiv_framework.diagnose.interval import IntervalOptions, linearised_bootstrap
from mosiv_framework.diagnose.locate import (
    decompose_direction,
    difference_noise_std,
    difference_variance_factor,
    estimate_noise,
    label_regimes,
    points_are_tracked,
)
from mosiv_framework.errors import ConfigError


@pytest.mark.parametrize("tau", [3, 7, 12])
def test_hinge_change_point_finds_onset_of_a_noisy_rise(tau):
    rng = np.random.default_rng(tau)
    t = np.arange(20.0)
    y = 0.5 + 0.3 * np.maximum(t - tau, 0.0) + 0.02 * rng.standard_normal(20)
    found, sse = hinge_change_point(y)
    assert found == tau
    assert sse < 20 * 0.05**2  # the hinge model explains all but the noise


def test_hinge_change_point_of_an_exact_hinge_has_zero_error():
    y = np.maximum(np.arange(10.0) - 4, 0.0) * 2.0 + 1.0
    assert hinge_change_point(y) == (4, pytest.approx(0.0, abs=1e-18))


@pytest.mark.parametrize("k", [1, 5, 9])
def test_mean_shift_change_point_matches_brute_force(k):
    rng = np.random.default_rng(k)
    y = np.concatenate([np.zeros(k), 3.0 * np.ones(10 - k)]) + 0.1 * rng.standard_normal(10)
    found, sse = mean_shift_change_point(y)
    brute = min(
        range(1, 10),
        key=lambda s: ((y[:s] - y[:s].mean()) ** 2).sum() + ((y[s:] - y[s:].mean()) ** 2).sum(),
    )
    assert found == brute == k
    expected = ((y[:k] - y[:k].mean()) ** 2).sum() + ((y[k:] - y[k:].mean()) ** 2).sum()
    assert sse == pytest.approx(expected)


def _two_blocks(z1, z2, x1, x2):
    """Two 2x2x2 particle cubes of spacing 0.01 m with lowest corners at (x_i, 0, z_i)."""
    g = torch.stack(torch.meshgrid(*[torch.tensor([0.0, 0.01])] * 3, indexing="ij"), -1).reshape(
        -1, 3
    )
    a = g + torch.tensor([x1, 0.0, z1])
    b = g + torch.tensor([x2, 0.0, z2])
    return torch.cat([a, b])


def test_label_regimes_on_a_scripted_motion():
    # frame 0-1: both in flight, far apart; 2: touching in mid-air; 3: object 1 lands while
    # moving; 4-5: object 1 lies still on the ground, object 2 keeps flying away
    frames = [
        _two_blocks(0.30, 0.30, 0.00, 0.20),
        _two_blocks(0.28, 0.28, 0.05, 0.15),
        _two_blocks(0.20, 0.20, 0.09, 0.105),
        _two_blocks(0.001, 0.35, 0.12, 0.30),
        _two_blocks(0.001, 0.40, 0.12, 0.40),
        _two_blocks(0.001, 0.45, 0.12, 0.50),
    ]
    positions = torch.stack(frames)
    ids = torch.tensor([1] * 8 + [2] * 8)
    labels = label_regimes(
        positions, ids, fps=10.0, ground_height=0.0, contact_distance=0.008, rest_speed=0.05
    )
    assert labels[1] == [
        "free_flight",
        "free_flight",
        "object_contact",
        "ground_contact",
        "rest",
        "rest",
    ]
    assert labels[2] == ["free_flight", "free_flight", "object_contact"] + ["free_flight"] * 3


def test_label_regimes_sees_an_impact_that_happened_between_frames():
    """Two bodies approach (10 cm gap closing by 20 cm per frame), meet and bounce apart between
    frames 1 and 2, and are never within the contact distance on a frame: frame 2, the first
    that shows the impact's effect, is labelled object contact; the others are flight."""
    frames = [
        _two_blocks(0.3, 0.3, 0.00, 0.30),
        _two_blocks(0.3, 0.3, 0.10, 0.20),
        _two_blocks(0.3, 0.3, 0.05, 0.25),
        _two_blocks(0.3, 0.3, 0.00, 0.30),
    ]
    labels = label_regimes(
        torch.stack(frames),
        torch.tensor([1] * 8 + [2] * 8),
        fps=10.0,
        ground_height=0.0,
        contact_distance=0.008,
        rest_speed=0.05,
    )
    expected = ["free_flight", "free_flight", "object_contact", "free_flight"]
    assert labels[1] == expected and labels[2] == expected


def test_label_regimes_without_ground_never_reports_ground_contact():
    positions = torch.stack([_two_blocks(-1.0, 0.3, 0.0, 0.5)] * 3)
    ids = torch.tensor([1] * 8 + [2] * 8)
    labels = label_regimes(
        positions, ids, fps=10.0, ground_height=None, contact_distance=0.008, rest_speed=0.05
    )
    assert labels[1] == ["free_flight"] * 3


def test_decompose_direction_splits_orthogonal_parts():
    up = np.array([0.0, 0.0, 1.0])
    v = np.array([[1.0, 0.0, 0.0], [0.0, 2.0, 0.0]])
    r = np.array([[0.3, 0.4, 0.1], [0.2, -0.5, 0.0]])
    parts = decompose_direction(r, v, up=up, min_speed=1e-3)
    assert parts["along_velocity"] == pytest.approx(0.3**2 + 0.5**2)
    assert parts["vertical"] == pytest.approx(0.1**2)
    assert parts["tangential"] == pytest.approx(0.4**2 + 0.2**2)
    assert sum(parts.values()) == pytest.approx(float((r**2).sum()))


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


def test_split_frames_holds_out_blocks_inside_the_window_and_the_future():
    fit, held = split_frames(8, 12, 0.25)
    assert fit == [1, 2, 3, 6, 7] and held == [4, 5, 8, 9, 10, 11]
    # the suite's windows: 14 observed of 24. Late effects (ground friction, a bounce) act in
    # the last frames of the window, so those must keep fitted frames, and every held-out
    # block has fitted frames on both sides
    fit, held = split_frames(14, 24, 0.25)
    observed_held = [t for t in held if t < 14]
    assert held[len(observed_held) :] == list(range(14, 24))
    assert 3 <= len(observed_held) <= 5 and set(fit).isdisjoint(held)
    assert sorted(fit + observed_held) == list(range(1, 14))
    assert {11, 12, 13} <= set(fit) and {1, 2} <= set(fit)
    assert all(min(fit) < t < max(fit) for t in observed_held)
    fit, held = split_frames(8, 12, 0.0)
    assert fit == list(range(1, 8)) and held == [8, 9, 10, 11]
    # without future frames the held-out frames come from the observed window
    fit, held = split_frames(8, 8, 0.0)
    assert fit == list(range(1, 6)) and held == [6, 7]
    with pytest.raises(ConfigError, match="observes 4 of 4 frames"):
        split_frames(4, 4, 0.25)


# --------------------------------------------------------------------------------------------
# noise floor


def _ballistic(frames: int, *, dt: float = 1 / 30) -> np.ndarray:
    """Centroid path [T, 3] (m) of a throw under gravity: zero third differences."""
    t = np.arange(frames)[:, None] * dt
    return (
        np.array([0.1, -0.2, 0.3])
        + np.array([0.8, 0.3, 1.5]) * t
        + 0.5 * np.array([0.0, 0.0, -9.81]) * t**2
    )


@pytest.mark.parametrize("sigma", [2e-4, 1e-3])
def test_difference_noise_std_recovers_white_noise_on_a_ballistic_path(sigma):
    rng = np.random.default_rng(7)
    # per axis std sigma: the 3D RMS noise length is sigma sqrt(3)
    path = _ballistic(400) + sigma * rng.standard_normal((400, 3))
    estimate = difference_noise_std(path, order=3)
    assert estimate == pytest.approx(sigma * math.sqrt(3.0), rel=0.2)
    # second differences of the same path see gravity (9.81 dt^2 = 11 mm per frame^2) as noise
    assert difference_noise_std(path, order=2) > 3 * sigma * math.sqrt(3.0)


def test_difference_variance_factor_matches_simulated_differences():
    rng = np.random.default_rng(3)
    noise = rng.standard_normal(200_000)
    for order in (1, 2, 3):
        assert np.diff(noise, n=order).var() == pytest.approx(
            difference_variance_factor(order), rel=0.03
        )


def _body(n: int, rng) -> np.ndarray:
    """n points drawn uniformly in a 10 cm cube (m)."""
    return 0.1 * rng.random((n, 3))


def test_tracked_points_have_no_sampling_term():
    rng = np.random.default_rng(0)
    body = _body(200, rng)
    path = _ballistic(10)
    tracked = body[None] + path[:, None]  # the same points every frame
    resampled = np.stack([_body(200, rng) for _ in range(10)]) + path[:, None]
    assert points_are_tracked(tracked)
    assert not points_are_tracked(resampled)
    # a tracked body's centroid residual is exact: the floor is float rounding only
    est = estimate_noise(np.zeros((10, 3)), tracked)
    assert est.tracked and est.sampling == 0.0 and est.floor < 1e-6
    # resampled: the closed-form centroid sampling std, spread / sqrt(N) (spread of a 10 cm
    # uniform cube: 0.1 sqrt(3 / 12) m), carried by frame 0 and frame t alike (sqrt 2)
    est = estimate_noise(np.zeros((10, 3)), resampled)
    expected = 0.1 * math.sqrt(3.0 / 12.0) / math.sqrt(200)
    assert not est.tracked
    assert est.sampling == pytest.approx(expected, rel=0.05)
    assert est.floor == pytest.approx(math.sqrt(2.0) * expected, rel=0.05)


def test_noise_floor_of_a_noisy_tracked_residual_ignores_smooth_curvature():
    rng = np.random.default_rng(1)
    sigma = 5e-4  # per axis, m
    frames = 300
    # a residual that grows as a drag's does (smooth, t^2) plus white measurement noise,
    # measured relative to frame 0 as locate does
    t = np.arange(frames)[:, None] / 30.0
    noise = sigma * rng.standard_normal((frames, 3))
    residual = 0.02 * t**2 * np.array([1.0, 0.5, 0.0]) + noise - noise[0]
    tracked = _body(50, rng)[None] + _ballistic(frames)[:, None]
    est = estimate_noise(residual, tracked)
    assert est.jitter == pytest.approx(sigma * math.sqrt(3.0), rel=0.2)
    assert est.floor == pytest.approx(math.sqrt(2.0) * sigma * math.sqrt(3.0), rel=0.2)
    # the residual's RMS over this floor is about 1 for noise alone
    pure = noise - noise[0]
    ratio = np.sqrt((np.linalg.norm(pure[1:], axis=1) ** 2).mean()) / est.floor
    assert ratio == pytest.approx(1.0, rel=0.2)


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


def test_suite_resumes_scored_entries_and_rejects_unknown_names(tmp_path):
    """A suite stopped part-way picks up the scores already on disk instead of recomputing,
    and ``only`` names that are not entries are refused with the valid ones."""
    from dataclasses import asdict

    from mosiv_framework.diagnose.formats import SUITE_FORMAT, FormatError
    from mosiv_framework.diagnose.suite import Score, run_suite, suite_entries
    from mosiv_framework.errors import ConfigError

    entry = suite_entries(small=True)[0]
    stored = Score(
        entry.name, entry.conceal, "missing physics", "wind", "wind", True, 9.0, 0.05, 0.9
    )
    (tmp_path / entry.name).mkdir()
    (tmp_path / entry.name / "score.json").write_text(json.dumps(asdict(stored)))
    summary = run_suite(tmp_path, small=True, only=[entry.name])
    assert summary["scores"] == [asdict(stored)]
    assert summary["missing"] == []
    assert summary["correct_first_rate"] == 1.0
    assert (tmp_path / "suite.png").stat().st_size > 0  # the suite's figure next to its table
    assert json.loads((tmp_path / "suite.json").read_text())["format"] == SUITE_FORMAT
    # a score of a format this version cannot read is refused, not misread
    (tmp_path / entry.name / "score.json").write_text(json.dumps({"format": "x/2"}))
    with pytest.raises(FormatError, match="score.json: field 'format' is 'x/2'"):
        run_suite(tmp_path, small=True, only=[entry.name])
    with pytest.raises(ConfigError, match="valid"):
        run_suite(tmp_path, small=True, only=["no-such-entry"])


def test_a_scored_entry_carries_its_format_and_is_resumed_from_it(tmp_path, monkeypatch):
    """run_entry writes score.json with its format; a second call reads it back instead of
    running anything."""
    from mosiv_framework.diagnose import suite
    from mosiv_framework.diagnose.formats import SCORE_FORMAT

    entry = next(e for e in suite.suite_entries(small=True) if not e.conceal)
    diagnosis = {
        "verdict": "no missing physics",
        "accepted": None,
        "evidence": [],
        "errors": {},
        "where": {"signal_to_noise": 1.5},
    }
    # the pipeline's part here: the run folder
    monkeypatch.setattr(suite, "run_pipeline", lambda recipe, run_dir: run_dir.mkdir())
    monkeypatch.setattr(suite, "diagnose_run", lambda run_dir, budget: diagnosis)
    monkeypatch.setattr(suite, "read_scene", lambda path: type("S", (), {"gt_effects": list})())
    recipe = suite.DEFAULT_RECIPES[True]
    score = suite.run_entry(entry, tmp_path, recipe, "small")
    saved = json.loads((tmp_path / entry.name / "score.json").read_text())
    assert saved["format"] == SCORE_FORMAT and saved["name"] == entry.name
    assert score.correct and score.signal_to_noise == 1.5

    def nothing_runs(*args, **kwargs):
        raise AssertionError("a scored entry is resumed from its score.json")

    monkeypatch.setattr(suite, "run_pipeline", nothing_runs)
    assert suite.run_entry(entry, tmp_path, recipe, "small") == score


def test_a_prepared_suite_runs_the_pipeline_and_diagnoses_nothing(tmp_path, monkeypatch):
    """``prepare_only``: the entries' pipelines run (into OUT/entry, for another machine to
    diagnose from their stages), no diagnosis starts, and nothing is scored."""
    from mosiv_framework.diagnose import suite

    ran = []
    monkeypatch.setattr(suite, "run_pipeline", lambda recipe, run_dir: ran.append(run_dir))

    def no_diagnosis(*args, **kwargs):
        raise AssertionError("a prepared suite must not diagnose")

    monkeypatch.setattr(suite, "diagnose_run", no_diagnosis)
    names = [e.name for e in suite.suite_entries(small=True)[:2]]
    summary = suite.run_suite(tmp_path, small=True, only=names, prepare_only=True)
    assert summary == {"prepared": sorted(names)}
    assert sorted(ran) == sorted(tmp_path / n for n in names)
    assert not list(tmp_path.glob("*/score.json")) and not (tmp_path / "suite.json").exists()


def test_null_refit_starts_from_the_identified_state_too():
    """The null model is refitted from the run's own state as well as from the regression's
    velocity change, so it can never end worse than the run every candidate starts from."""
    from mosiv_framework.diagnose.diagnosis import null_starts

    assert [(t.numel(), dv) for t, dv in null_starts(None)] == [(0, None)]
    change = {1: torch.tensor([0.1, 0.0, 0.0])}
    starts = null_starts((torch.zeros(3), change))
    assert starts[0][1] is None and starts[1][1] is change


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


# ------------------------------------------------------------------ plasticity candidate
def _elastic_pair_params():
    from mosiv_framework.types import ObjectParams, SimulationParams

    elastic = {"E": torch.tensor(5e4), "nu": torch.tensor(0.25), "rho": torch.tensor(1e3)}
    elastic["friction"] = torch.tensor(0.3)
    sand = {**elastic, "friction_angle": torch.tensor(30.0)}
    return SimulationParams(
        {1: ObjectParams("elastic", elastic), 2: ObjectParams("sand", sand)},
        {1: torch.zeros(3), 2: torch.zeros(3)},
        torch.tensor(0.3),
        {},
    )


class _FakeContext:
    """The few RunContext members that candidate building and screening read, for an elastic
    pair on a simulator supporting ``terms`` (subclasses add rollouts and a loss)."""

    identified = _elastic_pair_params()
    object_ids = [1, 2]
    simulator_name = "fake"
    fps = 24.0

    def __init__(self, terms: frozenset[str], *, ground_height: float | None = None):
        from types import SimpleNamespace

        self.simulator = SimpleNamespace(supported_terms=terms)
        self.world = SimpleNamespace(gravity=(0.0, 0.0, -9.81), ground_height=ground_height)

    def parameter_vector(self):
        from types import SimpleNamespace

        return SimpleNamespace(normalized={"obj1.friction": None})  # no friction candidate


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
    assert float(plastic.objects[1].values["yield_stress"]) == pytest.approx(bound * 10**-2.5)
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
        {n: float(v) for n, v in plastic.objects[1].values.items() if n not in ("rho", "friction")}
    )


def test_ladder_screen_picks_the_lowest_rung_and_scores_it():
    """A candidate with a ladder is probed at each rung (no gradient): the rung with the lowest
    loss is the predicted coefficient; a ladder that never beats the base predicts nothing."""
    from mosiv_framework.diagnose.hypothesise import _screen_ladder

    c = _plasticity_candidate()

    class FakeContext:
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


def test_concealed_plasticity_and_object_friction_specs():
    from mosiv_framework.conceal import YIELD_STRESS_RANGE, parse_conceal
    from mosiv_framework.laws import get_law

    spec = get_law("plasticine").param("yield_stress")
    assert YIELD_STRESS_RANGE == (spec.lower, spec.upper)
    assert parse_conceal("plasticity")[0].params == {"yield_stress": 3000.0}
    assert parse_conceal("object_friction:coefficient=0")[0].params == {"coefficient": 0.0}
    with pytest.raises(ValueError, match="yield_stress"):
        parse_conceal("plasticity:yield_stress=1")
    with pytest.raises(ValueError, match=">= 0"):
        parse_conceal("object_friction:coefficient=-0.1")


def test_suite_scores_a_per_object_plasticity_name_as_its_kind():
    from mosiv_framework.diagnose.suite import candidate_kind, suite_entries

    assert candidate_kind("plasticity@2") == "plasticity"
    assert candidate_kind("wind") == "wind"
    entries = {e.name: e for e in suite_entries(small=False)}
    for name in ("plasticity-0", "plasticity-1"):
        assert entries[name].materials.split(",").count("elastic") == 1
    assert entries["object_friction-0"].overrides == ("identify.identify_friction=false",)


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


def test_refit_ends_a_start_at_a_non_finite_gradient():
    """A NaN gradient (as from a degenerate backward pass) must not enter Adam's state: the
    start stops there and returns its best finite iterate."""
    from mosiv_framework.diagnose.model import RefitOptions, refit
    from mosiv_framework.pipeline.params import ParameterVector

    target = torch.tensor([1.0, 0.0, 0.0])

    class FakeContext:
        calls = 0

        def parameter_vector(self, params=None):
            return ParameterVector.create({1: "elastic"}, {1: torch.zeros(3)}, ground_friction=None)

        def simulate(self, params, *, frames):
            self.calls += 1
            v = params.initial_velocity[1]
            misfit = ((v - target) ** 2).sum()
            if self.calls >= 4:  # forward unchanged, gradient 0 * inf = NaN
                misfit = misfit + 0.0 * torch.sqrt(v.sum() - v.sum().detach())
            return misfit

        def loss(self, traj, frames):
            return traj

        def rollout(self, params, *, frames=None):
            return None

    ctx = FakeContext()
    fit = refit(ctx, None, fit_frames=[1, 2], options=RefitOptions(iterations=10))
    assert len(fit.history) == 4  # three clean steps, then the poisoned pass ends the start
    v = fit.params.initial_velocity[1]
    assert bool(torch.isfinite(v).all())
    assert fit.loss == pytest.approx(min(fit.history)) and fit.loss < float((target**2).sum())


class _ScalarLoss:
    """For fake contexts whose ``simulate`` returns the fit loss itself (m^2)."""

    def loss(self, traj, frames):
        return traj

    def rollout(self, params, *, frames=None):
        with torch.no_grad():
            return self.simulate(params, frames=frames)


class _QuadraticContext(_ScalarLoss):
    """A run whose only free parameter is object 1's initial velocity, and whose fit loss is
    its squared distance (m^2/s^2) to ``target``."""

    def __init__(self, target):
        self.target = torch.tensor(target)

    def parameter_vector(self, params=None):
        from mosiv_framework.pipeline.params import ParameterVector

        v = torch.zeros(3) if params is None else params.initial_velocity[1]
        return ParameterVector.create({1: "elastic"}, {1: v.clone()}, ground_friction=None)

    def simulate(self, params, *, frames):
        return ((params.initial_velocity[1] - self.target) ** 2).sum()


def test_the_null_continues_from_a_candidate_refit_that_found_better_shared_values():
    """A candidate's refit that moved the shared parameters closer than the null's own refit
    did: the null, refitted again from there, must fit at least as well as those values, so a
    candidate cannot win merely by having been optimised further."""
    from mosiv_framework.diagnose.model import Fit, RefitOptions, converge_null, refit

    ctx = _QuadraticContext([2.0, 0.0, 0.0])
    options = RefitOptions(iterations=3, velocity_lr=0.1)
    null = refit(ctx, None, fit_frames=[1], options=options)  # 3 steps of 0.1 from 0: still far
    assert null.loss > 2.0
    closer = ctx.parameter_vector().physical()
    closer.initial_velocity[1] = torch.tensor([1.8, 0.0, 0.0])
    far = ctx.parameter_vector().physical()
    far.initial_velocity[1] = torch.tensor([-3.0, 0.0, 0.0])
    fits = [
        Fit(name, None, p, torch.zeros(1), 0.0, 1, shared=p)
        for name, p in (("far", far), ("closer", closer))
    ]
    warm = converge_null(ctx, null, fits, fit_frames=[1], options=options)
    assert warm.started_from == "closer" and warm.name == "null"
    assert warm.loss <= 0.2**2 + 1e-6  # no worse than where it started
    assert warm.n_params == null.n_params

    # no candidate found better shared values: the null stays as it was
    assert converge_null(ctx, null, fits[:1], fit_frames=[1], options=options) is null


def test_a_regression_start_holds_its_coefficient_while_the_shared_parameters_settle():
    """The first start that brings a velocity change keeps the wind it was given for
    ``settle`` steps while the velocities move; a start without one, and the later regression
    multiples, move the wind from their first step."""
    from mosiv_framework.diagnose.candidates import build_candidates
    from mosiv_framework.diagnose.model import RefitOptions, refit
    from mosiv_framework.pipeline.params import ParameterVector

    class Context(_ScalarLoss, _FakeContext):
        seen: list = []

        def parameter_vector(self, params=None):
            return ParameterVector.create({1: "elastic"}, {1: torch.zeros(3)}, ground_friction=None)

        def simulate(self, params, *, frames):
            wind = params.terms["wind"]["acceleration"]
            self.seen.append(wind.detach().clone())
            v = params.initial_velocity[1]
            return ((v - 1.0) ** 2).sum() + ((wind - torch.tensor([0.0, 2.0, 0.0])) ** 2).sum()

    ctx = Context(frozenset({"wind"}))
    wind = next(c for c in build_candidates(ctx)[0] if c.name == "wind")
    start = torch.tensor([0.0, 2.5, 0.0])
    dv = {1: torch.full((3,), 0.1)}
    options = RefitOptions(iterations=3, settle=4)

    ctx.seen = []
    fit = refit(ctx, wind, fit_frames=[1], starts=[(start, dv), (0.5 * start, dv)], options=options)
    first, second = ctx.seen[:8], ctx.seen[8:12]  # 4 settle + 3 joint + 1 scoring, then 3 + 1
    assert all(torch.equal(w, start) for w in first[:5])  # the settle steps and the first joint
    assert not torch.equal(first[5], start)
    # ... and one rollout of the best fit
    assert len(ctx.seen) == 8 + 4 + 1 and not torch.equal(second[1], second[0])
    assert len(fit.starts) == 2

    ctx.seen = []
    refit(ctx, wind, fit_frames=[1], starts=[(start, None)], options=options)
    assert len(ctx.seen) == 4 + 1 and not torch.equal(ctx.seen[1], start)


def test_a_candidate_that_fits_worse_continues_from_the_best_models_state():
    """A candidate contains the null, so a candidate refit fitting worse than the null's is
    under-converged: it restarts at the best model's shared values (here the null's, then
    another candidate's) with its own coefficients (held while those settle) and must end
    below it; a candidate already the best is kept."""
    from mosiv_framework.diagnose.candidates import build_candidates
    from mosiv_framework.diagnose.model import Fit, RefitOptions, converge_candidates, refit
    from mosiv_framework.pipeline.params import ParameterVector

    wind_true, v_true = torch.tensor([0.0, 2.0, 0.0]), torch.ones(3)

    class Context(_ScalarLoss, _FakeContext):
        seen: list = []

        def parameter_vector(self, params=None):
            v = torch.zeros(3) if params is None else params.initial_velocity[1]
            return ParameterVector.create({1: "elastic"}, {1: v.clone()}, ground_friction=None)

        def simulate(self, params, *, frames):
            wind = params.terms.get("wind", {}).get("acceleration", torch.zeros(3))
            self.seen.append((params.initial_velocity[1].detach().clone(), wind.detach().clone()))
            v = params.initial_velocity[1]
            return ((v - v_true) ** 2).sum() + ((wind - wind_true) ** 2).sum()

    ctx = Context(frozenset({"wind"}))
    wind = next(c for c in build_candidates(ctx)[0] if c.name == "wind")
    options = RefitOptions(iterations=3, settle=2, velocity_lr=0.3)
    null = refit(ctx, None, fit_frames=[1], options=RefitOptions(iterations=30, velocity_lr=0.3))
    assert null.loss == pytest.approx(4.0, abs=0.05)  # the velocity is right; no wind
    # a wind refit that read the wind well but left the velocity far off: worse than the null
    stuck = ParameterVector.create(
        {1: "elastic"}, {1: torch.full((3,), -2.0)}, ground_friction=None
    )
    stuck = stuck.physical()
    theta = torch.tensor([0.0, 1.8, 0.0])
    bad = Fit(
        "wind", wind, wind.apply(stuck, theta), theta, 27.04, 4, starts=[([0, 1.8, 0], 27.04)]
    )
    ctx.seen = []
    (continued,) = converge_candidates(ctx, null, [bad], fit_frames=[1], options=options)
    assert continued.started_from == "null" and continued.name == "wind"
    v0, w0 = ctx.seen[0]
    assert torch.allclose(v0, null.params.initial_velocity[1])  # the null's state ...
    assert torch.equal(w0, theta) and torch.equal(ctx.seen[2][1], theta)  # ... wind held, settling
    assert continued.loss < 0.05 < null.loss  # now far below the null, as a nested model must be
    assert len(continued.starts) == 2  # the first refit's start is kept for the interval

    good = Fit("wind", wind, wind.apply(null.params, wind_true), wind_true, 0.01, 4)
    assert converge_candidates(ctx, null, [good], fit_frames=[1], options=options)[0] is good

    # the best model found is another candidate: the laggard continues from its shared values
    leader_shared = ParameterVector.create(
        {1: "elastic"}, {1: torch.full((3,), 0.9)}, ground_friction=None
    ).physical()
    leader = Fit("leader", wind, wind.apply(leader_shared, theta), theta, 0.05, 4)
    leader.shared = leader_shared
    ctx.seen = []
    kept, continued = converge_candidates(ctx, null, [leader, bad], fit_frames=[1], options=options)
    assert kept is leader and continued.started_from == "leader"
    assert torch.allclose(ctx.seen[0][0], leader_shared.initial_velocity[1])
    assert continued.loss < 0.05


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


def test_reidentification_replays_the_runs_schedule_on_the_fit_frames_only(monkeypatch):
    """Identifying afresh under a hypothesis: first the initial velocity with the wind (it acts
    in free flight) over the fit frames before contact, materials held; then the material with
    the wind over every fit frame, velocity held. Held-out frames are never scored, and the
    result reaches the optimum that a refit from a biased state would have to climb to."""
    from mosiv_framework.diagnose import reidentify as module
    from mosiv_framework.diagnose.candidates import build_candidates
    from mosiv_framework.pipeline.params import ParameterVector

    v_true, wind_true, e_true = torch.tensor([0.5, 0.0, 1.0]), torch.tensor([0.0, 2.0, 0.0]), 4e4

    class Context(_FakeContext):
        calls: list = []

        def simulate(self, params, *, frames):
            return params, frames  # the "trajectory": what the loss needs

        def loss(self, traj, frames):
            params, horizon = traj
            assert max(frames) <= horizon
            v = params.initial_velocity[1]
            wind = params.terms.get("wind", {}).get("acceleration", torch.zeros(3))
            e = params.objects[1].values["E"]
            self.calls.append((list(frames), v.detach().clone(), wind.detach().clone(), float(e)))
            flight = ((v - v_true) ** 2).sum() + 0.1 * ((wind - wind_true) ** 2).sum()
            # the material shows only once the bodies touch (frame 4 on)
            contact = (torch.log(e / e_true) ** 2) * float(max(frames) >= 4)
            return flight + contact

        def rollout(self, params, *, frames=None):
            return None

    def fresh(ctx):
        vector = ParameterVector.create(
            {1: "elastic"}, {1: torch.zeros(3)}, ground_friction=None, identify=("E",)
        )
        return vector, 4  # frames 0-3 are free flight

    monkeypatch.setattr(module, "fresh_vector", fresh)
    ctx = Context(frozenset({"wind"}))
    wind = next(c for c in build_candidates(ctx)[0] if c.name == "wind")
    fit_frames = [1, 2, 5, 6, 8]  # 3, 4 and 7 held out
    options = module.ReidentifyOptions(
        velocity_iterations=80,
        param_iterations=60,
        velocity_lr=0.1,
        param_lr=0.05,
        coefficient_lr=0.2,
    )
    fit = module.reidentify(ctx, wind, fit_frames=fit_frames, options=options)

    assert all(set(frames) <= set(fit_frames) for frames, *_ in ctx.calls)
    flight = [c for c in ctx.calls[: options.velocity_iterations + 1]]
    params = ctx.calls[options.velocity_iterations + 1 :]
    assert all(max(frames) <= 2 for frames, *_ in flight)  # before contact only
    assert len({e for *_, e in flight}) == 1  # the material held while velocities move
    assert not torch.equal(flight[0][2], flight[-1][2])  # the wind moved with them
    assert all(torch.equal(v, params[0][1]) for _, v, *_ in params)  # velocity held after
    assert max(max(frames) for frames, *_ in params) == 8
    assert fit.reidentified and fit.name == "wind"
    assert torch.allclose(fit.theta, wind_true, atol=0.1)
    assert fit.params.objects[1].values["E"] == pytest.approx(e_true, rel=0.1)
    assert fit.loss < 0.01


def test_resampled_particles_move_within_the_stated_fraction_of_their_spacing():
    from mosiv_framework.diagnose.floor import resampled
    from mosiv_framework.types import ParticleSet

    n = 2000
    particles = ParticleSet(
        torch.rand(n, 3), torch.full((n,), 0.01**3), torch.ones(n, dtype=torch.long), {1: "elastic"}
    )
    moved = resampled(particles, fraction=0.5, seed=3)
    offset = moved.positions - particles.positions
    assert offset.abs().max() <= 0.25 * 0.01 + 1e-7  # half of the fraction, per axis
    # uniform on [-s/4, s/4]: variance s^2 / 48 per axis
    assert float(offset.var()) == pytest.approx(0.01**2 / 48, rel=0.1)
    assert torch.equal(resampled(particles, fraction=0.5, seed=3).positions, moved.positions)
    assert torch.equal(moved.volumes, particles.volumes)
    with pytest.raises(ValueError, match="fraction"):
        resampled(particles, fraction=0.0)


def test_resolution_floor_of_a_rigid_motion_is_the_resampling_itself():
    """Under a motion that ignores how the body is sampled (a rigid translation), the two
    rollouts differ only by the offsets: the floor is the same every frame, and is the
    Chamfer of the resampled cloud against the original."""
    from types import SimpleNamespace

    from mosiv_framework.diagnose.floor import resampled, resolution_floor
    from mosiv_framework.losses import chamfer_m2
    from mosiv_framework.types import ParticleSet, Trajectory

    n = 600
    ids = torch.cat([torch.ones(n // 2), 2 * torch.ones(n // 2)]).long()
    particles = ParticleSet(
        torch.rand(n, 3) * 0.1, torch.full((n,), 0.01**3), ids, {1: "elastic", 2: "elastic"}
    )

    def translate(parts, params, *, world, frames):
        shift = torch.arange(frames + 1, dtype=torch.float32)[:, None, None] * 0.02
        return Trajectory(parts.positions[None] + shift, parts.object_ids, 24.0)

    ctx = SimpleNamespace(
        simulator=SimpleNamespace(rollout=translate),
        world=None,
        n_frames=5,
        object_ids=[1, 2],
        particles_for=lambda params: particles,
        rollout=lambda params: translate(particles, params, world=None, frames=4),
    )
    params = _elastic_pair_params()
    table = resolution_floor(ctx, params, fraction=0.5, seed=1)
    moved = resampled(particles, fraction=0.5, seed=1)
    for i, k in enumerate((1, 2)):
        mask = ids == k
        expected = float(chamfer_m2(particles.positions[mask], moved.positions[mask]))
        assert expected > 0
        assert np.allclose(table[i], expected, rtol=1e-4)


def test_a_model_keeps_the_better_of_its_refit_and_its_fresh_identification(monkeypatch):
    """``_better``: the fresh identification replaces the refit only where it fits the fit
    frames better (keeping both fits' starts for the interval), and a fresh identification
    whose every rollout diverged leaves the refit as it was."""
    from mosiv_framework.diagnose import diagnosis
    from mosiv_framework.diagnose.model import Fit
    from mosiv_framework.errors import SimulationDiverged

    params = _elastic_pair_params()
    refitted = Fit("wind", None, params, torch.zeros(3), 2.0, 4, starts=[([0, 0, 0], 2.0)])

    def fresh_with(loss):
        def fake(ctx, candidate, *, fit_frames, start, options):
            return Fit(
                "wind",
                None,
                params,
                torch.ones(3),
                loss,
                4,
                starts=[([1, 1, 1], loss)],
                reidentified=True,
            )

        return fake

    monkeypatch.setattr(diagnosis, "reidentify", fresh_with(1.0))
    kept = diagnosis._better(refitted, None, None, None, [1, 2], None)
    assert kept.reidentified and kept.loss == 1.0
    assert kept.starts == [([0, 0, 0], 2.0), ([1, 1, 1], 1.0)]

    monkeypatch.setattr(diagnosis, "reidentify", fresh_with(3.0))
    assert diagnosis._better(refitted, None, None, None, [1, 2], None) is refitted

    def diverges(*args, **kwargs):
        raise SimulationDiverged(object_id=1, frame=2, substep=3, reason="test", advice="")

    monkeypatch.setattr(diagnosis, "reidentify", diverges)
    assert diagnosis._better(refitted, None, None, None, [1, 2], None) is refitted


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


#: benchmarks/data/, where kept diagnoses are found by their content, not by folder names
KEPT = Path(__file__).resolve().parents[1] / "benchmarks" / "data"


def _kept_diagnosis(entry: str, accepted: str, match=lambda diagnosis: True) -> Path:
    """The first diagnosis.json of suite entry ``entry`` kept under benchmarks/data/ that
    accepted ``accepted`` as it ran and satisfies ``match``."""
    for path in sorted(KEPT.glob(f"**/{entry}/diagnosis.json")):
        diagnosis = json.loads(path.read_text())
        if (diagnosis.get("accepted") or {}).get("name") == accepted and match(diagnosis):
            return path
    pytest.fail(f"no diagnosis of {entry} accepting {accepted} is kept under {KEPT}")


def _interval_includes_zero(diagnosis: dict) -> bool:
    return any(lo <= 0.0 <= hi for lo, hi in diagnosis["accepted"]["interval_95"].values())


def test_replaying_with_the_interval_test_reports_the_out_of_library_entry_unexplained():
    """An out-of-library entry (a concealed drag with drag out of the library) that ran
    without the interval test accepted material damping with a viscosity interval of
    [0, 18.9] Pa s; replayed with the interval test it is unexplained, and a true effect's
    diagnosis of the same suite (its interval clear of zero) is unchanged."""
    from mosiv_framework.diagnose.decide import DecideOptions
    from mosiv_framework.diagnose.replay import replay_diagnosis

    outside_path = _kept_diagnosis(
        "outside-quadratic_drag", "material_damping", _interval_includes_zero
    )
    outside = json.loads(outside_path.read_text())
    true_path = outside_path.parents[1] / "material_damping-0" / "diagnosis.json"
    true = json.loads(true_path.read_text())
    strict = DecideOptions(**{**outside["rule"], "require_nonzero": True})
    assert replay_diagnosis(outside)["accepted"]["name"] == "material_damping"
    replayed = replay_diagnosis(outside, strict)
    assert replayed["verdict"] == "unexplained" and replayed["accepted"] is None
    assert replay_diagnosis(true, strict)["accepted"]["name"] == "material_damping"


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


def test_replaying_the_gravity_entry_names_gravity_not_a_vertical_wind():
    """A gravity-1 entry (gravity 7.5 m/s^2 instead of 9.81) diagnosed before the special-case
    preference accepted a nearly vertical wind; the decision with the preference names the
    gravity change, from the saved error tables alone. Files of the unversioned layout without
    a recorded ``special_case_of`` use the built-in declaration."""
    from mosiv_framework.diagnose.candidates import SPECIAL_CASES
    from mosiv_framework.diagnose.replay import replay_diagnosis, saved_special_cases

    diagnosis = json.loads(_kept_diagnosis("gravity-1", "wind").read_text())
    assert "format" not in diagnosis  # the unversioned layout
    assert diagnosis["accepted"]["name"] == "wind"  # as it ran, before the preference
    assert saved_special_cases(diagnosis)["gravity"] == SPECIAL_CASES["gravity"] == ("wind",)
    replayed = replay_diagnosis(diagnosis)
    assert replayed["verdict"] == "missing physics" and replayed["accepted"]["name"] == "gravity"
    assert replayed["evidence"][0]["special_case_of"] == ["wind"]
    assert replayed["evidence"][1]["name"] == "wind" and replayed["evidence"][1]["accepted"]
    assert replayed["evidence"][0]["theta"] == pytest.approx([-2.19], abs=0.01)  # kept from file
    # a file that records each fit's physical value: a newly accepted term carries it
    for e in diagnosis["evidence"]:
        if e["name"] == "gravity":
            e["value"] = {"acceleration": [0.0, 0.0, -7.62]}
    assert replay_diagnosis(diagnosis)["accepted"]["value"] == {"acceleration": [0.0, 0.0, -7.62]}


def test_a_replayed_suite_folder_without_scenes_scores_coefficients_from_the_entries(tmp_path):
    """benchmarks/data keeps diagnoses without their scenes; a replay scores the coefficient
    error against the entry's conceal spec (what the generator wrote to gt/effects.json)."""
    import shutil

    from mosiv_framework.diagnose.decide import DecideOptions
    from mosiv_framework.diagnose.replay import replay_suite

    kept = _kept_diagnosis("wind-0", "wind").parent
    shutil.copytree(kept, tmp_path / "wind-0")
    summary = replay_suite(tmp_path, DecideOptions())
    (score,) = summary["scores"]
    saved = json.loads((kept / "score.json").read_text())
    assert score["correct"] and score["accepted"] == "wind"
    assert score["coefficient_error"] == pytest.approx(saved["coefficient_error"], rel=1e-9)
    assert "control-0" in summary["missing"]


def test_a_diagnosis_of_an_unknown_format_is_refused_naming_the_file_field_and_values(tmp_path):
    """A diagnosis.json of a format this version cannot read (e.g. from a newer MOSIV) is not
    misread: the replay stops with the file, the field, its value and the supported values."""
    from mosiv_framework.diagnose.decide import DecideOptions
    from mosiv_framework.diagnose.formats import DIAGNOSIS_FORMAT, FormatError
    from mosiv_framework.diagnose.replay import replay_suite

    diagnosis = json.loads(_kept_diagnosis("wind-0", "wind").read_text())
    path = tmp_path / "wind-0" / "diagnosis.json"
    path.parent.mkdir()
    path.write_text(json.dumps({**diagnosis, "format": "mosiv-diagnosis/99"}))
    with pytest.raises(FormatError) as info:
        replay_suite(tmp_path, DecideOptions())
    message = str(info.value)
    assert str(path) in message and "'format'" in message
    assert "'mosiv-diagnosis/99'" in message and repr(DIAGNOSIS_FORMAT) in message


def test_kept_diagnoses_of_the_unversioned_layout_replay_to_their_own_decision():
    """Files written before diagnosis.json carried a format replay, under the rule they record
    (or the one their layout implies), to the verdict and term they recorded; the one change
    allowed is the special-case preference, which names the special case of the term they
    accepted (a gravity change for a vertical wind)."""
    from mosiv_framework.diagnose.candidates import SPECIAL_CASES
    from mosiv_framework.diagnose.replay import replay_diagnosis

    paths = sorted(KEPT.glob("**/diagnosis.json"))
    unversioned = [p for p in paths if "format" not in json.loads(p.read_text())]
    assert unversioned
    changed = 0
    for path in unversioned:
        saved = json.loads(path.read_text())
        replayed = replay_diagnosis(saved, source=path)
        assert replayed["verdict"] == saved["verdict"], path
        before = (saved["accepted"] or {}).get("name")
        after = (replayed["accepted"] or {}).get("name")
        changed += after != before
        assert after == before or before in SPECIAL_CASES.get(after, ()), path
    assert changed < len(unversioned)


def test_the_format_field_decides_how_a_diagnosis_is_read():
    """The unversioned layout gets what its fields leave out from the layout (a file without a
    rule ran BIC margin 2 without the interval test; the accepted interval stands for the
    evidence's); a versioned file is read as written. A complete unversioned file replays the
    same once it carries the current format."""
    from mosiv_framework.diagnose.decide import DecideOptions
    from mosiv_framework.diagnose.formats import DIAGNOSIS_FORMAT
    from mosiv_framework.diagnose.replay import (
        replay_diagnosis,
        saved_intervals,
        saved_rule,
        saved_special_cases,
    )

    saved = json.loads(_kept_diagnosis("outside-quadratic_drag", "material_damping").read_text())
    rule_less = {k: v for k, v in saved.items() if k != "rule"}
    legacy = saved_rule(rule_less)
    assert legacy.bic_margin == 2.0 and not legacy.require_nonzero and legacy.min_effect == 0.0
    assert "material_damping" in saved_intervals(saved)  # from accepted.interval_95
    versioned = {**saved, "format": DIAGNOSIS_FORMAT}
    assert "material_damping" not in saved_intervals(versioned)
    assert all(v == () for v in saved_special_cases(versioned).values())

    complete = json.loads(_kept_diagnosis("gravity-1", "gravity").read_text())
    # a file written before the physical-evidence tests lacks only their thresholds; without a
    # nuisance table or consistency records those tests leave its decision as it was
    physical = {"nuisance_degree", "nuisance_min_drop", "consistency_level"}
    assert set(complete["rule"]) | physical == set(DecideOptions().__dict__)
    assert all("special_case_of" in e for e in complete["evidence"])
    as_unversioned = replay_diagnosis(complete)
    as_versioned = replay_diagnosis({**complete, "format": DIAGNOSIS_FORMAT})
    as_versioned.pop("format")
    assert as_versioned == as_unversioned


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


def test_coefficient_error_is_relative_to_truth_or_to_the_change_when_truth_is_zero():
    from mosiv_framework.diagnose.suite import coefficient_error

    wind = {"kind": "wind", "params": {"acceleration": [2.0, 0.0, 0.0]}}
    assert coefficient_error({"value": {"acceleration": [2.2, 0.0, 0.0]}}, wind) == (
        pytest.approx(0.1)
    )
    # frictionless bodies (truth 0) against an assumed 0.3: 0.009 is 3 % of the 0.3 change
    frictionless = {"kind": "object_friction", "params": {"coefficient": 0.0}}
    fitted = {"value": {"friction_change": -0.291, "coefficient": 0.009}}
    assert coefficient_error(fitted, frictionless) == pytest.approx(0.03)
    # nothing to compare with: no error rather than a division by zero
    assert coefficient_error({"value": {"coefficient": 0.1}}, frictionless) is None


def test_suite_figure_draws_every_kind_of_entry(tmp_path):
    """The suite figure takes controls and misses (no coefficient, no reduction), a term that
    made the future worse, and an exact coefficient, and refuses an empty suite."""
    import imageio.v3 as iio

    from mosiv_framework.diagnose.suite import Score, summarise
    from mosiv_framework.diagnose.suite_plot import plot_suite

    scores = [
        Score(
            "wind-0",
            "wind:acceleration=1.5,0,0",
            "missing physics",
            "wind",
            "wind",
            True,
            182.0,
            0.0,
            0.99,
        ),
        Score(
            "ground_restitution-1",
            "ground_restitution:coefficient=0.9",
            "unexplained",
            None,
            "ground_restitution",
            False,
            26.6,
            None,
            None,
        ),
        Score("control-1", "-", "missing physics", "gravity", "gravity", False, 49.3, None, -0.4),
        Score(
            "outside-gravity",
            "gravity:acceleration=0,0,-7.5",
            "unexplained",
            None,
            None,
            True,
            64.8,
            None,
            None,
        ),
    ]
    summary = summarise(scores)
    path = plot_suite(summary, tmp_path / "suite.png")
    image = iio.imread(path)
    assert image.ndim == 3 and image.shape[0] > 200 and image.shape[1] > 800
    # not a blank canvas: the green and red markers are drawn
    assert image[..., :3].std() > 10
    with pytest.raises(ValueError, match="no scored entries"):
        plot_suite(summarise([]), tmp_path / "empty.png")


def test_a_recipe_sets_the_refit_budget_and_bad_values_are_named(tmp_path):
    from omegaconf import OmegaConf

    from mosiv_framework.diagnose.diagnosis import BUDGETS, resolve_budget
    from mosiv_framework.recipes import load_recipe

    recipe = "recipes/diagnose_small.yaml"
    section = load_recipe(
        recipe, ["diagnose.iterations=40", "diagnose.refit_velocity_lr=1e-4"]
    ).diagnose
    budget = resolve_budget("full", section)
    assert (budget.iterations, budget.velocity_lr) == (40, 1e-4)
    # what the recipe leaves unset stays the budget's
    assert (budget.starts, budget.polish) == (BUDGETS["full"].starts, BUDGETS["full"].polish)
    assert not budget.far_start
    assert resolve_budget(
        "full", load_recipe(recipe, ["diagnose.far_start=true"]).diagnose
    ).far_start
    assert resolve_budget("full", OmegaConf.create({})) == BUDGETS["full"]
    with pytest.raises(ConfigError, match="budget 'huge' is unknown; valid: \\['full', 'small'\\]"):
        resolve_budget("huge")
    with pytest.raises(ConfigError) as err:
        load_recipe(recipe, ["diagnose.refit_velocity_lr=0", "diagnose.polish=-1"])
    assert "diagnose.refit_velocity_lr=0.0: must be a positive step in m/s" in str(err.value)
    assert "diagnose.polish=-1: must be >= 0" in str(err.value)


def test_suite_overrides_are_checked_before_any_entry_runs(tmp_path):
    from mosiv_framework.diagnose.suite import run_suite

    with pytest.raises(ConfigError, match="diagnose.iterations=0: must be >= 1"):
        run_suite(tmp_path / "suite", small=True, overrides=["diagnose.iterations=0"])
    assert not any((tmp_path / "suite").glob("*/"))  # nothing generated


def test_the_far_start_is_added_only_when_asked_and_only_without_a_regression():
    from mosiv_framework.diagnose.candidates import Candidate
    from mosiv_framework.diagnose.diagnosis import refit_starts
    from mosiv_framework.diagnose.hypothesise import Screen

    bounce = Candidate(
        name="ground_restitution",
        kind="term",
        coefficient_names=["restitution"],
        units=["1"],
        lower=torch.tensor([0.0]),
        upper=torch.tensor([1.0]),
        step=torch.tensor([0.01]),
        regimes=frozenset({"ground_contact"}),
        description="a bounce",
    )
    contact = Screen(bounce, True, [-1.0], torch.tensor([0.1]), 0.3, 5.0, far=torch.tensor([1.0]))
    thetas = [float(t) for t, _ in refit_starts(contact, 3)]
    assert thetas == pytest.approx([0.1, 0.05, 0.15])
    with_far = refit_starts(contact, 3, far_start=True)
    assert [float(t) for t, _ in with_far] == pytest.approx([0.1, 0.05, 0.15, 1.0])
    assert with_far[-1][1] is None  # the run's initial velocities
    # a body force's regression start already carries its own estimate: no far start
    wind = Screen(
        bounce,
        True,
        [-1.0],
        torch.tensor([0.1]),
        0.3,
        5.0,
        far=torch.tensor([1.0]),
        regression=(torch.tensor([0.4]), {}),
    )
    assert len(refit_starts(wind, 3, far_start=True)) == 3


# ------------------------------------------------------------------ diverging predictions
def _diverged(frame: int = 18) -> Exception:
    from mosiv_framework.errors import SimulationDiverged

    return SimulationDiverged(
        object_id=2, frame=frame, substep=1, reason="a particle moved too far", advice="test"
    )


class _PredictingContext(_QuadraticContext):
    """A _QuadraticContext whose rollout over all frames (``frames=None``) diverges where
    ``blows_up(params)``, as a refit that fits the fit frames can still blow up after them."""

    def __init__(self, target, blows_up):
        super().__init__(target)
        self.blows_up, self.asked = blows_up, []

    def rollout(self, params, *, frames=None):
        self.asked.append(frames)
        if frames is None and self.blows_up(params):
            raise _diverged()
        return super().rollout(params, frames=frames)


def test_refit_predicts_with_the_next_best_start_when_the_best_ones_prediction_diverges():
    """The start that fits best (here the one begun at the target) blows up after the fit
    frames: the refit keeps the next-best start, whose prediction succeeds, with every start
    still listed for the interval."""
    from mosiv_framework.diagnose.model import RefitOptions, refit

    ctx = _PredictingContext([1.0, 0.0, 0.0], lambda p: float(p.initial_velocity[1][0]) > 0.5)
    starts = [(torch.zeros(0), None), (torch.zeros(0), {1: torch.tensor([1.0, 0.0, 0.0])})]
    fit = refit(ctx, None, fit_frames=[1, 2], starts=starts, options=RefitOptions(iterations=2))
    assert fit.diverged is None and fit.trajectory is not None
    assert float(fit.params.initial_velocity[1][0]) < 0.5  # the start begun at zero
    losses = sorted(loss for _, loss in fit.starts)
    assert len(losses) == 2 and fit.loss == pytest.approx(losses[1]) and losses[0] < 1e-3
    assert ctx.asked == [None, None]  # the best start's prediction, then the next one's


def test_refit_keeps_a_model_whose_every_prediction_diverges_as_evidence():
    """Every start's prediction diverges: no crash, but the best fit without a trajectory,
    with the simulator's message and its rollout up to the frame before the divergence; a
    fit that predicts replaces it in any later comparison, even at a higher fit loss."""
    from mosiv_framework.diagnose.model import Fit, RefitOptions, refit, replaces

    ctx = _PredictingContext([1.0, 0.0, 0.0], lambda p: True)
    starts = [(torch.zeros(0), None), (torch.zeros(0), {1: torch.tensor([1.0, 0.0, 0.0])})]
    fit = refit(ctx, None, fit_frames=[1, 2], starts=starts, options=RefitOptions(iterations=2))
    assert fit.trajectory is None
    assert "object 2 at frame 18, substep 1" in fit.diverged
    assert fit.loss == pytest.approx(min(loss for _, loss in fit.starts))  # the best start
    assert ctx.asked == [None, None, 17] and fit.reached is not None
    predicts = Fit("null", None, fit.params, torch.zeros(0), 10 * fit.loss + 1.0, fit.n_params)
    assert replaces(predicts, fit) and not replaces(fit, predicts)


def test_a_refit_whose_every_start_diverges_is_rejected_as_evidence_not_raised():
    """Every start of a candidate's refit diverges in its first rollout (a discovered law's did
    on two control scenes and ended the diagnosis): the model is kept at its first start with
    an infinite fit loss, the simulator's place in ``diverged`` and its rollout up to the frame
    before; a refit continued from the best model's state that diverges again leaves it as it
    was; its evidence stays strict JSON and the report gives the reason it was not accepted."""
    from mosiv_framework.diagnose.candidates import build_candidates
    from mosiv_framework.diagnose.model import RefitOptions, converge_candidates, refit
    from mosiv_framework.diagnose.report import _evidence_lines, _evidence_row
    from mosiv_framework.pipeline.params import ParameterVector

    class Context(_ScalarLoss, _FakeContext):
        asked: list = []

        def parameter_vector(self, params=None):
            v = torch.zeros(3) if params is None else params.initial_velocity[1]
            return ParameterVector.create({1: "elastic"}, {1: v.clone()}, ground_friction=None)

        def simulate(self, params, *, frames):
            self.asked.append(("wind" in params.terms, frames))
            if "wind" in params.terms and (frames is None or frames >= 3):
                raise _diverged(frame=3)  # the wind blows the bodies apart in frame 3
            return ((params.initial_velocity[1] - 1.0) ** 2).sum()

    ctx = Context(frozenset({"wind"}))
    wind = next(c for c in build_candidates(ctx)[0] if c.name == "wind")
    options = RefitOptions(iterations=2)
    null = refit(ctx, None, fit_frames=[1, 2, 3], options=options)
    starts = [(torch.tensor([0.0, 2.5, 0.0]), {1: torch.full((3,), 0.1)}), (torch.ones(3), None)]
    ctx.asked = []
    fit = refit(ctx, wind, fit_frames=[1, 2, 3], starts=starts, options=options)
    assert fit.refit_diverged and fit.trajectory is None and fit.shared is None
    assert fit.diverged == (
        "refit diverged at object 2, frame 3, substep 1 (a particle moved too far)"
    )
    assert fit.loss == math.inf and fit.starts == []
    assert fit.theta.tolist() == [0.0, 2.5, 0.0]  # the first start, velocity change and all
    assert torch.allclose(fit.params.initial_velocity[1], torch.full((3,), 0.1))
    assert fit.n_params == null.n_params + 3
    # one rollout per start, then the frames before the divergence
    assert ctx.asked == [(True, 3), (True, 3), (True, 2)] and fit.reached is not None
    assert null.diverged is None and not null.refit_diverged

    assert converge_candidates(ctx, null, [fit], fit_frames=[1, 2, 3], options=options) == [fit]

    e = Evidence("wind", -math.inf, math.inf, math.nan, False, False, fit.loss, 3)
    e.diverged = fit.diverged
    saved = json.loads(json.dumps(e.to_json(), allow_nan=False))
    assert saved["fit_loss_m2"] is None and not saved["accepted"]
    assert "| fail (refit diverged) |" in _evidence_row(saved)
    text = "\n".join(_evidence_lines({"evidence": [saved], "frames": {"fit": [1], "heldout": []}}))
    assert "`wind` was not accepted: refit diverged at object 2, frame 3, substep 1" in text


def test_a_diverged_null_is_continued_from_a_candidate_state_that_predicts():
    """The null fits the fit frames best but its prediction diverged: it is refitted again
    from a candidate's shared state, and that refit, which predicts, replaces it although it
    fits a little worse; a diverged state is never the one others continue from."""
    from mosiv_framework.diagnose.model import Fit, RefitOptions, converge_null, refit

    # a velocity above 0.5 m/s fits best and blows up after the fit frames
    ctx = _PredictingContext([1.0, 0.0, 0.0], lambda p: float(p.initial_velocity[1][0]) > 0.5)
    options = RefitOptions(iterations=2, velocity_lr=0.01)
    start = [(torch.zeros(0), {1: torch.tensor([1.0, 0.0, 0.0])})]
    null = refit(ctx, None, fit_frames=[1], starts=start, options=options)
    assert null.diverged is not None and null.loss < 1e-3
    calm = ctx.parameter_vector().physical()
    calm.initial_velocity[1] = torch.tensor([0.4, 0.0, 0.0])
    candidate = Fit("calm", None, calm, torch.zeros(1), 0.5, 7, shared=calm)
    warm = converge_null(ctx, null, [candidate], fit_frames=[1], options=options)
    assert warm.diverged is None and warm.trajectory is not None
    assert warm.started_from == "calm" and warm.loss > null.loss


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
