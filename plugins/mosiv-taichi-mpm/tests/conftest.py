"""Shared fixtures: one simulator per option set for the whole session (Taichi compiles each
kernel once per field layout; re-using simulators keeps the suite within minutes).

On several processes (pytest-xdist) these tests are one unit of work, which one worker runs
first, in their order (GROUPS in the repository's conftest.py): Taichi's offline cache keys a
kernel by the fields made before it in the process, so the same history finds the cache.
"""

import pytest

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
