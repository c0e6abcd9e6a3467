"""Where the future error of an identification on Genesis scenes comes from.

A model identified on the observed frames can fit them closely and still predict the future
badly. This takes the rows that ``benchmarks/genesis_identify.py`` wrote (each keeps every
identified value under ``identified``) and rolls each out again, with the row's contact between
objects, as identified and with one group of values replaced by the scene's truth at a time:

    identified   every value as identified
    ground       the ground's Coulomb coefficient true (Genesis's 0.1, or gt/params.json's)
    velocity     every object's initial velocity true
    material     every object's law parameters that gt/params.json gives true, the densities
                 too (the truth in its own density gauge: motion cannot tell a common scale of
                 densities and stresses); the rest (the friction between objects) as identified
    truth        all of it true, with the law defaults where the truth gives no value: the
                 model's own error at this contact, grid and substeps
                 (``benchmarks/genesis_model_error.py``)

Each rollout is scored over the observed and the future frames against gt/points.npz
(Chamfer, mm^2), and each object's centroid is compared with Genesis's at the last frame (mm).
The group whose truth lowers the future Chamfer most is where the identified model's future
error comes from; where even ``truth`` predicts badly, the model, not the parameters, is wrong.

    python benchmarks/genesis_future_attribution.py --rows benchmarks/data/genesis_identify \\
        --scenes runs/genesis --out runs/attribution [--set simulator.grid=64 ...]

``--set`` takes the recipe overrides the rows were identified with (the grid and substeps: the
rows do not record them). Writes ``OUT/attribution.json`` (one row per scene and variant; a
rerun skips what it has) and ``OUT/attribution.md``; ``--report`` measures nothing and gathers
every attribution.json under OUT; ``--write-results FILE`` replaces the section "Future error
on Genesis scenes" there.
"""

from __future__ import annotations

import argparse
import datetime
import json
import statistics
import sys
import time
from dataclasses import replace
from pathlib import Path

import torch
from genesis_identify import _device_name, replace_section, shown_command
from genesis_model_error import (
    _num,
    frame0_particles,
    gather_rows,
    true_params,
)
from identify_suite import code_version

from mosiv_framework.errors import SimulationDiverged
from mosiv_framework.laws import get_law
from mosiv_framework.pipeline.evaluate import score
from mosiv_framework.pipeline.params import ParameterVector
from mosiv_framework.pipeline.run import build_simulator
from mosiv_framework.recipes import load_recipe
from mosiv_framework.recipes.cell_size import resolve_cell_size
from mosiv_framework.scene import read_scene
from mosiv_framework.types import ObjectParams, SimulationParams

FORMAT = "mosiv-genesis-future-attribution/1"
SECTION = "Future error on Genesis scenes"
#: the section goes after "Contact geometry on Genesis scenes", before this one
SECTION_BEFORE = "Stiffness profile on Genesis scenes"
VARIANTS = ("identified", "ground", "velocity", "material", "truth")


def read_rows(folder: Path, only: set[str] | None = None) -> list[dict]:
    """The genesis_identify rows in ``folder`` (``*.json`` but table.json) of the scenes
    ``only`` names (all by default), each with its identified values; a row without them is an
    error naming the file."""
    rows = []
    for path in sorted(folder.glob("*.json")):
        if path.name == "table.json":
            continue
        row = json.loads(path.read_text())
        if "scene" not in row or (only is not None and row["scene"] not in only):
            continue
        if not row.get("identified"):
            raise SystemExit(
                f"{path}: the row keeps no identified values (rows written by "
                "benchmarks/genesis_identify.py since they record 'identified' do)"
            )
        rows.append(row)
    if not rows:
        raise SystemExit(f"--rows {folder}: no genesis_identify rows (*.json with 'scene')")
    return rows


def true_law_values(scene, materials: dict[int, str]) -> dict[int, dict[str, float]]:
    """Per object, the parameters of its law that gt/params.json gives (no defaults)."""
    values = {}
    for record in scene.gt_params()["objects"]:
        k = int(record["id"])
        names = {spec.name for spec in get_law(materials[k]).all_params}
        values[k] = {n: float(v) for n, v in record["params"].items() if n in names}
    return values


#: units of the parameters that the density gauge scales (densities and stresses scale alike)
GAUGE_UNITS = ("kg/m^3", "Pa", "Pa*s")


