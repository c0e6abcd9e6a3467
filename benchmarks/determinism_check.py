"""Does warp-mpm repeat itself bit for bit, and what does its deterministic mode cost?

For each setting of the simulator's ``deterministic`` option (each in its own process: Warp
compiles a module one way per process), the same work runs twice:
- the backend-parity collision scene (elastic against plasticine, multi-field contact), rolled
  out ``--frames`` frames, and the gradients of a rollout loss with respect to every parameter
  (mosiv_framework.testing.parity.rollout_gradients);
- a short identification loop: Adam on both objects' parameters against the Chamfer of a
  target rollout, so the torch side (the Chamfer's gathers and their scattered gradients)
  is in the loop as in Stage III.
It prints, per setting, the largest difference between the two runs (0 means bit-identical) and
the time per forward rollout and per forward+backward, and writes them to ``--out`` as JSON.

Usage (GPU machine): python benchmarks/determinism_check.py --out determinism.json
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time

import torch

SCENE = "collision"


def _rollout(sim, frames: int):
    from mosiv_framework.testing.parity import WORLD, standard_scenes
    from mosiv_framework.testing.shapes import default_params

    particles, velocities = standard_scenes()[SCENE]
    params = default_params(particles, velocities=velocities)
    with torch.no_grad():
        return sim.rollout(particles, params, world=WORLD, frames=frames).positions


def _identify(sim, iterations: int, frames: int) -> dict[str, torch.Tensor]:
    """Adam on every parameter of a perturbed start against a target rollout's Chamfer."""
    from mosiv_framework.losses import chamfer_m2
    from mosiv_framework.testing.parity import WORLD, standard_scenes
    from mosiv_framework.testing.shapes import default_params

    particles, velocities = standard_scenes()[SCENE]
    target = _rollout(sim, frames)
    ids = particles.object_ids.to(target.device)
    overrides = {k: {"E": 2.0e5} for k in particles.object_list}  # start away from the truth
    params = default_params(
        particles, velocities=velocities, overrides=overrides, requires_grad=True
    )
    tensors = [t for _, t in params.named_tensors()]
    opt = torch.optim.Adam(tensors, lr=1e-3)
    for _ in range(iterations):
        opt.zero_grad()
        traj = sim.rollout(particles, params, world=WORLD, frames=frames)
        loss = sum(
            chamfer_m2(traj.positions[f][ids == k], target[f][ids == k], search="brute")
            for f in range(1, frames + 1)
            for k in particles.object_list
        )
        loss.backward()
        opt.step()
    return {name: t.detach().cpu().clone() for name, t in params.named_tensors()}


def _largest_difference(a: dict[str, torch.Tensor], b: dict[str, torch.Tensor]) -> float:
    return max(float((a[k] - b[k]).abs().max()) for k in a)


def measure(
    deterministic: bool, *, frames: int, iterations: int, grid: int, substeps: int, device: str
):
    from mosiv_warp_mpm.simulator import WarpMPMSimulator

    from mosiv_framework.testing.parity import rollout_gradients

    sim = WarpMPMSimulator(grid=grid, substeps=substeps, device=device, deterministic=deterministic)

    def sync():
        if device.startswith("cuda"):
            torch.cuda.synchronize()

    _rollout(sim, 1)  # compile and capture
    sync()
    t0 = time.perf_counter()
    positions = [_rollout(sim, frames) for _ in range(2)]
    sync()
    forward_s = (time.perf_counter() - t0) / 2
    t0 = time.perf_counter()
    grads = [rollout_gradients(sim, SCENE, frames=frames) for _ in range(2)]
    sync()
    gradient_s = (time.perf_counter() - t0) / 2
    fitted = [_identify(sim, iterations, min(frames, 4)) for _ in range(2)]
    return {
        "deterministic": deterministic,
        "particles": int(positions[0].shape[1]),
        "frames": frames,
        "grid": grid,
        "substeps": substeps,
        "positions_max_diff_m": float((positions[0] - positions[1]).abs().max()),
        "gradients_max_diff": _largest_difference(*grads),
        "identified_max_diff": _largest_difference(*fitted),
        "identify_iterations": iterations,
        "forward_s": forward_s,
        "forward_backward_s": gradient_s,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", default="determinism.json")
    ap.add_argument("--frames", type=int, default=10)
    ap.add_argument("--iterations", type=int, default=10, help="Adam steps of the identify loop")
    ap.add_argument("--grid", type=int, default=64)
    ap.add_argument("--substeps", type=int, default=100)
    ap.add_argument("--device", default="cuda", help="cuda (the question) or cpu (a smoke run)")
    ap.add_argument("--one", choices=["on", "off"], help=argparse.SUPPRESS)  # child process
    args = ap.parse_args()
    options = dict(
        frames=args.frames,
        iterations=args.iterations,
        grid=args.grid,
        substeps=args.substeps,
        device=args.device,
    )
    if args.one:
        torch.use_deterministic_algorithms(args.one == "on", warn_only=True)
        print(json.dumps(measure(args.one == "on", **options)))
        return
    rows = []
    for setting in ("off", "on"):
        cmd = [sys.executable, __file__, "--one", setting]
        cmd += [f"--{k}={v}" for k, v in options.items()]
        done = subprocess.run(cmd, capture_output=True, text=True, check=False)
        if done.returncode != 0:
            sys.exit(f"deterministic={setting} failed:\n{done.stderr[-4000:]}")
        rows.append(json.loads(done.stdout.strip().splitlines()[-1]))
    for r in rows:
        print(
            f"deterministic={r['deterministic']}: positions differ by {r['positions_max_diff_m']:.3g} m,"
            f" gradients by {r['gradients_max_diff']:.3g}, identified parameters by "
            f"{r['identified_max_diff']:.3g} after {r['identify_iterations']} steps;"
            f" forward {r['forward_s']:.3f} s, forward+backward {r['forward_backward_s']:.3f} s"
            f" ({r['particles']} particles, {r['frames']} frames, grid {r['grid']},"
            f" {r['substeps']} substeps)"
        )
    slow = rows[1]["forward_backward_s"] / rows[0]["forward_backward_s"]
    print(f"deterministic mode costs {slow:.2f}x on forward+backward")
    with open(args.out, "w") as f:
        json.dump({"rows": rows, "slowdown_forward_backward": slow}, f, indent=1)


if __name__ == "__main__":
    main()
