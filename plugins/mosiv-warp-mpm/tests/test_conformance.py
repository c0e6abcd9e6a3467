"""The framework's BackendConformance suite (laws against the torch reference, shared physics
cases) run on the Warp backend, the reference every other backend is compared with."""

from __future__ import annotations

import os

from mosiv_framework.testing.conformance import BackendConformance


class TestWarpConformance(BackendConformance):
    backend = "warp-mpm"
    reference = None  # warp-mpm is the reference backend: the parity tests skip
    device = os.environ.get("MOSIV_TEST_DEVICE", "cpu")
