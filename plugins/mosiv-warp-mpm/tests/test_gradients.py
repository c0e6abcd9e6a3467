"""Rollout gradients of the Warp backend against central finite differences (5%), per law,
and through multi-field contact between two objects."""

from __future__ import annotations

import pytest

from mosiv_framework.laws import FAMILIES
from mosiv_framework.testing.physics_cases import (
    collision_gradient_check,
    gradient_check,
    interleaved_rollouts_check,
)


@pytest.mark.parametrize("family", FAMILIES)
def test_gradients_match_finite_differences(family, make_warp_simulator) -> None:
    report = gradient_check(make_warp_simulator, family)
    print(family, report)


def test_collision_gradients_match_finite_differences(make_warp_simulator) -> None:
    # guards the contact adjoint: sums over fields in a run-time loop lost their gradients
    report = collision_gradient_check(make_warp_simulator)
    print(report)


def test_a_rollout_between_forward_and_backward_leaves_the_gradients_alone(make_warp_simulator):
    report = interleaved_rollouts_check(make_warp_simulator)
    print("interleaved", report)
