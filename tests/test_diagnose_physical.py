"""Physical-evidence tests (diagnose/physical.py, decide.apply_physical_tests): a body force's
coefficient must agree across objects, and a candidate must beat the nuisance model (a smooth
per-object correction) unless it ties with it while agreeing across objects."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from mosiv_framework.diagnose.decide import DecideOptions, Evidence, apply_physical_tests, verdict
from mosiv_framework.diagnose.kinematics import ResidualSamples
from mosiv_framework.diagnose.physical import consistency, nuisance_displacement
from mosiv_framework.terms import Wind


class WindCandidate:
    """The part of ``candidates.Candidate`` the tests read: a 3-coefficient body force."""

    dim = 3

    def acceleration(self, velocity, theta):
        return Wind().reference_acceleration(velocity, {"acceleration": theta})


def samples(accel, seed, n=30, noise=0.02):
    rng = np.random.default_rng(seed)
    return ResidualSamples(
        np.arange(1, n + 1),
        np.arange(1, n + 1) / 30.0,
        rng.standard_normal((n, 3)),
        rng.standard_normal((n, 3)),
        np.asarray(accel) + noise * rng.standard_normal((n, 3)),
        ["free_flight"] * n,
    )


def test_same_wind_on_every_object_is_consistent_and_different_biases_are_not():
    wind = [0.5, 0.0, -0.2]
    same = consistency(WindCandidate(), {0: samples(wind, 0), 1: samples(wind, 1)})
    assert same["consistent"] is True and same["objects"] == 2
    assert same["pooled"] == pytest.approx(wind, abs=0.02)
    lo, hi = same["per_object"]["0"]["interval"][0]
    assert lo <= 0.5 <= hi
    apart = consistency(WindCandidate(), {0: samples(wind, 0), 1: samples([-0.5, 0, 0.3], 1)})
    assert apart["consistent"] is False
    single = consistency(WindCandidate(), {0: samples(wind, 0)})
    assert single["consistent"] is None


def test_the_tolerance_allows_a_few_percent_between_objects_and_no_more():
    """Two bodies with well-sampled free flight (noise 0.002 m/s^2, 200 samples each) whose
    winds differ by 2 %: their intervals alone disagree; with a standard deviation of 5 % of
    the pooled magnitude added to each, they agree. Winds 40 % apart disagree under that
    tolerance too. A replay that has only the intervals decides the tolerance on them
    (diagonal covariances)."""
    from mosiv_framework.diagnose.physical import agreement

    wind, near, far = [0.0, 0.0, 2.3], [0.0, 0.0, 2.346], [0.0, 0.0, 3.2]

    def two(second):
        return {0: samples(wind, 0, n=200, noise=0.002), 1: samples(second, 1, n=200, noise=0.002)}

    assert consistency(WindCandidate(), two(near))["consistent"] is False
    close = consistency(WindCandidate(), two(near), tolerance=0.05)
    assert close["consistent"] is True
    assert close["pooled"] == pytest.approx([0.0, 0.0, 2.323], abs=2e-3)
    assert consistency(WindCandidate(), two(far), tolerance=0.05)["consistent"] is False
    intervals_only = {
        k: {"theta": r["theta"], "interval": r["interval"]} for k, r in close["per_object"].items()
    }
    assert agreement(intervals_only, 0.95, 0.05)["consistent"] is True
    assert agreement(intervals_only, 0.95, 0.0)["consistent"] is False


def test_a_candidate_without_acceleration_has_no_consistency_test():
    class Contact:
        dim = 1

        def acceleration(self, velocity, theta):
            return None

    assert consistency(Contact(), {0: samples([0, 0, 0], 0)}) is None


def test_nuisance_displacement_fits_a_constant_acceleration_bias():
    fps, a, v = 30.0, np.array([0.3, -0.1, 0.0]), np.array([0.05, 0.0, 0.02])
    t = np.arange(20) / fps
    residual = np.outer(t, v) + 0.5 * np.outer(t**2, a)
    fit = list(range(1, 14))
    shift = nuisance_displacement(residual, fit, fps, degree=2)
    np.testing.assert_allclose(shift, residual, atol=1e-10)  # extrapolates the held-out frames
    linear = nuisance_displacement(residual, fit, fps, degree=1)
    assert np.abs(linear[19] - residual[19]).max() > 1e-3


def _evidence():
    return Evidence("wind", 0.5, 0.02, -20.0, True, True, 1e-6, 3)


def test_candidate_must_beat_the_nuisance_model_or_tie_with_object_agreement():
    rng = np.random.default_rng(0)
    null = 4.0 + rng.random((2, 12))
    held = list(range(6, 12))
    options = DecideOptions(bootstrap=200)
    wind = 1.0 + 0.1 * rng.random((2, 12))
    # the nuisance correction predicts as well as the candidate: no physical evidence
    errors = {"null": null, "wind": wind, "nuisance": wind * (1 + 0.01 * rng.random((2, 12)))}
    ranked = apply_physical_tests([_evidence()], errors, {"wind": None}, held, options)
    assert not ranked[0].passes_nuisance and not ranked[0].accepted
    assert verdict(True, ranked) == "discrepancy"
    # ... unless the coefficient agrees across two objects
    agree = {"wind": {"objects": 2, "consistent": True}}
    ranked = apply_physical_tests([_evidence()], errors, agree, held, options)
    assert ranked[0].accepted and verdict(True, ranked) == "missing physics"
    # disagreeing objects fail even a clear win over the nuisance model
    errors["nuisance"] = 3.0 * wind
    differ = {"wind": {"objects": 2, "consistent": False}}
    ranked = apply_physical_tests([_evidence()], errors, differ, held, options)
    assert ranked[0].passes_nuisance and not ranked[0].passes_consistency
    ranked = apply_physical_tests([_evidence()], errors, {"wind": None}, held, options)
    assert ranked[0].accepted and ranked[0].nuisance_drop == pytest.approx(2 / 3, abs=0.01)


def test_wind_reference_is_linear_in_its_coefficients():
    v = torch.randn(4, 3)
    acc = WindCandidate().acceleration(v, torch.tensor([1.0, 2.0, 3.0]))
    assert torch.allclose(acc, torch.tensor([1.0, 2.0, 3.0]).expand(4, 3))
