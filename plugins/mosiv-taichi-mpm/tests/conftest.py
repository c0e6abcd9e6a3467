"""Shared fixtures: one simulator per option set for the whole session (Taichi compiles each
kernel once per field layout; re-using simulators keeps the suite within minutes).

On several processes (pytest-xdist) these tests are one unit of work, which one worker runs
first, in their order (GROUPS in the repository's conftest.py): Taichi's offline cache keys a
kernel by the fields made before it in the process, so the same history finds the cache.
"""

import os

import pytest

_CACHE: dict = {}

#: the thrown bodies' velocities (m/s): they meet mid-domain, then land on the table
THROWN_VELOCITIES = {1: (1.2, 0.1, -0.4), 2: (-1.2, 0.0, -0.6)}


def make_simulator(**options):
    """A cached TaichiMPMSimulator for these options, on the CPU unless MOSIV_TEST_DEVICE=cuda
    (the same suite on a GPU)."""
    from mosiv_taichi_mpm.plugin import make_simulator as factory

    options.setdefault("device", os.environ.get("MOSIV_TEST_DEVICE", "cpu"))
    key = tuple(sorted(options.items()))
    if key not in _CACHE:
        _CACHE[key] = factory(**options)
    return _CACHE[key]


@pytest.fixture(scope="session")
def simulator_factory():
    return make_simulator


def two_thrown_spheres(terms: dict, *, requires_grad: bool = False):
    """Two SVD-law spheres (plasticine, sand) thrown into each other and onto the table, with
    the physics ``terms`` on. Returns (particles, params, world)."""
    from mosiv_framework.testing.shapes import combine, default_params, sphere
    from mosiv_framework.types import World

    world = World(
        domain_lower=(0.0, 0.0, 0.0),
        domain_upper=(0.5, 0.5, 0.5),
        gravity=(0.0, 0.0, -9.8),
        ground_height=0.0,
        fps=24.0,
    )
    a = sphere((0.17, 0.25, 0.12), 0.06, spacing=1.0 / 48, object_id=1, material="plasticine")
    b = sphere((0.33, 0.25, 0.15), 0.06, spacing=1.0 / 48, object_id=2, material="sand")
    particles = combine([a, b])
    params = default_params(
        particles,
        overrides={1: {"friction": 0.4, "yield_stress": 800.0}, 2: {"friction": 0.2}},
        velocities=THROWN_VELOCITIES,
        terms=terms,
        requires_grad=requires_grad,
    )
    return particles, params, world


@pytest.fixture(scope="session")
def thrown_spheres():
    """``two_thrown_spheres``, for tests (the tests import no module of this folder)."""
    return two_thrown_spheres