def in_truth_gauge(identified: SimulationParams, truth: SimulationParams) -> SimulationParams:
    """``identified`` rescaled into the truth's density gauge: identification holds the first
    object's density at its start value (motion cannot tell a common scale of densities and
    stresses), so every density and stress is multiplied by the truth's / the identified first
    density. The motion is the same; a mix of identified and true values is then consistent."""
    first = min(identified.objects)
    factor = truth.objects[first].values["rho"] / identified.objects[first].values["rho"]
    objects = {}
    for k, p in identified.objects.items():
        units = {spec.name: spec.unit for spec in get_law(p.family).all_params}
        objects[k] = ObjectParams(
            p.family,
            {n: v * factor if units.get(n) in GAUGE_UNITS else v for n, v in p.values.items()},
        )
    return replace(identified, objects=objects)


def variant_params(identified: SimulationParams, truth: SimulationParams, true_values, name):
    """``identified`` with the group ``name`` (one of VARIANTS) replaced by the truth's: the
    physics terms, if any, stay as identified except in ``truth``, which is the truth alone.
    ``material`` puts the identified values into the truth's density gauge first
    (:func:`in_truth_gauge`), so that a stress the truth does not give stays consistent with
    the true densities."""
    if name not in VARIANTS:
        raise ValueError(f"unknown variant {name!r}; valid: {', '.join(VARIANTS)}")
    terms = identified.terms
    if name == "identified":
        return identified
    if name == "truth":
        return truth
    if name == "ground":
        return SimulationParams(
            identified.objects, identified.initial_velocity, truth.ground_friction, terms
        )
    if name == "velocity":
        return SimulationParams(
            identified.objects, truth.initial_velocity, identified.ground_friction, terms
        )
    gauged = in_truth_gauge(identified, truth)
    objects = {
        k: ObjectParams(
            p.family,
            {**p.values, **{n: torch.tensor(v) for n, v in true_values[k].items()}},
        )
        for k, p in gauged.objects.items()
    }
    return SimulationParams(objects, identified.initial_velocity, identified.ground_friction, terms)


def last_frame_offsets(traj, reference: dict[int, torch.Tensor]) -> dict[str, float]:
    """Per object, the distance (mm) between the rollout's centroid and the recording's at the
    last frame both have."""
    n = min(traj.n_frames, min(r.shape[0] for r in reference.values()))
    out = {}
    for k, points in reference.items():
        predicted = traj.object_positions(k)[n - 1].detach().cpu().mean(0)
        out[str(k)] = float((predicted - points[n - 1].mean(0)).norm()) * 1000.0
    return out


def measure_scene(recipe, scene, row: dict, *, emd_samples: int, label: str, skip=()) -> list[dict]:
    """Every variant of one row not in ``skip``, rolled out and scored; a divergence is a row
    that says so. ``label`` names the run the row comes from (its folder)."""
    resolve_cell_size(recipe, scene.world.extent)  # a recipe giving its cell in metres
    section = recipe.simulator.copy()
    section.contact = row["contact"]["mode"]
    simulator, _ = build_simulator(section)
    identified = ParameterVector.from_json(row["identified"])
    particles = frame0_particles(recipe, scene)
    materials = {k: p.family for k, p in identified.objects.items()}
    particles = replace(particles, materials=materials)
    truth = true_params(scene, materials)
    true_values = true_law_values(scene, materials)
    reference = scene.gt_points()
    base = {
        "rows": label,
        "scene": row["scene"],
        "contact": section.contact,
        "grid": int(section.grid),
        "substeps": int(section.substeps),
        "device": _device_name(recipe),
        "code": code_version(),
    }
    out = []
    for name in VARIANTS:
        if name in skip:
            continue
        started = time.perf_counter()
        params = variant_params(identified, truth, true_values, name)
        try:
            with torch.no_grad():
                traj = simulator.rollout(
                    particles, params, world=scene.world, frames=scene.n_frames - 1
                )
        except SimulationDiverged as exc:
            out.append({**base, "variant": name, "diverged": str(exc)})
            continue
        blocks = score(
            traj, reference, observed_frames=scene.observed_frames, n_samples=emd_samples, seed=0
        )
        out.append({
            **base,
            "variant": name,
            "observed_cd": blocks["observed"]["cd_mm2"],
            "future_cd": blocks["future"]["cd_mm2"],
            "last_offset_mm": last_frame_offsets(traj, reference),
            "time_s": time.perf_counter() - started,
        })  # fmt: skip
        if name == "identified":
            _check_reproduced(row, out[-1])
    return out


