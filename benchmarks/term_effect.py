"""Measure each saved diagnosis's candidates' own effects (``diagnose.effect``) and resolution
floors (``diagnose.floor``), and write copies of the diagnosis files that carry them.

The suite's saved entries (benchmarks/data/diagnosis_suite/*/) hold every candidate's refitted
coefficients, and the accepted candidate's refitted shared parameters (``param_shift``), but not
the run's particles. This script regenerates each entry's scene from its suite definition (same
seed and conceal spec), reconstructs and lifts it as the suite's recipe does (no
identification), and rolls out:
- for each candidate that passed the held-out, BIC and interval tests: its refitted model with
  and without its effect. The accepted candidate uses its own refitted shared parameters; the
  others (whose shared parameters the files do not hold) use the accepted candidate's, marked
  ``"at": "accepted shared parameters"``;
- the resolution floor at the same shared parameters.

Output: OUT/NAME/diagnosis.json (the input with ``effect`` on those evidence rows and
``resolution_floor_mm2`` measured here, the file's own floor kept as ``resolution_floor_saved``),
plus diagnosis.md and score.json copied, so ``mosiv diagnose-suite OUT --replay`` scores them.

    python benchmarks/term_effect.py benchmarks/data/diagnosis_suite/*/ \
        --out runs/term_effect --jobs 8 --gpus-per-task 0.5
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path

import torch

from mosiv_framework.diagnose.candidates import build_candidates
from mosiv_framework.diagnose.context import RunContext, build_context
from mosiv_framework.diagnose.effect import effect_tables, summarise_effect
from mosiv_framework.diagnose.floor import resolution_floor, summarise_floor
from mosiv_framework.diagnose.suite import DEFAULT_RECIPES, entry_overrides, suite_entries
from mosiv_framework.pipeline import _component, ensure_scene
from mosiv_framework.pipeline.rundir import RunDir
from mosiv_framework.recipes import load_recipe
from mosiv_framework.registry import get_registry
from mosiv_framework.scale import Task, run_tasks
from mosiv_framework.scale.flags import add_scale_flags, scale_options
from mosiv_framework.types import ObjectParams, SimulationParams


def prepare(entry, run_dir: Path) -> RunContext:
    """The entry's scene, reconstruction and particles (made once, then reloaded), with no
    identified model yet (the caller sets it from the diagnosis file)."""
    recipe = load_recipe(DEFAULT_RECIPES[False], entry_overrides(entry, run_dir))
    rd = RunDir(run_dir)
    scene = ensure_scene(recipe.scene, rd)
    if rd.path("particles.pt").is_file():
        reconstruction = rd.load_torch("reconstruction.pt")
        particles = rd.load_torch("particles.pt")
    else:
        registry = get_registry()
        name, options = _component(recipe.reconstructor)
        reconstruction = registry.create("reconstructor", name, options).fit(scene, run_dir=rd.root)
        name, options = _component(recipe.lifter)
        particles = registry.create("lifter", name, options).lift(reconstruction, scene)
        rd.save_torch("reconstruction.pt", reconstruction)
        rd.save_torch("particles.pt", particles)
    return build_context(rd, recipe, scene, reconstruction, particles, None, {})


def params_from_shift(ctx: RunContext, shift: dict, side: str) -> SimulationParams:
    """The parameters a file's ``param_shift`` holds on ``side`` ("before": the run's
    identified model; "after": the accepted refit, its effect included), in the scene's
    declared families (a plasticity candidate's yield stress is left to the candidate)."""
    families = {obj.id: obj.material for obj in ctx.scene.objects}
    objects, velocity = {}, {}
    for key, rows in shift.items():
        if key == "ground_friction":
            continue
        k = int(key)
        values = {
            n: torch.tensor(float(r[side]))
            for n, r in rows.items()
            if n != "initial_velocity" and not (n == "yield_stress" and families[k] == "elastic")
        }
        objects[k] = ObjectParams(families[k], values)
        velocity[k] = torch.tensor(rows["initial_velocity"][side], dtype=torch.float32)
    ground = torch.tensor(float(shift["ground_friction"][side]))
    return SimulationParams(objects, velocity, ground, {})


def shared_of_accepted(ctx: RunContext, shift: dict, candidate, theta) -> SimulationParams:
    """The accepted candidate's refitted shared parameters, without its effect."""
    after = params_from_shift(ctx, shift, "after")
    if candidate.kind in ("ground_friction", "object_friction"):  # "after" holds mu + theta
        return candidate.without(after, torch.tensor(theta, dtype=torch.float32))
    return after  # terms and gravity live in params.terms; plasticity's yield stress dropped


def measure(entry_dir: str, out: str) -> str:
    """One saved entry: its effects and floor, written to OUT/NAME; returns a summary line."""
    src = Path(entry_dir)
    name = src.name
    entry = {e.name: e for e in suite_entries(False)}[name]
    diagnosis = json.loads((src / "diagnosis.json").read_text())
    dst = Path(out) / name
    dst.mkdir(parents=True, exist_ok=True)
    for extra in ("diagnosis.md", "score.json"):
        if (src / extra).is_file():
            shutil.copy(src / extra, dst / extra)
    accepted = diagnosis.get("accepted")
    passing = [
        e
        for e in diagnosis["evidence"]
        if e["passes_heldout"] and e["passes_bic"] and e.get("passes_interval", True)
    ]
    line = f"{name}: nothing accepted"
    if accepted is not None and passing:
        ctx = prepare(entry, dst / "run")
        # the candidates' bases (assumed frictions, free parameters) are the run's identified
        # model's, as in the diagnosis
        ctx.identified = params_from_shift(ctx, accepted["param_shift"], "before")
        candidates = {c.name: c for c in build_candidates(ctx)[0]}
        first = candidates[accepted["name"]]
        theta_first = next(e["theta"] for e in passing if e["name"] == accepted["name"])
        shared = shared_of_accepted(ctx, accepted["param_shift"], first, theta_first)
        frames = dict(diagnosis["frames"])
        floor = summarise_floor(resolution_floor(ctx, shared), frames)
        if "resolution_floor_mm2" in diagnosis:
            diagnosis["resolution_floor_saved"] = diagnosis["resolution_floor_mm2"]
        diagnosis["resolution_floor_mm2"] = floor
        parts = []
        for row in passing:
            candidate = candidates[row["name"]]
            theta = torch.tensor(row["theta"], dtype=torch.float32)
            tables = effect_tables(ctx, candidate.apply(shared, theta), shared)
            summary = summarise_effect(tables, frames)
            summary["at"] = (
                "own shared parameters"
                if row["name"] == accepted["name"]
                else "accepted shared parameters"
            )
            row["effect"] = summary
            parts.append(
                f"{row['name']} {summary['fit']:.3g} mm^2 fit, "
                f"max {summary['max_displacement_mm']:.3g} mm"
            )
        floor_text = "diverged" if floor is None else f"{floor['fit']:.3g} mm^2 fit"
        line = f"{name}: floor {floor_text}; " + "; ".join(parts)
    tmp = dst / "diagnosis.json.tmp"
    tmp.write_text(json.dumps(diagnosis, indent=2, default=float) + "\n")
    tmp.replace(dst / "diagnosis.json")
    return line


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("entries", nargs="+", help="saved suite entry folders")
    parser.add_argument("--out", required=True)
    add_scale_flags(parser, "entries")
    args = parser.parse_args(argv)
    tasks = [Task(Path(e).name, measure, (e, args.out)) for e in args.entries]

    def report(outcome) -> None:
        text = outcome.result if outcome.ok else f"{outcome.name}: FAILED {outcome.error!r}"
        print(text, flush=True)

    run_tasks(tasks, on_done=report, **scale_options(args))
    return 0


if __name__ == "__main__":
    sys.exit(main())
