"""Conformance tests for simulator backends, for third-party authors (pandas-style base tests).

One line checks a backend::

    from mosiv_framework.testing import check_backend
    assert check_backend("my-sim").passed

or, to get one pytest test per law, scene and physics case::

    from mosiv_framework.testing import BackendConformance

    class TestMySim(BackendConformance):
        backend = "my-sim"          # registered simulator name (or override make_simulator)
"""

from __future__ import annotations

import pytest

from mosiv_framework.laws import FAMILIES
from mosiv_framework.testing import physics_cases
from mosiv_framework.testing.parity import (
    SCENE_OPTIONS,
    ParityReport,
    check_forward,
    check_gradients,
    check_law,
    run_parity,
)


def _make(backend, device: str):
    """make_simulator(**options) for a registered name or an already built simulator."""
    if isinstance(backend, str):
        from mosiv_framework.registry import get_registry

        return lambda **options: get_registry().create(
            "simulator", backend, {**options, "device": device}
        )
    return lambda **options: backend


def check_backend(
    backend,
    *,
    reference: str | None = "warp-mpm",
    laws: tuple[str, ...] = FAMILIES,
    device: str = "cpu",
    gradients: bool = True,
) -> ParityReport:
    """Parity of ``backend`` (registered name or Simulator instance) against the torch
    reference laws and, if ``reference`` names an installed simulator, against it."""
    name = backend if isinstance(backend, str) else type(backend).__name__
    backends = {name: _make(backend, device)}
    if reference is not None and reference != name:
        backends = {reference: _make(reference, device), **backends}
    return run_parity(backends, laws=laws, gradients=gradients)


class BackendConformance:
    """Base class of a backend's conformance tests; subclass it in a module named test_*.py."""

    backend: str = ""
    reference: str | None = "warp-mpm"
    device: str = "cpu"
    #: scenes of test_gradients_match_reference_backend; each differentiates a rollout on both
    #: backends (minutes on a CPU). A backend whose own finite-difference tests cover every law
    #: may narrow it; only the scenes listed are collected.
    gradient_scenes: tuple[str, ...] = (*FAMILIES, "collision")

    def pytest_generate_tests(self, metafunc):
        # pytest calls this on an instance of the test class while collecting, so the
        # subclass's gradient_scenes decides which comparisons exist (none are collected and
        # skipped)
        if metafunc.function.__name__ == "test_gradients_match_reference_backend":
            metafunc.parametrize("scene", self.gradient_scenes)

    def make_simulator(self, **options):
        return _make(self.backend, self.device)(**options)

    def _reference_pair(self):
        if self.reference is None or self.reference == self.backend:
            pytest.skip("no reference backend to compare with")  # parity needs two backends
        return {
            self.reference: _make(self.reference, self.device)(**SCENE_OPTIONS),
            self.backend: self.make_simulator(**SCENE_OPTIONS),
        }

    @pytest.mark.parametrize("family", FAMILIES)
    def test_law_matches_torch_reference(self, family):
        results = check_law(self.make_simulator(**SCENE_OPTIONS), self.backend, family)
        report = ParityReport(results)
        assert report.passed, report.table()

    @pytest.mark.parametrize("scene", [*FAMILIES, "collision"])
    def test_forward_matches_reference_backend(self, scene):
        report = ParityReport(check_forward(self._reference_pair(), scene))
        assert report.passed, report.table()

    def test_gradients_match_reference_backend(self, scene):
        report = ParityReport(check_gradients(self._reference_pair(), scene))
        assert report.passed, report.table()

    @pytest.mark.parametrize("case", physics_cases.ALL_CASES, ids=lambda c: c.__name__)
    def test_physics(self, case):
        case(self.make_simulator)
