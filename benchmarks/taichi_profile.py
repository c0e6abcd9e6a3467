"""Per-kernel device time of taichi-mpm's forward rollouts on the `mosiv bench sim` workload.

Usage (GPU machine, or --device cpu):
    python benchmarks/taichi_profile.py --device cuda --particles 1000000 --grid 128 \\
        --substeps 50 --frames 2 [--repeats 3] [--json OUT.json]

Runs the bench's elastic cube forward only (under torch.no_grad, as `mosiv bench sim` times
the forward) with Taichi's kernel profiler on: one untimed rollout of the timed length, then
``--repeats`` timed rollouts, each by the wall clock after a synchronisation, and the device time
of every kernel of the last one (Taichi names a kernel's top-level loops ``NAME_kernel_K``, one
device launch each). Wall time minus kernel time is what the host adds: Python calling Taichi,
frame-boundary transfers, and any compilation a rollout still triggers. The profiler times each
launch, so a profiled rollout runs somewhat slower than the same rollout in `mosiv bench sim`.
"""

from __future__ import annotations

import argparse
import json
import time

import taichi as ti
import torch
from mosiv_taichi_mpm import runtime

from mosiv_framework.bench import bench_params, bench_particles, bench_world
from mosiv_framework.registry import get_registry


def parse_args(argv=None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--device", choices=("cpu", "cuda"), default="cpu")
    ap.add_argument("--particles", type=int, default=8000)
    ap.add_argument("--grid", type=int, default=48)
    ap.add_argument("--substeps", type=int, default=50)
    ap.add_argument("--frames", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=3, help="timed rollouts after the warm-up")
    ap.add_argument("--rows", type=int, default=12, help="kernels listed")
    ap.add_argument("--json", default=None, help="write the timings here")
    args = ap.parse_args(argv)
    for name in ("particles", "grid", "substeps", "frames", "repeats"):
        if getattr(args, name) < 1:
            ap.error(f"--{name} must be at least 1, got {getattr(args, name)}")
    return args


def kernel_times() -> dict[str, tuple[int, float]]:
    """{kernel: (launches, total ms)} recorded since the profiler was last cleared, largest
    first (Taichi's profiler keeps them in its statistics, which ``get_total_time`` fills)."""
    profiler = ti.profiler.kernel_profiler.get_default_kernel_profiler()
    profiler.get_total_time()
    stats = profiler._statistical_results  # no public accessor in Taichi 1.7
    return {name: (r.counter, r.total_time) for name, r in stats.items()}


def main(argv=None) -> dict:
    args = parse_args(argv)
    runtime.profile_kernels()
    device = torch.device(args.device)
    config = {"device": args.device, "grid": args.grid, "substeps": args.substeps}
    simulator = get_registry().create("simulator", "taichi-mpm", config)
    world = bench_world()
    parts = bench_particles(args.particles, grid=args.grid).to(device)
    params = bench_params(device, requires_grad=False)
    walls = []
    with torch.no_grad():
        simulator.rollout(parts, params, world=world, frames=args.frames)  # untimed warm-up
        for _ in range(args.repeats):
            ti.sync()
            ti.profiler.clear_kernel_profiler_info()
            t0 = time.perf_counter()
            simulator.rollout(parts, params, world=world, frames=args.frames)
            ti.sync()
            walls.append(time.perf_counter() - t0)
    kernels = kernel_times()
    kernel_s = sum(ms for _, ms in kernels.values()) / 1e3
    work = len(parts) * args.substeps * args.frames
    out = {
        "device": args.device,
        "particles": len(parts),
        "grid": args.grid,
        "substeps": args.substeps,
        "frames": args.frames,
        "wall_s": walls,
        "rate_last": work / walls[-1],
        "kernel_s_last": kernel_s,
        "kernels_ms": kernels,
    }
    print(
        f"taichi-mpm {args.device}: {len(parts)} particles, grid {args.grid}, {args.substeps} "
        f"substeps, {args.frames} frames: walls {', '.join(f'{w * 1e3:.1f}' for w in walls)} ms; "
        f"last {out['rate_last']:.3g} particle-substeps/s, its kernels {kernel_s * 1e3:.1f} ms"
    )
    for name, (count, ms) in list(kernels.items())[: args.rows]:
        print(f"  {ms:9.2f} ms {count:6d}x  {name}")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(out, f, indent=1)
    return out


if __name__ == "__main__":
    main()
