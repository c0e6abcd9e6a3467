"""Open-form discovery (diagnose/discover.py) on trajectories with a known force law: the
residual acceleration of a path integrated under gravity plus the law, against the same start
under gravity alone, is regressed on the feature library; the kept terms and their
coefficients must be the law's."""

from __future__ import annotations

import numpy as np
import pytest

from mosiv_framework.diagnose.discover import (
    best_subset,
    discover,
    formula,
    independent_columns,
    stlsq,
)
from mosiv_framework.diagnose.kinematics import residual_samples

FPS = 30.0
G = np.array([0.0, 0.0, -9.81])


def integrate(p0, v0, force, *, frames=60, substeps=200):
    """[frames, 3] positions at FPS of x'' = g + force(p, v), by RK4 with small steps."""

    def f(state):
        p, v = state[:3], state[3:]
        return np.concatenate([v, G + force(p, v)])

    dt = 1.0 / FPS / substeps
    state = np.concatenate([p0, v0]).astype(np.float64)
    out = [state[:3].copy()]
    for _ in range(frames - 1):
        for _ in range(substeps):
            k1 = f(state)
            k2 = f(state + dt / 2 * k1)
            k3 = f(state + dt / 2 * k2)
            k4 = f(state + dt * k3)
            state = state + dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        out.append(state[:3].copy())
    return np.array(out)


def samples_under(force, starts, noise=0.0, seed=0):
    rng = np.random.default_rng(seed)
    out = {}
    for k, (p0, v0) in enumerate(starts):
        target = integrate(np.array(p0), np.array(v0), force)
        target = target + noise * rng.standard_normal(target.shape)
        sim = integrate(np.array(p0), np.array(v0), lambda p, v: np.zeros(3))
        out[k] = residual_samples(target, sim, FPS)
    return out


def terms(result, axis):
    return {t["feature"]: t for t in result["axes"][axis]["terms"]}


# three objects: along one or two harmonic paths position, velocity and time features are
# nearly dependent, and a point attractor cannot be told from them
STARTS = [
    ([0.3, -0.2, 1.0], [0.5, 0.8, 3.0]),
    ([-0.4, 0.5, 1.5], [-0.7, 0.2, 2.0]),
    ([0.8, 0.4, 0.6], [0.1, -0.9, 1.0]),
]


def test_point_attractor_is_found_with_its_coefficients():
    k, centre = 2.5, np.array([0.2, 0.1, 1.2])
    result = discover(samples_under(lambda p, v: -k * (p - centre), STARTS), ground_height=0.0)
    # a = -k (p - c): a_x = -k x + k c_x, a_y = -k y + k c_y, a_z = -k h + k c_z
    for axis, pos, c in (("x", "x", centre[0]), ("y", "y", centre[1]), ("z", "h", centre[2])):
        found = terms(result, axis)
        assert set(found) == {"1", pos}, result["axes"][axis]["formula"]
        assert found[pos]["coefficient"] == pytest.approx(-k, rel=0.15)
        assert found["1"]["coefficient"] == pytest.approx(k * c, rel=0.15)
        lo, hi = found[pos]["interval"]
        assert lo <= found[pos]["coefficient"] <= hi
    assert result["node_local"]


def test_vortex_is_found_with_its_coefficients():
    w, centre = 3.0, np.array([0.1, -0.2, 0.0])
    omega = np.array([0.0, 0.0, w])
    result = discover(samples_under(lambda p, v: np.cross(omega, p - centre), STARTS))
    # a = w x (p - c) with w along z: a_x = -w (y - c_y), a_y = w (x - c_x), a_z = 0
    fx, fy = terms(result, "x"), terms(result, "y")
    assert set(fx) == {"1", "y"} and set(fy) == {"1", "x"}, result["formula"]
    assert fx["y"]["coefficient"] == pytest.approx(-w, rel=0.15)
    assert fx["1"]["coefficient"] == pytest.approx(w * centre[1], rel=0.15)
    assert fy["x"]["coefficient"] == pytest.approx(w, rel=0.15)
    assert fy["1"]["coefficient"] == pytest.approx(-w * centre[0], rel=0.15)
    assert result["axes"]["z"]["terms"] == []
    assert result["axes"]["z"]["formula"] == "a_z = 0"


def test_drag_law_with_noise_keeps_velocity_terms():
    c = 0.6
    result = discover(samples_under(lambda p, v: -c * v, STARTS, noise=2e-5))
    for axis in ("x", "y", "z"):
        found = terms(result, axis)
        assert f"v_{axis}" in found, result["formula"]
        assert found[f"v_{axis}"]["coefficient"] == pytest.approx(-c, rel=0.15)


def test_formula_text_and_helpers():
    text = formula(
        "x", [{"feature": "v_x", "coefficient": -0.41}, {"feature": "|v|v_x", "coefficient": -0.02}]
    )
    assert text == "a_x = -0.41 v_x - 0.02 |v|v_x"
    x = np.column_stack([np.ones(5), np.arange(5.0), np.arange(5.0) + 2.0, np.zeros(5)])
    assert independent_columns(x) == [0, 1]  # x+2 lies in span{1, x}; zeros carry nothing
    rng = np.random.default_rng(1)
    a = rng.standard_normal((50, 4))
    y = 2.0 * a[:, 1] + 1e-4 * a[:, 3]
    coef = stlsq(a, y, cutoff=0.05 * float(np.sqrt((y**2).mean())))
    assert np.flatnonzero(coef).tolist() == [1] and coef[1] == pytest.approx(2.0, rel=1e-3)


def test_too_few_samples_gives_none():
    short = {0: residual_samples(np.zeros((5, 3)), np.zeros((5, 3)), FPS)}
    assert discover(short) is None


def test_best_subset_picks_the_generating_columns_over_a_proxy():
    rng = np.random.default_rng(2)
    a = rng.standard_normal((80, 6))
    proxy = a[:, 0] + a[:, 1] + 0.3 * rng.standard_normal(80)  # correlated with the truth
    x = np.column_stack([a, proxy])
    y = 1.5 * a[:, 0] + 1.5 * a[:, 1] + 1e-3 * rng.standard_normal(80)
    assert sorted(best_subset(x, y, max_terms=3)) == [0, 1]
