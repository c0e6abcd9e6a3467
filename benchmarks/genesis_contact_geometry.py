"""Contact geometry on Genesis scenes: when the bodies meet, how close they come, how far apart
they end, in Genesis's recording and in warp-mpm's rollout of the same truth.

The model error (``benchmarks/genesis_model_error.py``) says how far warp-mpm, given Genesis's
true parameters, particles and initial velocities, ends from Genesis's points; this says where
contact makes the difference. For every scene of a suite folder and every configuration (a
contact between objects, a grid, a substep count; each material's own law), the rollout of the
truth and gt/points.npz are both measured the same way:

    onset     the first frame whose centroid leaves the gravity parabola through the frames
              before it (``ballistic_departure`` with the tolerance of
              ``identify.ballistic_tolerance``'s default, 0.1 of the points' spacing), the
              earliest over the objects: the first contact, with another body or the ground
              (none: "-"; identification also asks for a neighbour nearby, this does not)
    closest   the smallest distance (mm) between the points of any two objects over the
              frames from Genesis's onset to three frames after it (the whole clip where
              Genesis shows none): how close a contact lets the surfaces come (MPM acts
              across grid cells, so a coarser grid parts them wider)
    last      that distance at the last frame: whether the bodies parted after the collision
              or stayed together (Genesis's single grid holds touching bodies together); with
              three objects, the nearest two at that frame

    python benchmarks/genesis_contact_geometry.py --scenes runs/genesis_dev --out runs/geometry \\
        --contacts multi_field single_field --grids 48 96 --substeps 400 600 --pairs

``--pairs`` takes grids and substeps pairwise (48 with 400, 96 with 600) instead of every
combination. Writes ``OUT/contact_geometry.json`` (one row per scene and configuration, with
Genesis's numbers beside the rollout's; a rerun skips rows it has) and
``OUT/contact_geometry.md``; ``--write-results FILE`` replaces the section "Contact geometry on
Genesis scenes" there.
"""

from __future__ import annotations

import argparse
import datetime
import json
import shlex
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch
from genesis_identify import _device_name, _fill, find_scenes, replace_section
from genesis_model_error import _num, frame0_particles, rollout_truth
from identify_suite import code_version
from scipy.spatial import cKDTree

from mosiv_framework.errors import SimulationDiverged
from mosiv_framework.pipeline.params import ballistic_departure, point_spacing
from mosiv_framework.recipes import load_recipe
from mosiv_framework.scene import read_scene

SECTION = "Contact geometry on Genesis scenes"
#: the section goes after "Model error on Genesis scenes", before this one
SECTION_BEFORE = "Stiffness profile on Genesis scenes"
FORMAT = "mosiv-contact-geometry/1"
#: the departure tolerance, in point spacings (identify.ballistic_tolerance's default)
TOLERANCE_SPACINGS = 0.1
#: frames after Genesis's onset over which the closest approach is taken
WINDOW = 3


def pair_distances(points: dict[int, torch.Tensor]) -> np.ndarray:
    """Per frame, the smallest distance (m) between points of two different objects:
    ``points`` maps object id -> [F, N_k, 3]; [F], +inf for fewer than two objects."""
    ids = sorted(points)
    frames = next(iter(points.values())).shape[0]
    out = np.full(frames, np.inf)
    for i, a in enumerate(ids):
        for b in ids[i + 1 :]:
            for f in range(frames):
                tree = cKDTree(points[b][f].detach().cpu().double().numpy())
                d, _ = tree.query(points[a][f].detach().cpu().double().numpy(), k=1)
                out[f] = min(out[f], float(d.min()))
    return out


def onset(points: dict[int, torch.Tensor], world) -> int | None:
    """The earliest frame at which an object's centroid leaves its free-flight parabola; None
    where none does."""
    frames = next(iter(points.values())).shape[0]
    first = min(
        ballistic_departure(p, world, TOLERANCE_SPACINGS * point_spacing(p[0]))
        for p in points.values()
    )
    return first if first < frames else None


def _mm(metres: float) -> float | None:
    """Millimetres, None for no distance (fewer than two objects: +inf)."""
    return 1000.0 * metres if np.isfinite(metres) else None


def geometry(points: dict[int, torch.Tensor], world, window: tuple[int, int]) -> dict:
    """Onset frame, closest approach over frames ``window`` (inclusive) and last-frame
    distance (mm) of one recording or rollout."""
    distances = pair_distances(points)
    lo, hi = window
    return {
        "onset": onset(points, world),
        "closest_mm": _mm(float(distances[lo : hi + 1].min())),
        "last_mm": _mm(float(distances[-1])),
    }


