"""pytest plugin (entry point ``pytest11``): fixtures for MOSIV plugin authors.

- ``mosiv_registry``: the registry of installed plugins;
- ``mosiv_example_scene``: a small valid ``mosiv-scene/1`` folder (two analytic spheres);
- ``mosiv_make_simulator``: factory of the simulator named by ``--mosiv-backend``;
- ``require_simulator(name)``: skip a test that needs a simulator plugin not installed.
"""

from __future__ import annotations

import pytest


def pytest_addoption(parser):
    group = parser.getgroup("mosiv")
    group.addoption(
        "--mosiv-backend",
        default="warp-mpm",
        help="registered simulator used by the mosiv_make_simulator fixture",
    )
    group.addoption("--mosiv-device", default="cpu", help="cpu or cuda")


@pytest.fixture(scope="session")
def mosiv_registry():
    from mosiv_framework.registry import get_registry

    return get_registry()


@pytest.fixture
def mosiv_example_scene(tmp_path):
    from mosiv_framework.scene.example import write_example_scene

    return write_example_scene(tmp_path / "scene", n_frames=4, n_cameras=2, size=24)


@pytest.fixture
def mosiv_make_simulator(request, mosiv_registry):
    name = request.config.getoption("--mosiv-backend")
    device = request.config.getoption("--mosiv-device")
    return lambda **options: mosiv_registry.create("simulator", name, {**options, "device": device})


def require_simulator(name: str):
    """The registry, after skipping the calling test when simulator ``name`` is not installed.

    The core and the plugins other than the backend meet a simulator only through the
    registry (a plugin never imports another), and a simulator is an optional plugin, so a
    test that needs one says so here; the README's test command installs both backends, so
    there these tests run."""
    from mosiv_framework.registry import get_registry

    registry = get_registry()
    if name not in registry.names("simulator"):
        pytest.skip(f"simulator {name!r} is not installed")
    return registry
