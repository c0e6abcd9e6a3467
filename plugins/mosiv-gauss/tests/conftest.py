"""Shared fixtures of the mosiv-gauss tests: one tiny generated scene and one fit of it.

The scene comes from the registered ``synth`` scene source (plugins never import each other):
two objects colliding in mid-air, 4 cameras at 48x48, 6 frames, coarse particles. It is made
once per session and the dynamic reconstructor is fitted to it once, so the end-to-end tests
share one CPU run of about half a minute. On several processes (pytest-xdist) the modules that
use them are one unit of work, run by one worker (GROUPS in the repository's conftest.py).
"""

from __future__ import annotations

import pytest

from mosiv_framework.registry import get_registry
from mosiv_framework.scene import read_scene

#: the tiny scene (the known-good tiny synth options of recipes/quickstart.yaml, 6 frames)
TINY_SCENE = {
    "n_objects": 2,
    "materials": "elastic,plasticine",
    "resolution": 48,
    "n_cameras": 4,
    "n_frames": 6,
    "observed_frames": 6,
    "particle_spacing": 0.015,
    "collision_frame": 3,
    "simulator": "warp-mpm",
    "simulator_options": {"grid": 32, "substeps": 40, "device": "cpu"},
    "seed": 0,
    "progress": False,
}

#: gauss-dynamic options of the CPU fit: a coarse hull, few Gaussians, a short schedule
TINY_FIT = {
    "hull_resolution": 64,
    "max_init_gaussians": 800,
    "iterations": 500,
    "views_per_step": 2,
    "motion_init_iterations": 400,
    "densify_from": 100,
    "densify_every": 50,
    "densify_until": 400,
    "densify_grad": 5e-5,
    "tile_size": 8,
    "device": "cpu",
    "seed": 0,
    "progress": False,
}


@pytest.fixture(scope="session")
def tiny_scene(tmp_path_factory):
    root = tmp_path_factory.mktemp("gauss-scene") / "scene"
    path = get_registry().create("scene_source", "synth", TINY_SCENE).generate(root)
    return read_scene(path)


@pytest.fixture(scope="session")
def tiny_fit(tiny_scene, tmp_path_factory):
    """(reconstructor, reconstruction, run folder) of one fit of the tiny scene."""
    run_dir = tmp_path_factory.mktemp("gauss-run")
    reconstructor = get_registry().create("reconstructor", "gauss-dynamic", TINY_FIT)
    reconstruction = reconstructor.fit(tiny_scene, run_dir=run_dir)
    return reconstructor, reconstruction, run_dir
