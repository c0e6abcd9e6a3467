"""Several simulator processes on one GPU: throughput alone, side by side, and under NVIDIA MPS.

Usage (GPU machine, after ``source benchmarks/gpu_setup.sh``)::

    python3 benchmarks/gpu_concurrency.py --processes 1 4 8 [--json OUT.json]

Each trial starts K copies of ``mosiv -q bench sim --backend warp-mpm --device cuda`` at once
(default: 2,000 particles, grid 96, 600 substeps: a Genesis scene's identification at its
finest grid, where a process's kernels leave most of the GPU idle) and reads each copy's
forward and forward + backward rates (particle-substeps/s, timed by the bench after its
warm-up). The aggregate is their sum: every copy starts at the same
moment and spends the same seconds in imports and warm-up, so their timed parts overlap. Each
K runs twice, first as plain processes (the GPU switches between them), then under the MPS
daemon that ``device_queue.py --mps`` starts (their kernels run side by side). The gain is
the aggregate over one process's rate alone.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import device_queue  # noqa: E402

RATE = re.compile(r"fwd (\S+) p-substeps/s\s+fwd\+bwd (\S+) p-substeps/s")


def bench_command(args: argparse.Namespace) -> list[str]:
    """One copy's command line."""
    return [
        "mosiv", "-q", "bench", "sim", "--backend", "warp-mpm", "--device", "cuda",
        "--particles", str(args.particles), "--grid", str(args.grid),
        "--substeps", str(args.substeps), "--frames", str(args.frames),
    ]  # fmt: skip


def trial(command: list[str], copies: int, env: dict[str, str] | None) -> dict:
    """Run ``copies`` of ``command`` at once; their rates and the trial's wall time.

    Raises:
        RuntimeError: a copy failed or printed no rates (its output is in the message).
    """
    start = time.time()
    procs = [
        subprocess.Popen(
            command, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True
        )
        for _ in range(copies)
    ]
    rates = []
    for proc in procs:
        out, _ = proc.communicate()
        found = RATE.search(out)
        if proc.returncode != 0 or not found:
            raise RuntimeError(f"{' '.join(command)} (exit {proc.returncode}):\n{out[-2000:]}")
        rates.append((float(found.group(1)), float(found.group(2))))
    return {
        "copies": copies,
        "wall_s": round(time.time() - start, 2),
        "forward": [r[0] for r in rates],
        "forward_backward": [r[1] for r in rates],
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--processes", type=int, nargs="+", default=[1, 4, 8])
    parser.add_argument("--particles", type=int, default=2000)
    parser.add_argument("--grid", type=int, default=96)
    parser.add_argument("--substeps", type=int, default=600)
    parser.add_argument("--frames", type=int, default=6)
    parser.add_argument("--json", type=Path, default=None, help="also write the trials here")
    args = parser.parse_args(argv)
    if args.processes[0] != 1:
        parser.error("--processes must start with 1: the gains are over one process alone")
    command = bench_command(args)
    subprocess.run(command, check=True, capture_output=True)  # compiles the kernels once
    rows = []
    for mode in ("plain", "mps"):
        with tempfile.TemporaryDirectory() as folder:
            env = None
            if mode == "mps":
                env = {**os.environ, **device_queue.start_mps(Path(folder))}
            try:
                rows += [{"mode": mode, **trial(command, k, env)} for k in args.processes]
            finally:
                if mode == "mps":
                    device_queue.stop_mps(Path(folder))
    alone = {name: rows[0][name][0] for name in ("forward", "forward_backward")}
    print("| mode | processes | forward, sum | gain | forward + backward, sum | gain | wall s |")
    print("| --- | ---: | ---: | ---: | ---: | ---: | ---: |")
    for row in rows:
        cells = []
        for name in ("forward", "forward_backward"):
            total = sum(row[name])
            row[f"{name}_sum"], row[f"{name}_gain"] = total, total / alone[name]
            cells += [f"{total:.3g}", f"{total / alone[name]:.2f}"]
        print(f"| {row['mode']} | {row['copies']} | {' | '.join(cells)} | {row['wall_s']} |")
    if args.json:
        args.json.write_text(json.dumps({"command": command, "trials": rows}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
