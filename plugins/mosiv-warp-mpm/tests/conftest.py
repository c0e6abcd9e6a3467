"""Shared fixture: a factory of warp-mpm simulators (Warp kernels compile once).

The device is CPU unless MOSIV_TEST_DEVICE=cuda, which runs the same suite on a GPU.
"""

from __future__ import annotations

import os

import pytest
from mosiv_warp_mpm.plugin import make_simulator


@pytest.fixture(scope="session")
def make_warp_simulator():
    def make(**options):
        return make_simulator(device=os.environ.get("MOSIV_TEST_DEVICE", "cpu"), **options)

    return make
