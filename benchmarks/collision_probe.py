"""Roll the parity suite's two-body collision scene on one device with each backend and report
the per-object centroids after 10 frames (a quick cross-device sanity probe)."""

import sys

import torch

from mosiv_framework.registry import get_registry
from mosiv_framework.testing.parity import SCENE_OPTIONS, WORLD, standard_scenes
from mosiv_framework.testing.shapes import default_params

device = sys.argv[1] if len(sys.argv) > 1 else "cpu"
particles, velocities = standard_scenes()["collision"]
params = default_params(particles, velocities=velocities)
for backend in ("warp-mpm", "taichi-mpm"):
    sim = get_registry().create("simulator", backend, {**SCENE_OPTIONS, "device": device})
    try:
        with torch.no_grad():
            traj = sim.rollout(particles, params, world=WORLD, frames=10)
        print(backend, device, {k: v[-1].tolist() for k, v in traj.centroids().items()})
    except Exception as exc:  # report and continue with the other backend
        print(backend, device, "FAILED:", str(exc)[:300])
