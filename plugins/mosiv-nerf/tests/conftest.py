"""A tiny two-sphere scene and its frame-0 field, shared by the tests of a module."""

from __future__ import annotations

import pytest

from mosiv_framework.scene import read_scene
from mosiv_framework.scene.example import write_example_scene

#: tiny frame-0 fit: 35 s on the shared 2-core development machine (test_field.py)
TINY_FIELD = dict(
    resolution=20,
    iterations=120,
    rays_per_step=1024,
    step_ratio=1.0,
    hull_resolution=24,
    hull_points=200,
    device="cpu",
)


@pytest.fixture(scope="session")
def tiny_scene(tmp_path_factory):
    path = write_example_scene(
        tmp_path_factory.mktemp("nerf") / "scene", n_frames=6, n_cameras=4, size=32
    )
    return read_scene(path)


@pytest.fixture(scope="session")
def tiny_reconstruction(tiny_scene):
    from mosiv_nerf.reconstructor import NerfFieldReconstructor

    return NerfFieldReconstructor(**TINY_FIELD).fit(tiny_scene)


@pytest.fixture(scope="session")
def field_options() -> dict:
    """The options of the tiny frame-0 fit, for a test that fits another scene alike."""
    return dict(TINY_FIELD)
