"""Equivalent forms (diagnose/equivalence.py): the drag exponent from residual accelerations of
an object decelerating under a known drag law, and the uniform acceleration named as both a
wind and a gravity change with the right vectors."""

from __future__ import annotations

import numpy as np
import pytest

from mosiv_framework.diagnose.decide import Evidence
from mosiv_framework.diagnose.equivalence import (
    drag_exponent,
    drag_form,
    drag_from_samples,
    indistinguishable,
    told_from_lead,
    uniform_acceleration,
)
from mosiv_framework.diagnose.kinematics import residual_samples

FPS = 30.0
G = np.array([0.0, 0.0, -9.81])


def flight(force, v0, *, frames=45, substeps=100, p0=(0.0, 0.0, 1.0)):
    """[frames, 3] centroid path under gravity plus ``force(v)`` (semi-implicit Euler)."""
    dt = 1.0 / FPS / substeps
    p, v = np.array(p0, dtype=float), np.array(v0, dtype=float)
    out = [p.copy()]
    for _ in range(frames - 1):
        for _ in range(substeps):
            v = v + dt * (G + force(v))
            p = p + dt * v
        out.append(p.copy())
    return np.array(out)


def drag_samples(p_true, c, *, noise, seed=0):
    rng = np.random.default_rng(seed)
    out = {}
    for k, v0 in enumerate(([6.0, 1.0, 4.0], [-4.0, 3.0, 5.0])):
        law = lambda v: -c * np.linalg.norm(v) ** (p_true - 1.0) * v  # noqa: E731
        target = flight(law, v0) + noise * rng.standard_normal((45, 3))
        sim = flight(lambda v: np.zeros(3), v0)
        out[k] = residual_samples(target, sim, FPS, regimes=["free_flight"] * 45)
    return out


@pytest.mark.parametrize(
    "p_true, c, form", [(1.0, 0.8, "linear drag"), (2.0, 0.15, "quadratic drag")]
)
def test_drag_exponent_within_03_of_truth_and_form_named(p_true, c, form):
    fit = drag_from_samples(drag_samples(p_true, c, noise=1e-4))
    assert fit is not None
    assert abs(fit["exponent"] - p_true) < 0.3
    lo, hi = fit["interval"]
    assert lo <= p_true <= hi and hi - lo < 1.0
    assert fit["form"] == form


def test_drag_form_rules():
    assert drag_form(1.1, (0.8, 1.4)) == "linear drag"
    assert drag_form(1.9, (1.6, 2.3)) == "quadratic drag"
    assert drag_form(1.5, (0.9, 2.1)) == "drag, exponent 1.50 +- 0.60"
    assert drag_form(2.8, (2.6, 3.0)).startswith("drag, exponent 2.80")


def test_drag_exponent_needs_moving_samples():
    assert drag_exponent(np.zeros((5, 3)), np.zeros((5, 3))) is None


def test_constant_acceleration_is_wind_or_gravity_with_the_right_vectors():
    a = np.array([0.6, -0.3, 1.2])  # a wind that also lowers gravity
    fit = uniform_acceleration(
        "wind", {"acceleration": a.tolist()}, [[0.5, 0.7], [-0.4, -0.2], [1.1, 1.3]], G
    )
    assert fit["acceleration"] == pytest.approx(a.tolist())
    assert fit["gravity"] == pytest.approx((G + a).tolist())
    assert fit["gravity_magnitude"] == pytest.approx(np.linalg.norm(G + a))
    lo, hi = fit["gravity_magnitude_interval"]
    assert lo <= np.linalg.norm(G + a) <= hi
    terms = {e["term"]: e["value"] for e in fit["equivalent"]}
    assert set(terms) == {"wind", "gravity"}
    assert terms["wind"]["acceleration"] == pytest.approx(a.tolist())
    assert terms["gravity"]["acceleration"] == pytest.approx((G + a).tolist())


def test_gravity_candidate_reports_its_change_as_an_acceleration():
    lower = 0.9 * G  # gravity candidate's value: the replacing vector
    fit = uniform_acceleration("gravity", {"acceleration": lower.tolist()}, [[-1.2, -0.8]], G)
    assert fit["acceleration"] == pytest.approx((lower - G).tolist())
    assert fit["gravity_magnitude"] == pytest.approx(0.9 * 9.81)
    lo, hi = fit["gravity_magnitude_interval"]
    assert lo == pytest.approx(9.81 - 1.2) and hi == pytest.approx(9.81 - 0.8)
    assert uniform_acceleration("linear_drag", {"coefficient": 1.0}, None, G) is None


def test_uniform_acceleration_from_residuals_matches_wind():
    a = np.array([0.5, 0.0, 0.0])
    target = flight(lambda v: a, [1.0, 0.0, 3.0])
    sim = flight(lambda v: np.zeros(3), [1.0, 0.0, 3.0])
    res = residual_samples(target, sim, FPS).residual
    assert res.mean(axis=0) == pytest.approx(a, abs=1e-6)
    assert res.std(axis=0) == pytest.approx(np.zeros(3), abs=1e-6)


def test_indistinguishable_lists_equal_predictions_only():
    rng = np.random.default_rng(0)
    base = 1.0 + rng.random((2, 20))
    errors = {
        "wind": base,
        "gravity": base * (1 + 0.001 * rng.standard_normal((2, 20))),
        "linear_drag": 2.0 * base,
    }
    same = indistinguishable(
        "wind", errors, ["gravity", "linear_drag"], list(range(20)), z=2.0, block=2, resamples=200
    )
    assert [e["term"] for e in same] == ["gravity"]


def _explaining(name: str):
    return Evidence(
        name=name,
        heldout_drop=0.8,
        heldout_spread=0.05,
        delta_bic=-10.0,
        passes_heldout=True,
        passes_bic=True,
        fit_loss=1.0,
        n_new=1,
    )


def test_equivalence_is_said_of_the_term_ranked_first():
    """The drag form's preference can move linear drag ahead of quadratic drag after the
    equivalences were found from quadratic drag: the report then names linear drag as the
    reference and quadratic drag as the term it cannot be told apart from."""
    forms = {"best": "quadratic_drag", "equivalent": ["linear_drag"], "drag": None}
    ranked = [_explaining("linear_drag"), _explaining("quadratic_drag")]
    told = told_from_lead(forms, ranked)
    assert told["best"] == "linear_drag"
    assert told["equivalent"] == ["quadratic_drag"]
    # a lead not among the equivalents leaves the statement as found
    ranked = [_explaining("wind"), _explaining("quadratic_drag")]
    assert told_from_lead(forms, ranked) == forms
    assert told_from_lead({}, ranked) == {}
