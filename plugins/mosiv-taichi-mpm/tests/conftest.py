"""Shared fixtures: one simulator per option set for the whole session (Taichi compiles each
kernel once per field layout; re-using simulators keeps the suite within minutes).

On several processes (pytest-xdist, the repository's conftest.py) these tests are one group:
one worker runs them all, in their order, before anything else. Taichi's offline cache keys a
kernel by the fields made before it in the process, so that history, and with it the cache,
is the same every run; spread over the workers, the kernels would compile again each time.
"""

from pathlib import Path

import pytest

HERE = Path(__file__).parent


@pytest.hookimpl(tryfirst=True)  # before xdist's hook reads the groups
def pytest_collection_modifyitems(config, items):
    for item in items:
        if HERE in item.path.parents:
            item.add_marker(pytest.mark.xdist_group("mosiv-taichi-mpm"))


_CACHE: dict = {}


def make_simulator(**options):
    """A cached TaichiMPMSimulator for these options (CPU)."""
    from mosiv_taichi_mpm.plugin import make_simulator as factory

    key = tuple(sorted(options.items()))
    if key not in _CACHE:
        _CACHE[key] = factory(device="cpu", **options)
    return _CACHE[key]


@pytest.fixture(scope="session")
def simulator_factory():
    return make_simulator
