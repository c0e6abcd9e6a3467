"""The framework's BackendConformance suite on the Taichi backend: laws against the torch
reference, forward rollouts and gradients against warp-mpm, and the shared physics cases."""

from __future__ import annotations

import pytest

from mosiv_framework.testing.conformance import BackendConformance


class TestTaichiConformance(BackendConformance):
    backend = "taichi-mpm"
    reference = "warp-mpm"
    # Gradients of every law are checked against finite differences on both backends
    # (test_gradients.py here and in mosiv-warp-mpm), so the parity of the two adjoints, over a
    # minute of CPU per scene, is checked on the two-body contact scene only: the path (fields,
    # contact normals, Coulomb projection) that the single-body scenes never reach.
    gradient_scenes = ("collision",)

    @pytest.fixture(autouse=True)
    def _use_cached_simulators(self, simulator_factory):
        # Taichi compiles its kernels once per field layout: reuse the suite's cached simulators
        self._factory = simulator_factory

    def make_simulator(self, **options):
        return self._factory(**options)