def by_object(positions: torch.Tensor, object_ids: torch.Tensor) -> dict[int, torch.Tensor]:
    return {int(k): positions[:, object_ids == k] for k in torch.unique(object_ids)}


def measure(recipe, scene, particles, config: dict, truth: dict) -> dict:
    """One configuration's rollout of the truth, measured over the window of Genesis's own."""
    row = {"scene": scene.root.name, "config": config_key(config), **config, "genesis": truth}
    row.update(device=_device_name(recipe), code=code_version())
    started = time.perf_counter()
    try:
        traj = rollout_truth(recipe, scene, particles, config)  # each material's own law
    except SimulationDiverged as exc:
        return {**row, "diverged": str(exc), "time_s": time.perf_counter() - started}
    window = truth["window"]
    rollout = geometry(by_object(traj.positions, traj.object_ids), scene.world, window)
    return {**row, "rollout": rollout, "time_s": time.perf_counter() - started}


def genesis_geometry(scene) -> dict:
    """Genesis's own numbers, with the frames its closest approach is taken over."""
    points = scene.gt_points()
    first, last = onset(points, scene.world), scene.n_frames - 1
    window = (0, last) if first is None else (first, min(first + WINDOW, last))
    return {**geometry(points, scene.world, window), "window": list(window)}


def config_key(config: dict) -> str:
    return f"{config['contact']}/g{config['grid']}/s{config['substeps']}"


def configurations(args) -> list[dict]:
    """Every (contact, grid, substeps) the command names; with ``--pairs`` the grids and
    substeps go together pairwise."""
    if args.pairs:
        if len(args.grids) != len(args.substeps):
            raise SystemExit(
                f"--pairs: {len(args.grids)} grids and {len(args.substeps)} substep counts; "
                "give as many of each"
            )
        steps = list(zip(args.grids, args.substeps))
    else:
        steps = [(g, s) for g in args.grids for s in args.substeps]
    return [{"contact": c, "grid": g, "substeps": s} for c in args.contacts for g, s in steps]


def _cell(values: dict) -> str:
    onset = "-" if values["onset"] is None else values["onset"]
    return f"{onset} / {_num(values['closest_mm'])} / {_num(values['last_mm'])}"


def _shift(row: dict) -> int | None:
    first, truth = row["rollout"]["onset"], row["genesis"]["onset"]
    return None if first is None or truth is None else first - truth


def _ratio(row: dict, name: str) -> float | None:
    value, truth = row["rollout"][name], row["genesis"][name]
    return None if value is None or not truth else value / truth


def summary(rows: list[dict]) -> list[dict]:
    """Per configuration over the scenes that did not diverge: the median onset shift
    (frames, rollout minus Genesis) and the medians of the closest and last distances as
    multiples of Genesis's (a row without an onset, or with a Genesis distance of 0, is left
    out of that median)."""
    out = []
    for key in dict.fromkeys(r["config"] for r in rows):
        ok = [r for r in rows if r["config"] == key and "rollout" in r]
        mine = [r for r in rows if r["config"] == key]
        out.append({
            "config": key, "scenes": len(mine), "diverged": len(mine) - len(ok),
            "onset_shift": _median(ok, _shift),
            "closest_ratio": _median(ok, lambda r: _ratio(r, "closest_mm")),
            "last_ratio": _median(ok, lambda r: _ratio(r, "last_mm")),
        })  # fmt: skip
    return out


def _median(rows: list[dict], value) -> float | None:
    """The median of ``value`` over ``rows``, leaving out rows where it is None."""
    values = [v for v in map(value, rows) if v is not None]
    return statistics.median(values) if values else None


def markdown(rows: list[dict]) -> str:
    """The per-scene table (Genesis, then each configuration) and the medians."""
    keys = list(dict.fromkeys(r["config"] for r in rows))
    scenes = sorted(dict.fromkeys(r["scene"] for r in rows))
    cell = {(r["scene"], r["config"]): r for r in rows}
    lines = [
        "| scene | Genesis | " + " | ".join(keys) + " |",
        "|---|---|" + "---|" * len(keys),
    ]
    for scene in scenes:
        mine = [r for r in rows if r["scene"] == scene]
        cells = [_cell(mine[0]["genesis"])]
        for key in keys:
            r = cell.get((scene, key))
            cells.append(
                "" if r is None else "diverged" if "diverged" in r else _cell(r["rollout"])
            )
        lines.append(f"| {scene} | " + " | ".join(cells) + " |")
    lines += [
        "",
        "Cells: onset frame / closest distance between two bodies over Genesis's onset and the "
        f"{WINDOW} frames after it (mm) / distance at the last frame (mm).",
        "",
        "| configuration | scenes | diverged | median onset shift (frames) | "
        "median closest / Genesis's | median last / Genesis's |",
        "|---|---|---|---|---|---|",
    ]
    for s in summary(rows):
        lines.append(
            f"| {s['config']} | {s['scenes']} | {s['diverged']} | {_num(s['onset_shift'])} | "
            f"{_num(s['closest_ratio'])} | {_num(s['last_ratio'])} |"
        )
    return "\n".join(lines) + "\n"


