"""``mosiv bench sim``: simulator throughput and peak memory, one or several backends side by side,
and with ``--peer NAME`` another simulator on the same workload (mosiv_framework.bench_peer)."""

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
        help="measure rollout_batch of B members against B single rollouts (forward only, "
        "unless --gradients)",
    )
    sim.add_argument(
        "--gradients",
        action="store_true",
        help="with --batch: time forward plus backward on both sides",
    )
    sim.add_argument(
        "--peer",
        metavar="NAME",
        help="also time another simulator (a registered bench peer, e.g. genesis) on the same "
        "particles, law, grid, substeps and frames, forward only, after its untimed warm-up",
    )
    sim.add_argument(
        "--sim-option",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="a further simulator option for every rollout timed (repeatable), e.g. "
        "grid_window=particles for warp-mpm",
    )
    sim.add_argument("--json", action="store_true")
    sim.add_argument(
        "--jsonl",
        default=None,
        metavar="FILE",
        help="also append each result to FILE as one JSON line the moment it is measured, so a "
        "run cut short keeps the rows it finished (FILE must not exist yet)",
    )
    sim.set_defaults(handler=run_sim)


def sim_options(pairs: list[str]) -> dict:
    """``--sim-option KEY=VALUE`` pairs as a dict, each value read as YAML (numbers, true)."""
    import yaml

    from mosiv_framework.errors import ConfigError

    options = {}
    for pair in pairs:
        key, eq, value = pair.partition("=")
        if not eq or not key.strip():
            raise ConfigError(f"--sim-option {pair!r}: expected KEY=VALUE, e.g. grid_window=whole")
        options[key.strip()] = yaml.safe_load(value)
    return options


def result_log(path: str | None):
    """A function that appends one result to ``path`` as a JSON line and flushes it (a no-op
    without a path). An existing file is refused, so a user's file is never overwritten or
    mixed with another run's rows."""
    if path is None:
        return lambda row: None
    from pathlib import Path

    from mosiv_framework.errors import ConfigError

    target = Path(path)
    if target.exists():
        raise ConfigError(f"--jsonl {path}: the file exists already; give a new path")
    if not target.parent.is_dir():
        raise ConfigError(f"--jsonl {path}: folder {target.parent} does not exist")
    target.touch(exist_ok=False)

    def append(row: dict) -> None:
        with target.open("a") as f:
            f.write(json.dumps(row) + "\n")

    return append


def run_sim(args) -> int:
    from mosiv_framework.bench import run_bench

    if args.batch:
        if args.peer:
            from mosiv_framework.errors import ConfigError

            raise ConfigError("--peer times single rollouts; it does not combine with --batch")
        return run_batch(args)
    if args.gradients:
        from mosiv_framework.errors import ConfigError

        raise ConfigError(
            "--gradients goes with --batch B; without --batch the bench times forward plus "
            "backward already (unless --no-backward)"
        )
    if args.peer:  # an unknown or uninstalled peer fails before minutes of MOSIV timing
        from mosiv_framework.bench_peer import resolve_peer

        resolve_peer(args.peer)
    log = result_log(args.jsonl)
    results = []
    for n in args.particles:
        for grid in args.grid:
            ours = []
            for backend in args.backend.split(","):
                result = run_bench(
                    backend=backend.strip(),
                    device=args.device,
                    particles=n,
                    grid=grid,
                    substeps=args.substeps,
                    frames=args.frames,
                    backward=not args.no_backward,
                    options=sim_options(args.sim_option),
                )
                ours.append(result.as_dict())
                log(result.as_dict())
                if not args.json:
                    print(_line(result.as_dict()), flush=True)
            results += ours
            if args.peer:
                results.append(_run_peer(args, n, grid, ours))
                log(results[-1])
    if args.json:
        print(json.dumps(results, indent=2))
    return 0


def _run_peer(args, n: int, grid: int, ours: list[dict]) -> dict:
    """Time the peer on this size and compare it with each MOSIV backend just timed."""
    from mosiv_framework.bench_peer import compare_with_peer, run_peer_bench

    peer = run_peer_bench(
        peer=args.peer,
        device=args.device,
        particles=n,
        grid=grid,
        substeps=args.substeps,
        frames=args.frames,
    ).as_dict()
    peer["versus"] = {r["backend"]: compare_with_peer(r, peer) for r in ours}
    if not args.json:
        print(_peer_line(peer), flush=True)
        for backend, c in peer["versus"].items():
            print(
                f"  {backend} / {peer['peer']} forward: {c['forward_ratio']:.3g}x; "
                f"final centroids {c['centroid_distance_m'] * 1e3:.2g} mm apart",
                flush=True,
            )
    return peer


def _peer_line(r: dict) -> str:
    lines = [
        f"{r['peer'] + ' (peer)':<11} {r['device']:<4} N={r['particles']:>8} "
        f"grid={r['grid']:<4} substeps={r['substeps']:<4} fwd "
        f"{r['forward_particle_substeps_per_s']:.3g} p-substeps/s  fwd+bwd n/a "
        f"({r['gradients']})  memory {_mem(r['peak_memory_bytes'])}"
        + (f" ({r['memory_note']})" if r["memory_note"] else ""),
        f"  {r['peer']} warm-up excluded from the timing: {r['warmup_s']:.1f} s (scene build, "
        "kernel compilation, one frame)",
    ]
    return "\n".join(lines + [f"  {r['peer']}: {note}" for note in r["notes"]])


def run_batch(args) -> int:
    from mosiv_framework.bench import run_batch_bench
    from mosiv_framework.errors import ConfigError

    if min(args.batch) < 1:
        raise ConfigError(f"--batch {args.batch}: every B must be >= 1")
    log = result_log(args.jsonl)
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
                        options=sim_options(args.sim_option),
                        gradients=args.gradients,
                    ).as_dict()
                    results.append(r)
                    log(r)
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
        + ("  forward+backward" if r.get("gradients") else "")
        + "".join(f"  {k}={v}" for k, v in r.get("options", {}).items())
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