#: how far the identified rollout's future Chamfer may be from the row's own before the
#: settings are suspect (GPU runs are not bit-reproducible; rows here agree within 0.05 %)
REPRODUCE_TOLERANCE = 0.02


def _check_reproduced(row: dict, measured: dict) -> None:
    """Warn when the identified values, rolled out again, do not give the row's own future
    Chamfer: the rows do not record the grid and substeps, so a wrong ``--set`` shows here."""
    recorded = row.get("future_cd_mm2")
    if recorded is None or not recorded:
        return
    off = abs(measured["future_cd"] - recorded) / recorded
    if off > REPRODUCE_TOLERANCE:
        print(
            f"warning: {row['scene']}: the identified rollout's future Chamfer "
            f"{measured['future_cd']:.4g} mm^2 is {100 * off:.1f} % off the row's "
            f"{recorded:.4g}: were the rows identified with other --set values (grid "
            f"{measured['grid']}, substeps {measured['substeps']} here)?",
            file=sys.stderr,
        )


def _label(row: dict) -> str:
    return row.get("rows", "-")


def _run(row: dict) -> tuple[str, int, int]:
    """What tells one attribution run from another: its rows folder, grid and substeps."""
    return _label(row), int(row["grid"]), int(row["substeps"])


def summary(rows: list[dict]) -> dict[str, dict]:
    """Per variant of one run's rows: scenes, median future Chamfer, and on how many scenes it
    lowers the identified model's future Chamfer."""
    identified = {r["scene"]: r.get("future_cd") for r in rows if r["variant"] == "identified"}
    out = {}
    for name in VARIANTS:
        scored = [r for r in rows if r["variant"] == name and r.get("future_cd") is not None]
        lower = [r for r in scored if (identified.get(r["scene"]) or 0) > r["future_cd"]]
        median = statistics.median(r["future_cd"] for r in scored) if scored else None
        out[name] = {
            "scenes": len(scored),
            "diverged": sum(1 for r in rows if r["variant"] == name and "diverged" in r),
            "median_future_cd": median,
            "lower_than_identified": len(lower) if name != "identified" else None,
        }
    return out


def _cell(row: dict | None) -> str:
    if row is None:
        return "-"
    if "diverged" in row:
        return "diverged"
    return f"{_num(row['observed_cd'])} / {_num(row['future_cd'])}"


