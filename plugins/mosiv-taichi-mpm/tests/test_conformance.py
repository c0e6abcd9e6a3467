"""The framework's BackendConformance suite on the Taichi backend: laws against the torch
reference, forward rollouts and gradients against warp-mpm, and the shared physics cases."""

from __future__ import annotations

import pytest

from mosiv_framework.testing.conformance import BackendConformance


class TestTaichiConformance(BackendConformance):
    backend = "taichi-mpm"
    reference = "warp-mpm"
    # Every law's gradients are held to warp-mpm's by the parity suite (tests/test_parity.py),
    # and checked against finite differences law by law in mosiv-warp-mpm and on sand, newtonian
    # and two bodies in contact here (test_gradients.py); so this suite's parity of the two
    # adjoints, over a minute of CPU per scene, runs on the two-body contact scene only: the path
    # (fields, contact normals, Coulomb projection) that the single-body scenes never reach.
    gradient_scenes = ("collision",)

    @pytest.fixture(autouse=True)
    def _use_cached_simulators(self, simulator_factory):
        # Taichi compiles its kernels once per field layout: reuse the suite's cached simulators
        self._factory = simulator_factory

    def make_simulator(self, **options):
        return self._factory(**options)
