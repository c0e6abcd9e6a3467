"""The shared physics acceptance cases (mosiv_framework.testing.physics_cases) on Taichi."""

import pytest

from mosiv_framework.testing import physics_cases


@pytest.mark.parametrize("case", physics_cases.ALL_CASES, ids=lambda c: c.__name__)
def test_shared_physics_case(case, simulator_factory):
    result = case(simulator_factory)
    assert isinstance(result, dict) and result
