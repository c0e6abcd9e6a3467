"""``mosiv bench sim``: simulator throughput and peak memory, one or several backends side by side."""

from __future__ import annotations

import json


def add_parser(sub) -> None:
    p = sub.add_parser("bench", help="measure speed and memory")
    bsub = p.add_subparsers(dest="bench_command", metavar="WHAT", required=True)
    sim = bsub.add_parser("sim", help="simulator particle-substeps per second and peak memory")
    sim.add_argument(
        "--backend", default="warp-mpm", help="registered simulator, or several separated by commas"
    )
    sim.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    sim.add_argument("--particles", type=int, nargs="+", default=[10_000])
    sim.add_argument("--grid", type=int, nargs="+", default=[64])
    sim.add_argument("--substeps", type=int, default=50)
    sim.add_argument("--frames", type=int, default=2)
    sim.add_argument("--no-backward", action="store_true", help="forward only")
    sim.add_argument(
        "--batch",
        type=int,
        nargs="+",
        metavar="B",
        help="measure rollout_batch of B members against B single rollouts (forward only)",
    )
    sim.add_argument("--json", action="store_true")
    sim.set_defaults(handler=run_sim)


def run_sim(args) -> int:
    from mosiv_framework.bench import run_bench

    if args.batch:
        return run_batch(args)
    results = []
    for n in args.particles:
        for grid in args.grid:
            for backend in args.backend.split(","):
                result = run_bench(
                    backend=backend.strip(),
                    device=args.device,
                    particles=n,
                    grid=grid,
                    substeps=args.substeps,
                    frames=args.frames,
                    backward=not args.no_backward,
                )
                results.append(result.as_dict())
                if not args.json:
                    print(_line(result.as_dict()), flush=True)
    if args.json:
        print(json.dumps(results, indent=2))
    return 0


def run_batch(args) -> int:
    from mosiv_framework.bench import run_batch_bench
    from mosiv_framework.errors import ConfigError

    if min(args.batch) < 1:
        raise ConfigError(f"--batch {args.batch}: every B must be >= 1")
    results = []
    for n in args.particles:
        for grid in args.grid:
            for backend in args.backend.split(","):
                for batch in args.batch:
                    r = run_batch_bench(
                        backend=backend.strip(),
                        device=args.device,
                        particles=n,
                        grid=grid,
                        substeps=args.substeps,
                        batch=batch,
                        frames=args.frames,
                    ).as_dict()
                    results.append(r)
                    if not args.json:
                        print(_batch_line(r), flush=True)
    if args.json:
        print(json.dumps(results, indent=2))
    return 0


def _mem(b) -> str:
    return "n/a" if b is None else f"{b / 2**20:.0f} MiB"


def _batch_line(r: dict) -> str:
    return (
        f"{r['backend']:<11} {r['device']:<4} B={r['batch']:<3} N={r['particles']:>8} "
        f"grid={r['grid']:<4} substeps={r['substeps']:<4} batched "
        f"{r['batched_particle_substeps_per_s']:.3g} p-substeps/s  sequential "
        f"{r['sequential_particle_substeps_per_s']:.3g} p-substeps/s  gain {r['gain']:.2f}x  "
        f"peak {_mem(r['peak_memory_batched_bytes'])} / {_mem(r['peak_memory_sequential_bytes'])}"
        f"  max RSS {_mem(r['max_rss_after_batched_bytes'])}"
    )


def _line(r: dict) -> str:
    def mem(b):
        return "n/a" if b is None else f"{b / 2**20:.0f} MiB"

    fb = r["forward_backward_particle_substeps_per_s"]
    fb_text = "n/a" if fb is None else f"{fb:.3g}"
    return (
        f"{r['backend']:<11} {r['device']:<4} N={r['particles']:>8} grid={r['grid']:<4} "
        f"substeps={r['substeps']:<4} fwd {r['forward_particle_substeps_per_s']:.3g} p-substeps/s  "
        f"fwd+bwd {fb_text} p-substeps/s  peak {mem(r['peak_memory_bytes'])} / "
        f"{mem(r['peak_memory_forward_backward_bytes'])}"
    )
