"""The shared MPM physics cases (mosiv_framework.testing.physics_cases) on the Warp backend."""

from __future__ import annotations

import pytest

from mosiv_framework.testing import physics_cases


@pytest.mark.parametrize("case", physics_cases.ALL_CASES, ids=lambda c: c.__name__)
def test_physics_case(case, make_warp_simulator) -> None:
    result = case(make_warp_simulator)
    print(case.__name__, result)
