"""Shared fixture: a factory of warp-mpm simulators on CPU (Warp kernels compile once)."""

from __future__ import annotations

import pytest
from mosiv_warp_mpm.plugin import make_simulator


@pytest.fixture(scope="session")
def make_warp_simulator():
    def make(**options):
        return make_simulator(device="cpu", **options)

    return make
