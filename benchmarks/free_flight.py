"""When free flight ends on scenes another engine made: the frames identification fits the
initial velocities on, against the collision frame the generator recorded.

Identification fits each object's initial velocity to its centroids over the frames before any
contact (``mosiv_framework.pipeline.params.free_flight_frames``), first by a ballistic fit, then
through the simulator. A frame ends free flight when points come closer than the contact gap
(two cells of the simulator grid by default) or, with ``identify.ballistic_tolerance``, when an
object near another or the ground has its centroid leave its gravity parabola. This measures,
for every scene of a suite folder (``mosiv data suite OUT --source genesis``), the frames each
rule counts, how many of them lie past the collision frame in ``gt/params.json``, and the error
of the ballistic initial velocity over those frames against the true one. No simulation: the
targets are the scene's ground-truth points over its observed frames.

    python benchmarks/free_flight.py --scenes runs/genesis --grid 96
    python benchmarks/free_flight.py --scenes runs/genesis --grid 96 --write-results docs/RESULTS.md

Prints the table; ``--json FILE`` saves the rows; ``--write-results`` replaces the section "Free
flight on Genesis scenes" of that markdown file (a part below the hand-written marker is kept).
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import shlex
import statistics
import sys
from pathlib import Path

import numpy as np
import torch
from genesis_identify_table import _fill, data_description, replace_section
from identify_suite import code_version

from mosiv_framework.pipeline.params import free_flight_frames, initial_velocity_from_points
from mosiv_framework.scene import read_scene

SECTION = "Free flight on Genesis scenes"


def scene_row(folder: Path, *, grid: int, substeps: int, tolerance: float) -> dict:
    """One scene: the collision frame, and per rule (the gap alone, the gap and the centroids)
    the frames counted and each object's ballistic initial-velocity error (%)."""
    scene = read_scene(folder)
    truth = json.loads((folder / "gt" / "params.json").read_text())
    observed = scene.observed_frames
    with np.load(folder / "gt" / "points.npz") as data:
        points = {
            int(key.split("_")[1]): torch.tensor(data[key][:observed], dtype=torch.float32)
            for key in data.files
        }
    velocities = {o["id"]: torch.tensor(o["initial_velocity"]) for o in truth["objects"]}
    world = scene.world
    gap = 2.0 * world.extent / grid
    rules = {}
    for name, rule_tolerance in (("gap", 0.0), ("centroids", tolerance)):
        frames = free_flight_frames(points, world, gap=gap, ballistic_tolerance=rule_tolerance)
        fitted = initial_velocity_from_points(
            points,
            fps=scene.fps,
            gravity=scene.gravity,
            frames=frames,
            time_step=1.0 / (scene.fps * substeps),
        )
        errors = {  # relative to the true speed (at least 1 cm/s: a body thrown at rest)
            str(k): 100.0
            * float((fitted[k] - velocities[k]).norm() / max(float(velocities[k].norm()), 0.01))
            for k in sorted(fitted)
        }
        rules[name] = {"frames": frames, "v0_error": errors}
    generator = truth.get("generator_params", {})
    return {
        "scene": folder.name,
        "collision_frame": generator.get("collision_frame"),
        "rules": rules,
        "data": {
            "generator": truth.get("generator", ""),
            "ranges": truth.get("ranges"),
            "seed": generator.get("seed"),
        },
    }


def markdown(rows: list[dict]) -> str:
    lines = [
        "| scene | collision frame | frames, gap alone | frames, gap and centroids "
        "| v0 error %, gap alone | v0 error %, gap and centroids |",
        "|---|---|---|---|---|---|",
    ]
    for row in rows:
        gap, cen = row["rules"]["gap"], row["rules"]["centroids"]
        lines.append(
            f"| {row['scene']} | {row['collision_frame']} | {gap['frames']} | {cen['frames']} "
            f"| {_errors(gap)} | {_errors(cen)} |"
        )
    return "\n".join(lines)


def _errors(rule: dict) -> str:
    return ", ".join(f"{e:.2g}" for e in rule["v0_error"].values())


def summary(rows: list[dict]) -> str:
    """Per rule: frames past the collision (range) and the median and worst v0 error."""
    parts = []
    for name, label in (("gap", "the gap alone"), ("centroids", "the gap and the centroids")):
        past = [
            r["rules"][name]["frames"] - r["collision_frame"]
            for r in rows
            if r["collision_frame"] is not None
        ]
        errors = [e for r in rows for e in r["rules"][name]["v0_error"].values()]
        frames = f"{min(past)}-{max(past)} frames past the recorded collision" if past else ""
        parts.append(
            f"with {label}: {frames or 'no collision recorded'}, median v0 error {statistics.median(errors):.2g} % "
            f"(worst {max(errors):.2g} %)"
        )
    return "; ".join(parts) + "."


def section_text(rows: list[dict], *, command: str, grid: int, tolerance: float) -> str:
    intro = (
        "`benchmarks/free_flight.py` counts the frames identification fits the initial "
        "velocities on (the frames before any contact) on scenes another engine made, with the "
        f"contact gap of grid {grid} (two cells) alone and with `identify.ballistic_tolerance="
        f"{tolerance:g}` as well, against the collision frame the generator recorded, and the "
        "error of the ballistic initial velocity over those frames (docs/PHYSICS.md, Free "
        "flight in the data). No simulation."
    )
    machine = f"{platform.machine()} CPU, {os.cpu_count()} cores"
    return "\n".join(
        [
            f"## {SECTION}",
            "",
            _fill(intro),
            "",
            f"- Command: `{command}`",
            f"- Machine: {machine}. Date {datetime.date.today().isoformat()}. "
            f"Code {code_version()}.",
            f"- Data: {data_description(rows)}.",
            "",
            markdown(rows),
            "",
            _fill(summary(rows)),
        ]
    )


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", type=Path, required=True, help="a mosiv data suite folder")
    parser.add_argument("--grid", type=int, default=96, help="the simulator grid of the gap")
    parser.add_argument("--substeps", type=int, default=600, help="the simulator's substeps")
    parser.add_argument("--tolerance", type=float, default=0.1, help="ballistic_tolerance")
    parser.add_argument("--json", type=Path, default=None, help="save the rows here")
    parser.add_argument("--write-results", type=Path, default=None)
    args = parser.parse_args(argv)
    folders = sorted(p.parent.parent for p in args.scenes.glob("*/gt/params.json"))
    if not folders:
        raise SystemExit(f"--scenes {args.scenes}: no scene folders with gt/params.json")
    rows = [
        scene_row(f, grid=args.grid, substeps=args.substeps, tolerance=args.tolerance)
        for f in folders
    ]
    print(markdown(rows))
    print(summary(rows))
    if args.json is not None:
        args.json.write_text(json.dumps(rows, indent=2) + "\n")
    if args.write_results is not None:
        shown = ["SCENES" if a == str(args.scenes) else a for a in argv]
        command = "python benchmarks/free_flight.py " + shlex.join(shown)
        text = args.write_results.read_text()
        body = section_text(rows, command=command, grid=args.grid, tolerance=args.tolerance)
        args.write_results.write_text(replace_section(text, body, title=SECTION))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
