"""Two values of one simulator option, timed against each other in one process.

Both sides run the ``mosiv bench sim`` workload (the bench cube, `mosiv_framework.bench`) on
the same machine, alternately, several times, each on its own simulator made once (so repeats
re-use compiled kernels and buffers, as identification does); the table gives each side's
median throughput and the ratio B / A per size. For example the fused forward kernels of
taichi-mpm against its split ones:

    python benchmarks/option_ab.py --backend taichi-mpm --option fused_forward \\
        --values false true --device cuda --particles 100000 1000000 --grid 128 \\
        --substeps 50 --frames 2 --repeats 3 --json OUT.json

or warp-mpm's grid window (``--option grid_window --values whole particles``).
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys

import yaml

from mosiv_framework.bench import measure
from mosiv_framework.registry import get_registry


def parse_args(argv=None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--backend", required=True, help="a registered simulator, e.g. taichi-mpm")
    ap.add_argument("--option", required=True, help="the simulator option to compare")
    ap.add_argument("--values", nargs=2, required=True, metavar=("A", "B"),
                    help="its two values (read as YAML: true, 12, whole)")  # fmt: skip
    ap.add_argument("--device", choices=("cpu", "cuda"), default="cpu")
    ap.add_argument("--particles", type=int, nargs="+", default=[8000])
    ap.add_argument("--grid", type=int, default=48)
    ap.add_argument("--substeps", type=int, default=60)
    ap.add_argument("--frames", type=int, default=4)
    ap.add_argument("--repeats", type=int, default=3, help="timings per side and size")
    ap.add_argument("--no-backward", action="store_true", help="forward only")
    ap.add_argument("--json", help="write every timing and the medians here")
    return ap.parse_args(argv)


def _median(rows, key):
    values = [r[key] for r in rows if r[key] is not None]
    return statistics.median(values) if values else None


def compare(args) -> list[dict]:
    """Per particle count: both sides' timings and medians, the sides run alternately."""
    values = [yaml.safe_load(v) for v in args.values]
    out = []
    for n in args.particles:
        config = {"device": args.device, "grid": args.grid, "substeps": args.substeps}
        sides = [
            get_registry().create("simulator", args.backend, {**config, args.option: v})
            for v in values
        ]
        timings: list[list[dict]] = [[], []]
        for repeat in range(args.repeats):
            for side, simulator in enumerate(sides):
                result = measure(
                    simulator,
                    backend=args.backend,
                    device=args.device,
                    particles=n,
                    grid=args.grid,
                    substeps=args.substeps,
                    frames=args.frames,
                    backward=not args.no_backward,
                ).as_dict()
                timings[side].append(result)
                print(
                    f"[option_ab] N={n} {args.option}={values[side]!r} repeat {repeat + 1}: "
                    f"fwd {result['forward_particle_substeps_per_s']:.3g}",
                    file=sys.stderr,
                )
        row = {"particles": timings[0][0]["particles"], "grid": args.grid}
        for key in ("forward_particle_substeps_per_s", "forward_backward_particle_substeps_per_s"):
            a, b = _median(timings[0], key), _median(timings[1], key)
            row[key] = {"A": a, "B": b, "B_over_A": None if not a or b is None else b / a}
        row["timings"] = {str(values[0]): timings[0], str(values[1]): timings[1]}
        out.append(row)
        del sides
    return out


def table(rows, args) -> str:
    a, b = args.values
    lines = [
        f"| particles | grid | fwd {a} | fwd {b} | fwd {b} / {a} "
        f"| fwd+bwd {a} | fwd+bwd {b} | fwd+bwd {b} / {a} |",
        "| ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]

    def fmt(x, spec=".3g"):
        return "n/a" if x is None else format(x, spec)

    for r in rows:
        f, fb = r["forward_particle_substeps_per_s"], r["forward_backward_particle_substeps_per_s"]
        lines.append(
            f"| {r['particles']:,} | {r['grid']} | {fmt(f['A'])} | {fmt(f['B'])} "
            f"| {fmt(f['B_over_A'], '.2f')} | {fmt(fb['A'])} | {fmt(fb['B'])} "
            f"| {fmt(fb['B_over_A'], '.2f')} |"
        )
    return "\n".join(lines)


def main(argv=None) -> int:
    args = parse_args(argv)
    rows = compare(args)
    print(f"{args.backend} on {args.device}, {args.option}: A = {args.values[0]}, "
          f"B = {args.values[1]}; medians of {args.repeats} (particle-substeps/s)")  # fmt: skip
    print(table(rows, args))
    if args.json:
        with open(args.json, "w") as fh:
            json.dump({"args": vars(args), "rows": rows}, fh, indent=2)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
