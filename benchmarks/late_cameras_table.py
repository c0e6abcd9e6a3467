"""Which ``--late-cameras`` policy predicts best: the tiny round trips of several seeds side by side.

Each policy's round trip (``capture_roundtrip.py --part capture`` and ``--part imported`` with
``--late-cameras POLICY``) lives in ``ROOT/POLICY/seed_S``, the direct runs of the same scenes
(``--part direct`` and ``--part reseeded --spread-seed 1``) in ``ROOT/direct/seed_S``::

    python benchmarks/late_cameras_table.py ROOT --seeds 7 8 9 --dev 7 8 --out table.json

Prints a markdown table of future Chamfer (mm^2) and mask IoU per seed and policy, the mean over
the development seeds (the policy with the lowest is the one to choose) and writes the numbers
to ``--out``.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

POLICIES = ("trim", "drop", "keep")


def read_part(folder: Path, name: str) -> dict:
    path = folder / "parts" / f"{name}.json"
    if not path.is_file():
        raise SystemExit(f"{path}: missing; run that part of capture_roundtrip.py first")
    return json.loads(path.read_text())


def collect(root: Path, seeds: list[int]) -> dict:
    """seed -> {direct, reseeded: future CD; POLICY: {future_cd_mm2, mask_iou_mean}}."""
    out = {}
    for seed in seeds:
        direct = root / "direct" / f"seed_{seed}"
        row = {
            "direct": read_part(direct, "direct")["future_cd_mm2"],
            "reseeded": read_part(direct, "reseeded")["direct"]["future_cd_mm2"],
        }
        for policy in POLICIES:
            folder = root / policy / f"seed_{seed}"
            capture = read_part(folder, "capture")
            row[policy] = {
                "future_cd_mm2": read_part(folder, "imported")["future_cd_mm2"],
                "mask_iou_mean": {k: v["iou_mean"] for k, v in sorted(capture["mask_iou"].items())},
            }
        out[str(seed)] = row
    return out


def dev_means(rows: dict, dev: list[int]) -> dict[str, float]:
    """Policy -> mean future Chamfer (mm^2) over the development seeds."""
    return {p: sum(rows[str(s)][p]["future_cd_mm2"] for s in dev) / len(dev) for p in POLICIES}


def table(rows: dict, dev: list[int]) -> str:
    lines = [
        "| seed | direct | direct, reseeded | trim | drop | keep |",
        "|---|---|---|---|---|---|",
    ]
    for seed, row in rows.items():
        label = f"{seed} ({'development' if int(seed) in dev else 'test'})"
        cells = [f"{row['direct']:,.0f}", f"{row['reseeded']:,.0f}"]
        cells += [f"{row[p]['future_cd_mm2']:,.0f}" for p in POLICIES]
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    means = dev_means(rows, dev)
    lines.append(
        "| mean of the development seeds | | | "
        + " | ".join(f"{means[p]:,.0f}" for p in POLICIES)
        + " |"
    )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("root", type=Path)
    parser.add_argument("--seeds", type=int, nargs="+", required=True)
    parser.add_argument("--dev", type=int, nargs="+", required=True, help="development seeds")
    parser.add_argument("--out", type=Path, help="write the numbers here (JSON)")
    parser.add_argument("--code", default="", help="the code version the runs ran at")
    parser.add_argument("--machine", default="", help="where the runs ran")
    args = parser.parse_args(argv)
    rows = collect(args.root, args.seeds)
    means = dev_means(rows, args.dev)
    print(table(rows, args.dev))
    print(f"lowest development mean: {min(means, key=means.get)}")
    if args.out:
        record = {"seeds": rows, "dev": args.dev, "dev_mean_future_cd_mm2": means}
        record.update(code=args.code, machine=args.machine)
        args.out.write_text(json.dumps(record, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
