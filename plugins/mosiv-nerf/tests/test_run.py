"""The CoupNeRF* recipe end to end on CPU (``mosiv run``) and the plugin's registration."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from mosiv_framework.errors import ConfigError
from mosiv_framework.registry import get_registry
from mosiv_framework.scene.example import write_example_scene

RECIPE = Path(__file__).parents[3] / "recipes" / "baselines" / "coupnerf.yaml"

#: the paper recipe shrunk to a 32-pixel, 4-camera, 6-frame scene on CPU; measured 40 s on the
#: shared 2-core development machine
TINY = [
    "reconstructor.resolution=16",
    "reconstructor.iterations=60",
    "reconstructor.rays_per_step=1024",
    "reconstructor.step_ratio=1.0",
    "reconstructor.hull_resolution=24",
    "reconstructor.hull_points=200",
    "reconstructor.device=cpu",
    "lifter.spacing=0",
    "lifter.max_particles_per_object=400",
    "simulator.device=cpu",
    "simulator.grid=24",
    "simulator.substeps=20",
    "losses.nerf-photometric.size=16",
    "losses.nerf-photometric.cameras_per_call=2",
    "identify.velocity_iterations=2",
    "identify.param_iterations=2",
    "identify.horizon_start=2",
    "identify.checkpoint_every=1",
    "evaluate.emd_samples=64",
    "evaluate.video_size=32",
]


def test_registered_with_options():
    registry = get_registry()
    assert "nerf-field" in registry.names("reconstructor")
    assert "nerf-particles" in registry.names("lifter")
    assert "nerf-grid" in registry.names("renderer")
    assert "nerf-photometric" in registry.names("loss")
    with pytest.raises(ConfigError, match="resolution"):
        registry.create("reconstructor", "nerf-field", {"resolution": 2})
    with pytest.raises(ConfigError, match="kernel"):
        registry.create("renderer", "nerf-grid", {"kernel": "cubic"})


def test_coupnerf_recipe_runs_end_to_end(tmp_path):
    scene = write_example_scene(tmp_path / "scene", n_frames=6, n_cameras=4, size=32)
    run = tmp_path / "run"
    cmd = [sys.executable, "-m", "mosiv_framework.cli.main", "run", str(RECIPE)]
    cmd += [f"scene.path={scene}", f"output.dir={run}", *TINY]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    metrics = json.loads((run / "metrics.json").read_text())
    observed = metrics["observed"]
    # the evaluation rendered the simulated particles with nerf-grid against the videos
    assert observed["psnr"] is not None and observed["psnr"] > 20.0
    assert observed["cd_mm2"] > 0
    identified = json.loads((run / "identified.json").read_text())
    assert set(identified["objects"]) == {"1", "2"}
