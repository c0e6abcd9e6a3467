"""Where one identification iteration spends its time: simulator forward, losses, loss
backward and simulator backward, timed apart (CUDA synchronised around each part).

Usage: python benchmarks/identify_profile.py RUN_DIR [--horizon 14] [--iterations 5]
RUN_DIR is a `mosiv run` folder that has finished lifting (recipe.yaml, particles.pt,
reconstruction.pt and its scene). The parameters are the lifted defaults (no optimisation);
the first iteration (Warp compile, graph capture) is reported apart from the mean of the rest.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import torch
from omegaconf import OmegaConf

from mosiv_framework.pipeline import build_objective
from mosiv_framework.pipeline.identify import geometry
from mosiv_framework.pipeline.params import (
    GROUND_FRICTION,
    ParameterVector,
    free_flight_frames,
    initial_velocity_from_points,
)
from mosiv_framework.pipeline.rundir import RunDir
from mosiv_framework.pipeline.silhouettes import SILHOUETTE_LOSSES, SilhouetteObjective
from mosiv_framework.registry import get_registry
from mosiv_framework.scene import read_scene


def _sync() -> float:
    if torch.cuda.is_available():
        torch.cuda.synchronize()
    return time.perf_counter()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run_dir", type=Path)
    ap.add_argument("--horizon", type=int, default=14, help="frames rolled out per iteration")
    ap.add_argument("--iterations", type=int, default=5)
    args = ap.parse_args()

    rd = RunDir(args.run_dir)
    recipe = OmegaConf.load(args.run_dir / "recipe.yaml")
    plain = OmegaConf.to_container(recipe, resolve=True)
    scene = read_scene(Path(plain["scene"]["path"]))
    particles = rd.load_torch("particles.pt")
    targets = rd.load_torch("reconstruction.pt").points
    registry = get_registry()
    sim_options = dict(plain["simulator"])
    simulator = registry.create("simulator", sim_options.pop("name"), sim_options)
    objective = build_objective(plain["losses"], registry)
    if any(name in SILHOUETTE_LOSSES for name in objective.terms):
        size = min(recipe.identify.silhouette_size, max(c.width for c in scene.cameras))
        objective = SilhouetteObjective(objective, scene=scene, particles=particles, size=size)
    particles = particles.to(simulator.torch_device)  # as identification does
    world = scene.world
    free = free_flight_frames(targets, world, gap=0.02)
    v0 = initial_velocity_from_points(targets, fps=scene.fps, gravity=scene.gravity, frames=free)
    vector = ParameterVector.create(
        particles.materials, v0, ground_friction=GROUND_FRICTION.default
    )
    h = min(args.horizon, scene.observed_frames - 1)
    frames = list(range(1, h + 1))

    rows = []
    for it in range(args.iterations):
        t0 = _sync()
        traj = simulator.rollout(particles, vector.physical(), world=world, frames=h)
        t1 = _sync()
        device = traj.positions.device
        target = geometry({k: t.to(device) for k, t in targets.items()}, frames)
        loss, _ = objective.evaluate(geometry(traj, frames), target)
        t2 = _sync()
        (grad_positions,) = torch.autograd.grad(loss, traj.positions, retain_graph=True)
        t3 = _sync()
        traj.positions.backward(grad_positions)
        t4 = _sync()
        rows.append(
            {
                "simulator_forward": t1 - t0,
                "losses_forward": t2 - t1,
                "losses_backward": t3 - t2,
                "simulator_backward": t4 - t3,
                "total": t4 - t0,
            }
        )
        print(f"iteration {it}: " + ", ".join(f"{k} {v:.3f} s" for k, v in rows[-1].items()))
    rest = rows[1:] or rows
    mean = {k: sum(r[k] for r in rest) / len(rest) for k in rows[0]}
    summary = {
        "run_dir": str(args.run_dir),
        "horizon": h,
        "particles": len(particles),
        "substeps_per_frame": sim_options.get("substeps"),
        "device": torch.cuda.get_device_name() if torch.cuda.is_available() else "cpu",
        "first_iteration_s": rows[0],
        "mean_after_first_s": mean,
    }
    print(json.dumps(summary, indent=2))


if __name__ == "__main__":
    main()