def section_text(rows: list[dict], *, command: str, data: str) -> str:
    """The RESULTS section: what is measured, how, where, and the tables."""
    machines = sorted({str(r.get("device", "not recorded")) for r in rows})
    codes = sorted({str(r.get("code", "not recorded")) for r in rows})
    intro = (
        "Genesis's true parameters, its frame-0 particles and initial velocities rolled out by "
        "warp-mpm with each material's own law (as in Model error on Genesis scenes), and the "
        "rollout and Genesis's recording measured alike: the frame the collision bends a "
        "centroid off its free-flight parabola (onset), how close two bodies come over that "
        f"frame and the {WINDOW} after it, and how far apart they are at the last frame."
    )
    return "\n".join([
        f"## {SECTION}", "", _fill(intro), "",
        f"- Command: `{command}`",
        f"- Machine: {', '.join(machines)}. Date {datetime.date.today().isoformat()}. "
        f"Code {', '.join(codes)}.",
        f"- Data: {data}.", "", markdown(rows),
    ])  # fmt: skip


def parse_args(argv: list[str] | None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", type=Path, required=True, help="suite folder")
    ap.add_argument("--out", type=Path, required=True, help="folder for contact_geometry.*")
    ap.add_argument("--recipe", type=Path, default=Path("recipes/genesis_oracle.yaml"))
    ap.add_argument("--only", help="comma-separated scene names")
    ap.add_argument("--contacts", nargs="+", default=["multi_field", "single_field"])
    ap.add_argument("--grids", nargs="+", type=int, default=[96])
    ap.add_argument("--substeps", nargs="+", type=int, default=[600])
    ap.add_argument("--pairs", action="store_true", help="grids and substeps pairwise")
    ap.add_argument("--device", default=None, help="simulator device (default: the recipe's)")
    ap.add_argument("--data", default=None, help="which scenes, as the section's Data line says")
    ap.add_argument("--write-results", type=Path, default=None, help="markdown file to update")
    return ap.parse_args(argv)


def measure_all(args) -> list[dict]:
    """Measure every scene and configuration not yet in OUT/contact_geometry.json; its rows."""
    args.out.mkdir(parents=True, exist_ok=True)
    path = args.out / "contact_geometry.json"
    data = json.loads(path.read_text()) if path.exists() else {"format": FORMAT, "rows": []}
    if data.get("format") != FORMAT:
        raise SystemExit(f"{path}: not a contact-geometry table (format {data.get('format')!r})")
    done = {(r["scene"], r["config"]) for r in data["rows"]}
    overrides = [f"simulator.device={args.device}"] if args.device else []
    configs = configurations(args)
    for name in find_scenes(args.scenes, args.only):
        folder = args.scenes / name
        recipe = load_recipe(args.recipe, [f"scene.path={folder}", *overrides])
        scene = read_scene(folder)
        if len(scene.object_ids) < 2:
            print(f"[geometry] {name}: one object, no contact between bodies; skipped")
            continue
        todo = [c for c in configs if (name, config_key(c)) not in done]
        if not todo:
            continue
        truth, particles = genesis_geometry(scene), frame0_particles(recipe, scene)
        for config in todo:
            row = measure(recipe, scene, particles, config, truth)
            print(json.dumps(row), flush=True)
            data["rows"].append(row)
            path.write_text(json.dumps(data, indent=1))
    return data["rows"]


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    args = parse_args(argv)
    rows = measure_all(args)
    (args.out / "contact_geometry.md").write_text(markdown(rows))
    print(markdown(rows))
    if args.write_results is not None:
        command = "python benchmarks/genesis_contact_geometry.py " + shlex.join(argv)
        data = args.data or f"the scenes of {args.scenes.name}"
        body = section_text(rows, command=command, data=data)
        text = args.write_results.read_text()
        args.write_results.write_text(
            replace_section(text, body, title=SECTION, before=SECTION_BEFORE)
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