def markdown(rows: list[dict]) -> str:
    """Per run (rows folder, grid, substeps) and scene a row of observed / future Chamfer per
    variant, the per-variant summary of each run, and the last-frame centroid offsets."""
    runs = list(dict.fromkeys(_run(r) for r in rows))
    by = {(*_run(r), r["scene"], r["variant"]): r for r in rows}
    keys = list(dict.fromkeys((*_run(r), r["scene"]) for r in rows))
    lines = ["| rows | grid / substeps | scene | contact | " + " | ".join(VARIANTS) + " |"]
    lines += ["|---|---|---|---|" + "---|" * len(VARIANTS)]
    for label, grid, substeps, scene in keys:
        first = next(r for r in rows if (*_run(r), r["scene"]) == (label, grid, substeps, scene))
        cells = [_cell(by.get((label, grid, substeps, scene, name))) for name in VARIANTS]
        lines.append(
            f"| {label} | {grid} / {substeps} | {scene} | {first['contact']} | "
            + " | ".join(cells)
            + " |"
        )
    lines += ["", "Cells: observed / future Chamfer (mm^2).", ""]
    lines += [
        "| rows | grid / substeps | variant | scenes | diverged | median future CD mm^2 "
        "| future CD lower than identified |",
        "|---|---|---|---|---|---|---|",
    ]
    for run in runs:
        for name, s in summary([r for r in rows if _run(r) == run]).items():
            lower = "-" if s["lower_than_identified"] is None else str(s["lower_than_identified"])
            lines.append(
                f"| {run[0]} | {run[1]} / {run[2]} | {name} | {s['scenes']} | {s['diverged']} | "
                f"{_num(s['median_future_cd'])} | {lower} |"
            )
    lines += ["", "Last-frame centroid offsets from the recording's (mm, per object):", ""]
    lines += ["| rows | grid / substeps | scene | " + " | ".join(VARIANTS) + " |"]
    lines += ["|---|---|---|" + "---|" * len(VARIANTS)]
    for label, grid, substeps, scene in keys:
        cells = []
        for name in VARIANTS:
            offsets = (by.get((label, grid, substeps, scene, name)) or {}).get("last_offset_mm")
            cells.append(", ".join(f"{v:.0f}" for v in offsets.values()) if offsets else "-")
        lines.append(f"| {label} | {grid} / {substeps} | {scene} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def section_text(rows: list[dict], *, command: str, report: str, data: str) -> str:
    """The RESULTS section: what was measured, with what, on which data; the tables."""
    devices = sorted({r["device"] for r in rows})
    codes = sorted({r["code"] for r in rows})
    head = [
        f"## {SECTION}",
        "",
        "The identified values of each scene (the rows of `benchmarks/genesis_identify.py`), rolled",
        "out again with the contact identification chose, as identified and with one group of",
        "values replaced by the truth at a time (ground friction, initial velocities, the law",
        "parameters, all of them): which one the future error comes from.",
        "",
        f"- Command: `{command}`; table: `{report}`",
        f"- Machine: {', '.join(devices)}. Date {datetime.date.today().isoformat()}. "
        f"Code {', '.join(codes)}.",
        f"- Data: {data}.",
        "",
    ]
    return "\n".join(head) + "\n" + markdown(rows)


def parse_args(argv: list[str] | None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rows", type=Path, help="folder of genesis_identify rows (not with --report)")
    ap.add_argument("--scenes", type=Path, help="the suite folder the rows were identified on")
    ap.add_argument("--out", type=Path, required=True, help="folder for attribution.json/.md")
    ap.add_argument("--recipe", type=Path, default=Path("recipes/genesis_oracle.yaml"))
    ap.add_argument("--set", dest="sets", action="append", default=[], metavar="KEY=VALUE",
                    help="recipe override the rows were identified with (repeatable)")  # fmt: skip
    ap.add_argument("--only", help="comma-separated scene names")
    ap.add_argument("--emd-samples", type=int, default=1024)
    ap.add_argument("--report", action="store_true", help="gather the rows under --out")
    ap.add_argument(
        "--data", default="the scenes of --scenes", help="what the data is, for --write-results"
    )
    ap.add_argument("--measured-with", default=None, help="the measuring command, for --report")
    ap.add_argument("--write-results", type=Path, default=None, help="markdown file to update")
    args = ap.parse_args(argv)
    if not args.report and (args.rows is None or args.scenes is None):
        ap.error("--rows and --scenes are required unless --report")
    return args


def measure_all(args) -> list[dict]:
    """Measure every row's variants not yet in OUT/attribution.json; all its rows."""
    args.out.mkdir(parents=True, exist_ok=True)
    path = args.out / "attribution.json"
    data = json.loads(path.read_text()) if path.exists() else {"format": FORMAT, "rows": []}
    if data.get("format") != FORMAT:
        raise SystemExit(f"{path}: not a future-error attribution (format {data.get('format')!r})")
    wanted = None if not args.only else {n.strip() for n in args.only.split(",")}
    for row in read_rows(args.rows, wanted):
        name = row["scene"]
        folder = args.scenes / name
        if not (folder / "scene.json").is_file():
            raise SystemExit(f"--scenes {args.scenes}: no scene {name!r} (row {name})")
        recipe = load_recipe(args.recipe, [f"scene.path={folder}", *args.sets])
        run = (args.rows.name, int(recipe.simulator.grid), int(recipe.simulator.substeps))
        done = {r["variant"] for r in data["rows"] if r["scene"] == name and _run(r) == run}
        if done >= set(VARIANTS):
            continue
        scene = read_scene(folder)
        measured_rows = measure_scene(
            recipe, scene, row, emd_samples=args.emd_samples, label=args.rows.name, skip=done
        )
        for measured in measured_rows:
            print(json.dumps(measured), flush=True)
            data["rows"].append(measured)
            path.write_text(json.dumps(data, indent=1))
    return data["rows"]


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    args = parse_args(argv)
    if args.report:
        rows = gather_rows(args.out, "attribution.json", FORMAT, "a future-error attribution")
    else:
        rows = measure_all(args)
    (args.out / "attribution.md").write_text(markdown(rows))
    print(markdown(rows))
    if args.write_results is not None:
        command = shown_command(
            "benchmarks/genesis_future_attribution.py", argv, drop=("--measured-with", "--data")
        )
        body = section_text(
            rows, command=args.measured_with or command, report=command, data=args.data
        )
        text = args.write_results.read_text()
        args.write_results.write_text(
            replace_section(text, body, title=SECTION, before=SECTION_BEFORE)
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
