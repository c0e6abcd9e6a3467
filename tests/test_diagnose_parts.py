"""Unit tests of the diagnosis's parts on synthetic signals with known answers (no simulator)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from mosiv_framework.diagnose import split_frames
from mosiv_framework.diagnose.changepoint import hinge_change_point, mean_shift_change_point
from mosiv_framework.diagnose.decide import bic, bootstrap_drop, verdict
from mosiv_framework.diagnose.hypothesise import bic_gain
from mosiv_framework.diagnose.locate import decompose_direction, label_regimes
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
    assert bic_gain(0.0, n=n, dim=1) == pytest.approx(-math.log(n))
    # explaining half the residual with one coefficient from 10 residuals is worth it
    assert bic_gain(0.5, n=n, dim=1) == pytest.approx(n * math.log(2) - math.log(n))


def test_verdicts():
    class E:
        def __init__(self, accepted):
            self.accepted = accepted

    assert verdict(True, [E(True)]) == "missing physics"
    assert verdict(True, [E(False)]) == "unexplained"
    assert verdict(False, []) == "no missing physics"


def test_split_frames_holds_out_the_end_of_the_window_and_the_future():
    fit, held = split_frames(8, 12, 0.25)
    assert fit == [1, 2, 3, 4, 5] and held == [6, 7, 8, 9, 10, 11]
    fit, held = split_frames(8, 12, 0.0)
    assert fit == list(range(1, 8)) and held == [8, 9, 10, 11]
    # without future frames the held-out frames come from the observed window
    fit, held = split_frames(8, 8, 0.0)
    assert fit == list(range(1, 6)) and held == [6, 7]
    with pytest.raises(ConfigError, match="observes 4 of 4 frames"):
        split_frames(4, 4, 0.25)
