"""The resolution floor of diagnosis-suite entries, beside their candidates' held-out drops.

For each named entry of the full diagnosis suite, the scene is generated and identified exactly
as ``mosiv diagnose-suite`` does it (a rerun reuses finished stages), and the identified
model's resolution floor is measured (``mosiv_framework.diagnose.floor``: the prediction on
resampled particles against the original, in excess of frame 0, mean over the diagnosis's
fit and held-out frames, mm^2). Then, for every candidate that a saved diagnosis of the entry
evaluated (``--diagnoses DIR/ENTRY/diagnosis.json``), the absolute held-out drop against the
null (mm^2) is printed next to the floor. This shows whether the rule "a held-out drop must
exceed the floor" would keep the true effects and reject the false acceptances. It refits
nothing.

    python benchmarks/resolution_floor.py --out runs/floor --jobs 5 --gpus-per-task 0.2 \\
        --diagnoses benchmarks/data/diagnosis_suite \\
        control-1 outside-quadratic_drag material_damping-0 ground_friction-0 quadratic_drag-0
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from mosiv_framework.diagnose.report import loaded_table
from mosiv_framework.diagnose.suite import DEFAULT_RECIPES, suite_entries
from mosiv_framework.logs import configure_logging, level_from_flags
from mosiv_framework.scale import Task, run_tasks
from mosiv_framework.scale.flags import add_scale_flags, scale_options


def measure(entry, out: Path, recipe_path: Path, fractions: tuple[float, ...]) -> dict:
    """Generate and identify ``entry`` (resumable), then its floors at each fraction."""
    from mosiv_framework.diagnose.context import load_run
    from mosiv_framework.diagnose.diagnosis import BUDGETS, split_frames
    from mosiv_framework.diagnose.floor import resolution_floor, summarise_floor
    from mosiv_framework.pipeline import run_pipeline
    from mosiv_framework.recipes import load_recipe

    run_dir = out / entry.name
    overrides = [
        f"scene.path={run_dir / 'scene'}",
        f"output.dir={run_dir}",
        f"scene.source.materials={entry.materials}",
        f"scene.source.seed={entry.seed}",
        *([f"scene.source.conceal='{entry.conceal}'"] if entry.conceal else []),
        *entry.overrides,
    ]
    run_pipeline(load_recipe(recipe_path, overrides), run_dir=run_dir)
    ctx = load_run(run_dir)
    fit, held = split_frames(ctx.observed_frames, ctx.n_frames, BUDGETS["full"].heldout_fraction)
    floors = {}
    for fraction in fractions:
        table = resolution_floor(ctx, ctx.identified, fraction=fraction)
        floors[str(fraction)] = summarise_floor(
            table, {"fit": fit, "heldout": held}, fraction=fraction
        )
    return {"entry": entry.name, "fit_frames": fit, "heldout_frames": held, "floors": floors}


def heldout_drops(diagnosis: dict) -> dict[str, tuple[float, bool]]:
    """Candidate -> (null's held-out mean minus the candidate's, mm^2; accepted) of a saved
    diagnosis. A model whose prediction diverged (an infinite error) has no such number and is
    left out."""
    held = diagnosis["frames"]["heldout"]
    tables = {
        k: loaded_table(v).sum(axis=0)[held].mean()
        for k, v in diagnosis["frame_errors_mm2"].items()
    }
    return {
        e["name"]: (float(tables["null"] - tables[e["name"]]), bool(e["accepted"]))
        for e in diagnosis["evidence"]
        if np.isfinite(tables["null"]) and np.isfinite(tables[e["name"]])
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("entries", nargs="+", help="names of full-suite entries")
    parser.add_argument("--out", required=True, type=Path)
    add_scale_flags(parser, "entries")
    parser.add_argument("--diagnoses", type=Path, default=None)
    parser.add_argument("--fractions", default="0.25,0.5")
    args = parser.parse_args()
    # the pipeline's progress (stages, global candidates) is logged at INFO: show it
    configure_logging(level_from_flags())
    fractions = tuple(float(x) for x in args.fractions.split(","))
    known = {e.name: e for e in suite_entries(False)}
    unknown = sorted(set(args.entries) - set(known))
    if unknown:
        raise SystemExit(f"unknown entries {unknown}; valid: {sorted(known)}")
    args.out.mkdir(parents=True, exist_ok=True)
    recipe = DEFAULT_RECIPES[False]
    tasks = [Task(n, measure, (known[n], args.out, recipe, fractions)) for n in args.entries]

    def report(outcome) -> None:
        if outcome.ok:
            print(f"{outcome.name}: floors {outcome.result['floors']}", flush=True)
        else:
            print(f"{outcome.name} FAILED: {outcome.error!r}", flush=True)

    outcomes = run_tasks(tasks, on_done=report, **scale_options(args))
    results = {name: o.result for name, o in outcomes.items() if o.ok}
    lines = [
        "| entry | floor fit (mm^2) | floor held-out (mm^2) | candidate | held-out drop (mm^2) | accepted |",
        "|---|---|---|---|---:|---|",
    ]
    for name in args.entries:
        if name not in results:
            continue
        r = results[name]
        floor_fit = ", ".join(
            f"{f}: {v['fit']:.3g}" if v else f"{f}: diverged" for f, v in r["floors"].items()
        )
        floor_held = ", ".join(
            f"{f}: {v['heldout']:.3g}" if v else f"{f}: diverged" for f, v in r["floors"].items()
        )
        saved = args.diagnoses / name / "diagnosis.json" if args.diagnoses else None
        drops = heldout_drops(json.loads(saved.read_text())) if saved and saved.exists() else {}
        if not drops:
            lines.append(f"| {name} | {floor_fit} | {floor_held} | - | - | - |")
        for cand, (drop, accepted) in drops.items():
            lines.append(
                f"| {name} | {floor_fit} | {floor_held} | {cand} | {drop:.4g} | "
                f"{'yes' if accepted else 'no'} |"
            )
    table = "\n".join(lines)
    (args.out / "floors.json").write_text(json.dumps(results, indent=2) + "\n")
    (args.out / "floors.md").write_text(table + "\n")
    print(table)


if __name__ == "__main__":
    main()
