"""The framework's BackendConformance suite (laws against the torch reference, shared physics
cases) run on the Warp backend, the reference every other backend is compared with."""

from __future__ import annotations

import os

from mosiv_framework.testing.conformance import BackendConformance


class TestWarpConformance(BackendConformance):
    backend = "warp-mpm"
    reference = None
    device = os.environ.get("MOSIV_TEST_DEVICE", "cpu")
    # warp-mpm is the reference every other backend is compared with: it has nothing to be
    # compared to, so these two are not collected here (rather than collected and skipped)
    test_forward_matches_reference_backend = None
    test_gradients_match_reference_backend = None
