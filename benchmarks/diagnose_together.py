"""What the diagnosis's lockstep descents save: one finished run diagnosed twice on one machine,
its models' refits and fresh identifications descending in lockstep (``diagnose.together:
true``, the default: one batched rollout per step) and one after another (``false``).

Each side diagnoses its own copy of the run (the run itself is not touched), in its own process,
after an untimed warm-up that compiles the simulator's kernels (``mosiv bench sim --batch 2
--gradients`` on a small body); the apart side goes first. Reported per side: the diagnosis's
own time (diagnosis.json ``time_s``), the process's wall time and peak resident memory, the
verdict and the accepted term with its coefficients; and whether both sides reached the same
verdict (on warp-mpm's CPU path the descents are the same bit for bit; on a GPU the rollouts are
not bit-reproducible, so coefficients may differ in the last digits).

    python benchmarks/diagnose_together.py RUN --out OUT --budget full --device cuda

Writes OUT/diagnose_together.json and prints a table.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

import yaml

#: what a run folder holds from an earlier diagnosis: a copy starts without it
DIAGNOSIS_OUTPUTS = ("diagnosis.json", "diagnosis.md", "diagnose")
SIDES = (("apart", False), ("together", True))

#: runs in each side's process: the diagnosis, then its peak resident memory
RUNNER = """
import json, resource, sys
from mosiv_framework.diagnose import diagnose_run
overrides = {"device": sys.argv[3]} if sys.argv[3] else None
summary = diagnose_run(sys.argv[1], budget=sys.argv[2], simulator_overrides=overrides)
peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
print("MOSIV_PEAK_RSS", peak)
"""


def prepare_copy(run: Path, copy: Path, together: bool) -> None:
    """``run`` copied to ``copy`` without an earlier diagnosis, its recipe's
    ``diagnose.together`` set."""
    shutil.copytree(run, copy, ignore=shutil.ignore_patterns(*DIAGNOSIS_OUTPUTS))
    recipe_path = copy / "recipe.yaml"
    recipe = yaml.safe_load(recipe_path.read_text()) or {}
    recipe.setdefault("diagnose", {})
    recipe["diagnose"] = dict(recipe["diagnose"] or {}, together=together)
    recipe_path.write_text(yaml.safe_dump(recipe, sort_keys=False))


def warm_up(device: str) -> None:
    """Compile the forward, batched and backward kernels before either side is timed."""
    command = [sys.executable, "-m", "mosiv_framework.cli.main", "bench", "sim", "--device"]
    command += [device, "--particles", "512", "--grid", "16", "--substeps", "2", "--frames"]
    command += ["1", "--batch", "2", "--gradients", "--json"]
    subprocess.run(command, check=True, capture_output=True)


def diagnose_side(copy: Path, budget: str, device: str | None) -> dict:
    """Diagnose ``copy`` in a process of its own; its numbers."""
    t0 = time.perf_counter()
    done = subprocess.run(
        [sys.executable, "-c", RUNNER, str(copy), budget, device or ""],
        capture_output=True,
        text=True,
    )
    wall = time.perf_counter() - t0
    if done.returncode != 0:
        raise RuntimeError(f"the diagnosis of {copy} failed:\n{done.stderr[-2000:]}")
    peak = next(
        int(line.split()[1]) for line in done.stdout.splitlines() if line.startswith("MOSIV_PEAK")
    )
    report = json.loads((copy / "diagnosis.json").read_text())
    accepted = report.get("accepted") or {}
    return {
        "time_s": report["time_s"],
        "wall_s": wall,
        "peak_rss_bytes": peak,
        "verdict": report["verdict"],
        "accepted": accepted.get("name"),
        "coefficients": accepted.get("coefficients"),
    }


def markdown(rows: dict) -> str:
    lines = [
        "| side | diagnosis s | process wall s | peak RSS MiB | verdict | accepted | coefficients |",
        "|---|---:|---:|---:|---|---|---|",
    ]
    for side, r in rows.items():
        coefficients = r["coefficients"] or {}
        theta = ", ".join(f"{k} {v:.4g}" for k, v in coefficients.items()) or "-"
        lines.append(
            f"| {side} | {r['time_s']:.1f} | {r['wall_s']:.1f} | {r['peak_rss_bytes'] / 2**20:.0f}"
            f" | {r['verdict']} | {r['accepted'] or '-'} | {theta} |"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path, help="a folder written by `mosiv run`")
    parser.add_argument("--out", type=Path, required=True, help="a new or empty folder")
    parser.add_argument("--budget", choices=("small", "full"), default="small")
    parser.add_argument("--device", choices=("cpu", "cuda"), default=None)
    args = parser.parse_args(argv)
    if not (args.run / "recipe.yaml").is_file():
        parser.error(f"{args.run}: not a run folder (no recipe.yaml); give a `mosiv run` output")
    if args.out.exists() and any(args.out.iterdir()):
        parser.error(f"--out {args.out}: not empty; give a new or empty folder")
    args.out.mkdir(parents=True, exist_ok=True)
    recipe = yaml.safe_load((args.run / "recipe.yaml").read_text()) or {}
    warm_up(args.device or str((recipe.get("simulator") or {}).get("device", "cpu")))
    rows = {}
    for side, together in SIDES:
        prepare_copy(args.run, args.out / side, together)
        rows[side] = diagnose_side(args.out / side, args.budget, args.device)
        print(f"[diagnose-together] {side}: {rows[side]['time_s']:.1f} s", flush=True)
    result = {
        "run": args.run.name,
        "budget": args.budget,
        "device": args.device or "the run's",
        "sides": rows,
        "speedup": rows["apart"]["time_s"] / rows["together"]["time_s"],
        "same_verdict": rows["apart"]["verdict"] == rows["together"]["verdict"]
        and rows["apart"]["accepted"] == rows["together"]["accepted"],
    }
    (args.out / "diagnose_together.json").write_text(json.dumps(result, indent=2))
    print(markdown(rows))
    print(f"speedup {result['speedup']:.2f}x, same verdict: {result['same_verdict']}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
