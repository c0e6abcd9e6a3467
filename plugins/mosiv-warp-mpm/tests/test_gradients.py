"""Rollout gradients of the Warp backend against central finite differences (5%), per law."""

from __future__ import annotations

import pytest

from mosiv_framework.laws import FAMILIES
from mosiv_framework.testing.physics_cases import gradient_check

# Snow recomposes U diag(clamp(s)) V^T where singular values nearly coincide; Warp's svd3 adjoint
# (1 / (s_i^2 - s_j^2) clamped at 1e6) then gives wrong gradients. Known issue, see the report.
SNOW_SVD = pytest.mark.xfail(reason="svd3 adjoint ill-conditioned for clamped snow", strict=True)


@pytest.mark.parametrize(
    "family", [pytest.param(f, marks=SNOW_SVD) if f == "snow" else f for f in FAMILIES]
)
def test_gradients_match_finite_differences(family, make_warp_simulator) -> None:
    report = gradient_check(make_warp_simulator, family)
    print(family, report)
