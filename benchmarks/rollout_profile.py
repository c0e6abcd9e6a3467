"""Where a whole differentiable rollout's time goes, the frames' kernels and everything around.

`mosiv bench sim` times a rollout of the bench cube and its backward as a whole; on an H200
at 1M particles warp-mpm's ran at 1.82e8 particle-substeps/s while the frame alone, its
captured forward and adjoint graphs replayed, ran at 3.13e8 (benchmarks/warp_profile.py): this
script found the 0.2 s outside the frames in torch's backward of the initial velocities'
per-particle rows (docs/BENCHMARKS.md, "GPU: warp-mpm and taichi-mpm side by side"). It
runs the rollout as `mosiv bench sim` does (the same simulator, workload and warm-up), times
its two calls (the rollout, then the loss's backward) by the wall clock, and profiles them with
torch.profiler: host-side operations and, on CUDA, every kernel on the device (Warp's too,
which CUPTI sees), so the device's busy time and the host's largest items can be set beside
the wall time.

Usage (GPU machine):
    python benchmarks/rollout_profile.py --device cuda --particles 1000000 --grid 128 \\
        --substeps 50 --frames 2 [--settle] [--trace OUT.json] [--json OUT.json]

The warm-up is the bench's: a forward rollout and a differentiable one, each of the timed
length. ``--settle`` runs one more untimed rollout of the timed kind first: a difference
between the two says how much of the timing is still first-use work (buffers, graph
captures). ``--forward-only`` profiles the bench's forward timing instead: a rollout under
``torch.no_grad`` (for taichi-mpm, to see whether kernels or the host set its rate).
"""

from __future__ import annotations

import argparse
import json
import time

import torch
from torch.profiler import ProfilerActivity, profile

from mosiv_framework.bench import bench_params, bench_particles, bench_world
from mosiv_framework.registry import get_registry


def parse_args(argv=None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--backend", default="warp-mpm", help="a registered simulator")
    ap.add_argument("--device", choices=("cpu", "cuda"), default="cpu")
    ap.add_argument("--particles", type=int, default=8000)
    ap.add_argument("--grid", type=int, default=48)
    ap.add_argument("--substeps", type=int, default=50)
    ap.add_argument("--frames", type=int, default=2)
    ap.add_argument("--settle", action="store_true", help="an untimed rollout of --frames first")
    ap.add_argument(
        "--forward-only", action="store_true", help="profile a rollout under torch.no_grad"
    )
    ap.add_argument("--rows", type=int, default=15, help="rows of each profiler table")
    ap.add_argument("--trace", default=None, help="write the profiler's Chrome trace here")
    ap.add_argument("--json", default=None, help="write the timings here")
    args = ap.parse_args(argv)
    for name in ("particles", "grid", "substeps", "frames"):
        if getattr(args, name) < 1:
            ap.error(f"--{name} must be at least 1, got {getattr(args, name)}")
    return args


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize()


def _differentiable(simulator, parts, world, device, frames: int):
    """One differentiable rollout and its loss's backward (the bench's: the sum of the last
    frame's positions), each timed by the wall clock after a synchronisation."""
    params = bench_params(device, requires_grad=True)
    _sync(device)
    t0 = time.perf_counter()
    traj = simulator.rollout(parts, params, world=world, frames=frames)
    _sync(device)
    t1 = time.perf_counter()
    traj.positions[-1].sum().backward()
    _sync(device)
    t2 = time.perf_counter()
    return t1 - t0, t2 - t1


def _forward(simulator, parts, world, device, frames: int):
    """One rollout under torch.no_grad (the bench's forward timing), timed by the wall clock
    after a synchronisation; (rollout s, 0.0) so it reads like ``_differentiable``."""
    params = bench_params(device, requires_grad=False)
    _sync(device)
    t0 = time.perf_counter()
    with torch.no_grad():
        simulator.rollout(parts, params, world=world, frames=frames)
    _sync(device)
    return time.perf_counter() - t0, 0.0


def device_busy_ms(prof) -> float | None:
    """Summed time of the device kernels, memsets and copies the profiler saw (None on CPU)."""
    events = [e for e in prof.events() if e.device_type == torch.autograd.DeviceType.CUDA]
    if not events:
        return None
    return sum(e.device_time_total for e in events) / 1e3


def main(argv=None) -> dict:
    args = parse_args(argv)
    device = torch.device(args.device)
    config = {"device": args.device, "grid": args.grid, "substeps": args.substeps}
    simulator = get_registry().create("simulator", args.backend, config)
    world = bench_world()
    parts = bench_particles(args.particles, grid=args.grid).to(device)
    # the bench's warm-up: a forward rollout, then a differentiable one, of the timed length
    _forward(simulator, parts, world, device, args.frames)
    timed = _forward if args.forward_only else _differentiable
    if not args.forward_only:
        _differentiable(simulator, parts, world, device, args.frames)
    if args.settle:
        timed(simulator, parts, world, device, args.frames)
    activities = [ProfilerActivity.CPU]
    if device.type == "cuda":
        activities.append(ProfilerActivity.CUDA)
    with profile(activities=activities) as prof:
        rollout_s, backward_s = timed(simulator, parts, world, device, args.frames)
    work = len(parts) * args.substeps * args.frames
    out = {
        "backend": args.backend,
        "device": args.device,
        "particles": len(parts),
        "grid": args.grid,
        "substeps": args.substeps,
        "frames": args.frames,
        "settled": args.settle,
        "forward_only": args.forward_only,
        "rollout_s": rollout_s,
        "backward_s": backward_s,
        "rate": work / (rollout_s + backward_s),
        "device_busy_ms": device_busy_ms(prof),
    }
    print(
        f"{args.backend} {args.device}: {len(parts)} particles, grid {args.grid}, "
        f"{args.substeps} substeps, {args.frames} frames{', settled' if args.settle else ''}: "
        f"rollout {rollout_s * 1e3:.1f} ms + backward {backward_s * 1e3:.1f} ms = "
        f"{out['rate']:.3g} particle-substeps/s"
    )
    if out["device_busy_ms"] is not None:
        print(f"device busy (kernels, memsets, copies): {out['device_busy_ms']:.1f} ms")
    table = prof.key_averages()
    print(table.table(sort_by="self_cpu_time_total", row_limit=args.rows))
    if device.type == "cuda":
        print(table.table(sort_by="self_device_time_total", row_limit=args.rows))
    if args.trace:
        prof.export_chrome_trace(args.trace)
    if args.json:
        with open(args.json, "w") as f:
            json.dump(out, f, indent=2)
    return out


if __name__ == "__main__":
    main()
