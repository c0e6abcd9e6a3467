"""Per-kernel GPU time of one warp-mpm frame on the `mosiv bench sim` workload.

Usage (GPU machine): python benchmarks/warp_profile.py [--particles 1000000] [--grid 128]
Prints the summed CUDA time of each kernel over one frame (no graph capture, so Warp can time
every launch), to show where the forward substep loop spends its time.
"""

from __future__ import annotations

import argparse
import time

import torch
import warp as wp
from mosiv_warp_mpm.simulator import MPMRun, pack_theta
from mosiv_warp_mpm.state import GridLayout

from mosiv_framework.bench import bench_params, bench_particles, bench_world


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--particles", type=int, default=1_000_000)
    ap.add_argument("--grid", type=int, default=128)
    ap.add_argument("--substeps", type=int, default=50)
    ap.add_argument(
        "--order",
        choices=["scatter", "cell", "lattice", "random"],
        default="scatter",
        help="particle order: GridLayout.scatter_order (what rollouts use), sorted by grid cell, "
        "as generated, or shuffled",
    )
    args = ap.parse_args()
    wp.init()
    device = "cuda:0"
    dev = wp.device_to_torch(device)
    world = bench_world()
    particles = bench_particles(args.particles, grid=args.grid)
    params = bench_params(dev, requires_grad=False)
    layout = GridLayout.for_world(world, grid=args.grid, fields=1)
    x0 = particles.positions.to(dev)
    if args.order == "scatter":
        order = layout.scatter_order(x0)
    elif args.order == "cell":
        order = torch.argsort(layout.cell_keys(x0))
    elif args.order == "random":
        order = torch.randperm(x0.shape[0], device=dev)
    else:
        order = torch.arange(x0.shape[0], device=dev)
    n = x0.shape[0]
    run = MPMRun(
        layout=layout,
        world=world,
        substeps=args.substeps,
        device=device,
        object_ids=[1],
        families=["elastic"],
        obj_index=torch.zeros(n, dtype=torch.int64, device=dev),
        volumes=particles.volumes.to(dev)[order],
    )
    theta = pack_theta(params, [1], world.gravity, dev)
    v0 = params.initial_velocity[1].expand(n, 3).contiguous()
    run.tables.load(theta)
    run.a.set_initial(x0[order].contiguous(), v0)
    run._frame_launches()  # compile and warm up
    wp.synchronize()
    wp.timing_begin(cuda_filter=wp.TIMING_KERNEL)
    t0 = time.perf_counter()
    run._frame_launches()
    wp.synchronize()
    wall = time.perf_counter() - t0
    results = wp.timing_end()
    per_kernel: dict[str, float] = {}
    for r in results:
        per_kernel[r.name] = per_kernel.get(r.name, 0.0) + r.elapsed
    total = sum(per_kernel.values())
    print(
        f"N={n} grid={args.grid} substeps={args.substeps} order={args.order}: frame wall {wall * 1e3:.1f} ms"
    )
    for name, ms in sorted(per_kernel.items(), key=lambda kv: -kv[1]):
        print(f"  {name:<50} {ms:8.2f} ms  {100 * ms / total:5.1f}%")
    print(f"  throughput without graph: {n * args.substeps / wall:.3g} particle-substeps/s")


if __name__ == "__main__":
    main()
