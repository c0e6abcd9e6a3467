"""Unit tests of where the diagnosis looks: change points, regimes, the residual's direction,
the fit/held-out split, the noise floor and the resolution floor, on synthetic signals with
known answers (no simulator)."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from mosiv_framework.diagnose import split_frames
from mosiv_framework.diagnose.changepoint import hinge_change_point, mean_shift_change_point
from mosiv_framework.diagnose.locate import (
    decompose_direction,
    difference_noise_std,
    difference_variance_factor,
    estimate_noise,
    label_regimes,
    points_are_tracked,
)
from mosiv_framework.errors import ConfigError

# shared fakes of the diagnosis tests; --import-mode=importlib leaves this folder off sys.path
HERE = Path(__file__).resolve().parent
if str(HERE) not in sys.path:
    sys.path.insert(0, str(HERE))
from diagnose_fakes import _elastic_pair_params  # noqa: E402


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
# resolution floor


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
