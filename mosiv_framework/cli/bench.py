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
    sim.add_argument("--json", action="store_true")
    sim.set_defaults(handler=run_sim)


def run_sim(args) -> int:
    from mosiv_framework.bench import run_bench

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
