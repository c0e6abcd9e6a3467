"""Silhouettes of simulated particles: the splat's coverage against an analytic disk, its
gradient against central differences, and the silhouette loss running inside the pipeline."""

from __future__ import annotations

import math

import pytest
import torch
from omegaconf import OmegaConf

from mosiv_framework.pipeline.silhouettes import splat_alpha
from mosiv_framework.scene.cameras import Camera


def camera(size=64, f=80.0, distance=1.0):
    # looking down +z from z = -distance at the origin; OpenCV frame equals world frame shifted
    w2c = torch.eye(4, dtype=torch.float64)
    w2c[2, 3] = distance
    return Camera("c0", size, size, f, f, size / 2, size / 2, w2c)


def ball(radius=0.1, spacing=0.01):
    g = torch.arange(-radius, radius + 1e-9, spacing)
    pts = torch.stack(torch.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    return pts[pts.norm(dim=1) <= radius]


def test_batched_splat_equals_one_image_at_a_time(monkeypatch):
    # the silhouette loss draws every frame of an object in one call; batches of one image
    # (a tiny element budget) and one batch of all must both equal separate calls
    import mosiv_framework.pipeline.silhouettes as silhouettes

    cam = camera(32)
    frames = torch.stack([ball(0.05) + torch.tensor([0.02 * i, -0.01 * i, 0.0]) for i in range(3)])
    separate = torch.stack([splat_alpha(f, 0.006, cam, 32, supersample=3) for f in frames])
    together = splat_alpha(frames, 0.006, cam, 32, supersample=3)
    monkeypatch.setattr(silhouettes, "SPLAT_BATCH_ELEMENTS", 1)
    chunked = splat_alpha(frames, 0.006, cam, 32, supersample=3)
    assert separate.shape == (3, 32, 32) and separate.sum() > 10.0
    assert torch.allclose(together, separate, atol=1e-6)
    assert torch.allclose(chunked, separate, atol=1e-6)


def test_splat_of_a_ball_covers_its_projected_disk():
    cam, r = camera(), 0.1
    pts = ball(r)
    alpha = splat_alpha(pts, 0.5 * 0.01 * 1.24, cam, 64)
    # a ball of radius r at distance d projects to a disk of radius f r / sqrt(d^2 - r^2) pixels
    disk = math.pi * (80.0 * r / math.sqrt(1.0 - r**2)) ** 2
    # the square footprints (half-width 0.62 spacings) reach a little beyond the outermost
    # lattice cells in this axis-aligned view: a third of a pixel along the outline at most
    perimeter = 2 * math.pi * math.sqrt(disk / math.pi)
    assert disk < float(alpha.sum()) < disk + 0.35 * perimeter
    assert float(alpha[32, 32]) > 0.99 and float(alpha[0, 0]) < 1e-3


def test_splat_keeps_the_area_of_an_object_a_few_pixels_wide():
    # particles 0.4 px apart, the ball 8 px across: a nonlinearity applied at pixel scale, or
    # footprint tails summed over a deep column, grow the outline by about a pixel (area x1.6);
    # supersampled sharp footprints keep the area of the disk
    cam, r = camera(size=32, f=40.0), 0.1
    alpha = splat_alpha(ball(r), 0.5 * 0.01 * 1.24, cam, 32)
    disk = math.pi * (40.0 * r / math.sqrt(1.0 - r**2)) ** 2
    assert 0.95 < float(alpha.sum()) / disk < 1.12


def test_splat_gradient_matches_central_differences():
    cam = camera(size=16, f=20.0)
    pts = (ball(0.08, 0.04) + torch.tensor([0.013, -0.007, 0.0])).double()
    weights = torch.rand(16, 16, dtype=torch.float64, generator=torch.Generator().manual_seed(1))

    def f(p):
        return (splat_alpha(p, 0.03, cam, 16) * weights).sum()

    x = pts.clone().requires_grad_(True)
    f(x).backward()
    eps = 1e-6
    for i, j in [(0, 0), (3, 1), (len(pts) - 1, 2)]:
        plus, minus = pts.clone(), pts.clone()
        plus[i, j] += eps
        minus[i, j] -= eps
        numeric = (f(plus) - f(minus)) / (2 * eps)
        assert float(x.grad[i, j]) == pytest.approx(float(numeric), rel=1e-4, abs=1e-8)


def test_silhouette_loss_runs_in_the_pipeline(tmp_path, monkeypatch):
    from mosiv_framework.interfaces import Simulator
    from mosiv_framework.pipeline import run_pipeline
    from mosiv_framework.pipeline.formats import read_history
    from mosiv_framework.recipes import validate_recipe
    from mosiv_framework.registry import Component, Registry, hookimpl, manager
    from mosiv_framework.types import Trajectory

    class Ballistic(Simulator):
        def __init__(self, **options):
            pass

        def rollout(self, particles, params, *, world, frames):
            t = torch.arange(frames + 1, dtype=torch.float32) / world.fps
            g = torch.tensor(world.gravity, dtype=torch.float32)
            ids = particles.object_ids.tolist()
            v0 = torch.stack([params.initial_velocity[int(k)] for k in ids])
            x = particles.positions[None] + t[:, None, None] * v0[None]
            return Trajectory(x + 0.5 * t[:, None, None] ** 2 * g, particles.object_ids, world.fps)

    class Plugin:
        @hookimpl
        def mosiv_simulators(self, register):
            register(Component("simulator", "ballistic", factory=Ballistic))

    reg = Registry().load_entry_points(disabled=["warp-mpm", "taichi-mpm", "gauss"])
    reg.add_plugin(Plugin(), name="ballistic-test")
    monkeypatch.setattr(manager, "_REGISTRY", reg)
    raw = {
        "scene": {
            "path": str(tmp_path / "scene"),
            "generate": "if-missing",
            "source": {"name": "example", "n_frames": 5, "n_cameras": 2, "size": 32},
        },
        "reconstructor": {"name": "oracle", "max_points": 300},
        "lifter": {"name": "gt-points", "max_particles_per_object": 300},
        "simulator": {"name": "ballistic"},
        "losses": {"chamfer": {"weight": 1.0, "max_points": 300}, "silhouette": {"weight": 1e-3}},
        "identify": {"velocity_iterations": 4, "param_iterations": 0, "velocity_lr": 0.01},
        "evaluate": {"emd_samples": 64, "render_videos": False},
        "output": {"dir": str(tmp_path / "run")},
    }
    resolved, problems = validate_recipe(raw, reg)
    assert problems == []
    metrics = run_pipeline(OmegaConf.create(resolved), run_dir=tmp_path / "run")
    history = read_history(tmp_path / "run" / "identify/history.json")
    assert all(set(h["terms"]) == {"chamfer", "silhouette"} for h in history)
    # the recorded masks and the splatted particles agree for the true motion
    assert all(h["terms"]["silhouette"] < 0.05 for h in history)
    assert metrics["future"]["cd_mm2"] < 5.0
