"""Resolution study on Genesis scenes: identification at several simulator grids and substep
counts, how each identified parameter converges with resolution, and the defaults it supports.

Every scene of a suite folder (``mosiv data suite OUT --source genesis``), or one scene folder,
is identified as ``benchmarks/genesis_identify.py`` identifies it (its ``run_scene``, recipe
``recipes/genesis_oracle.yaml`` unless ``--recipe``), once per grid of ``--grids`` and substep
count of ``--substeps``, each configuration in its own process so that its wall time and peak
memory are its own. Before anything runs each (scene, grid, substeps) is checked
(``check_configuration``): the recipe validator's stiffness check (``mosiv recipe validate``:
no stiffness cap below the value identification starts from), and no cap below an object's
true stiffness in the density gauge (the truth out of reach: the identified value would stop
at the cap, whatever the grid). A count that fails is refused, and the row says how many
substeps that grid needs; ``--unstable raise`` runs that count instead and says so.

    python benchmarks/genesis_resolution.py --scenes runs/genesis --out runs/resolution --plan
    python benchmarks/genesis_resolution.py --scenes runs/genesis --out runs/resolution \\
        --grids 48 64 96 128 --substeps 400 800 --jobs 8 --gpus-per-task 0.125 \\
        --set identify.velocity_iterations=40 --write-results docs/RESULTS.md
    # one process per configuration (e.g. on a device machine), then the merge
    python benchmarks/genesis_resolution.py --scenes runs/genesis --out runs/resolution \\
        --only E-S --grid 96 --substeps 800 --part
    python benchmarks/genesis_resolution.py --out runs/resolution --merge \\
        --write-results docs/RESULTS.md

``OUT`` holds ``study.json`` (the recipe and overrides; a non-empty folder without it is
refused, and so is a rerun with other settings), ``parts/SCENE__gG__sS.json`` (one
configuration's row; a rerun skips finished configurations, the runs in ``configs/gG-sS/``
resume their stages), and after the merge ``table.json``, ``table.csv`` (one line per scene,
object, parameter and configuration), ``table.md`` and ``convergence.png``. ``--write-results``
replaces the section "Resolution study on Genesis scenes" of that markdown file and copies the
plot to ``img/genesis_resolution.png`` beside it. The chosen defaults follow ``RULE``.
"""

from __future__ import annotations

import argparse
import copy
import json
import os
import sys
from pathlib import Path

from genesis_identify import _portable, command_line, find_scenes, run_scene
from genesis_resolution_report import (
    SECTION,
    make_study,
    markdown,
    plot,
    write_csv,
    write_results,
)
from identify_suite import code_version

from mosiv_framework.errors import ConfigError
from mosiv_framework.laws import get_law
from mosiv_framework.pipeline.params import GAUGE_PARAM, stiffness_ceilings
from mosiv_framework.recipes import check_recipe
from mosiv_framework.recipes.stiffness import scene_facts, stiffness_findings
from mosiv_framework.scale import Task, run_command, run_tasks
from mosiv_framework.scale.flags import add_scale_flags, scale_options

SCRIPT = "benchmarks/genesis_resolution.py"
#: what marks a folder as a study's output (and what it was run with)
STUDY = "study.json"
FORMAT = "mosiv-genesis-resolution/1"
#: the recipe keys each configuration sets; an override of them would be overwritten
SWEPT = ("simulator.grid", "simulator.substeps")
#: more substeps than this for one grid is treated as no stable count at all
MAX_SUBSTEPS = 1_000_000


# --------------------------------------------------------------------------------------------
# which substep counts keep a grid stable


def study_recipe(recipe: Path, sets: list[str]) -> dict:
    """The recipe with ``sets``, validated as ``mosiv recipe validate`` does (at its own grid
    and substeps), as plain containers; bad overrides are the caller's error (SystemExit)."""
    from omegaconf import OmegaConf

    swept = [s for s in sets if s.partition("=")[0].strip() in SWEPT]
    if swept:
        raise SystemExit(
            f"--set {swept[0]}: the study sets simulator.grid and simulator.substeps itself; "
            "give them as --grids and --substeps"
        )
    try:
        cfg, _warnings = check_recipe(recipe, sets)
    except ConfigError as exc:
        raise SystemExit(
            f"--recipe {recipe} with --set {sets}: {'; '.join(exc.problems)}"
        ) from None
    return OmegaConf.to_container(cfg, resolve=True)


def gauged_truth(scene: Path) -> dict[int, dict[str, float]]:
    """Per object id, its true parameters (gt/params.json) in the density gauge identification
    works in: scaled by assumed / true density of the first object, the one whose density is
    held at its law's default (``mosiv_framework.pipeline.params.GAUGE_PARAM``)."""
    gt = json.loads((scene / "gt" / "params.json").read_text())
    objects = {int(o["id"]): o for o in gt["objects"]}
    first = objects[min(objects)]
    assumed = get_law(first["material"]).param(GAUGE_PARAM).default
    gauge = assumed / float(first["params"][GAUGE_PARAM])
    return {
        k: {n: float(v) * gauge for n, v in o["params"].items() if isinstance(v, (int, float))}
        for k, o in objects.items()
    }


def check_configuration(scene: Path, recipe: dict, grid: int, substeps: int) -> list[str]:
    """Why ``substeps`` are too few at ``grid`` for ``scene`` (empty: they are enough).

    The recipe validator's stiffness errors (``stiffness_findings``: a cap below the value
    identification starts from), then every object whose true stiffness in the density gauge
    lies above its cap (``stiffness_ceilings``, the caps the validator and identification use).
    """
    run = copy.deepcopy(recipe)
    run["scene"]["path"] = str(scene)
    run["simulator"].update(grid=grid, substeps=substeps)
    facts = scene_facts(run, registry=None)  # read from scene.json, never generated
    if facts is None:
        raise SystemExit(f"{scene / 'scene.json'}: no usable fps, domain or object materials")
    problems, _caps = stiffness_findings(run, facts)
    cfl = float(run["identify"].get("stiffness_cfl", 0.0))
    if cfl <= 0:
        return problems  # no cap: identification may reach any stiffness
    dt = 1.0 / (facts.fps * substeps)
    caps = stiffness_ceilings(facts.families, {}, dx=facts.extent / grid, dt=dt, cfl=cfl)
    truth = gauged_truth(scene)
    for k, named in caps.items():
        for name, cap in named.items():
            true = truth.get(k, {}).get(name)
            if true is not None and true > cap:
                problems.append(
                    f"simulator.grid={grid} with simulator.substeps={substeps} caps {name} of "
                    f"object {k} ({facts.families[k]}) at {cap:,.0f} Pa, below its true "
                    f"{true:,.0f} Pa in the density gauge: the truth is out of reach"
                )
    return problems


def substeps_needed(scene: Path, recipe: dict, grid: int) -> int | None:
    """The fewest substeps ``check_configuration`` accepts at ``grid`` (every cap grows with the
    substep count, so the accepted counts are those from this one up); None beyond
    ``MAX_SUBSTEPS``."""
    high = 1
    while check_configuration(scene, recipe, grid, high):
        high *= 2
        if high > MAX_SUBSTEPS:
            return None
    low = high // 2 + 1 if high > 1 else 1
    while low < high:  # the first accepted count in (high / 2, high]
        mid = (low + high) // 2
        if check_configuration(scene, recipe, grid, mid):
            low = mid + 1
        else:
            high = mid
    return high


def plan_configuration(
    scene: Path, recipe: dict, grid: int, requested: int, *, policy: str
) -> dict:
    """What runs for one (scene, grid, substeps): ``substeps`` is the requested count when it is
    enough, the needed one when it is not and ``policy`` is "raise", None (refused) else;
    ``problems`` says why the requested count is not enough."""
    problems = check_configuration(scene, recipe, grid, requested)
    need = substeps_needed(scene, recipe, grid)
    substeps = requested if not problems else (need if policy == "raise" else None)
    return {
        "scene": scene.name,
        "grid": grid,
        "substeps_requested": requested,
        "substeps": substeps,
        "need": need,
        "problems": problems,
    }


def describe(plan: dict) -> str:
    """One line: the configuration and what becomes of it."""
    head = f"{plan['scene']}, grid {plan['grid']}, {plan['substeps_requested']} substeps"
    if not plan["problems"]:
        return f"{head}: stable"
    need = f"needs at least {plan['need']}" if plan["need"] else "no count up to 1e6 is enough"
    what = "refused" if plan["substeps"] is None else f"raised to {plan['substeps']}"
    return f"{head}: {what} ({need}): {plan['problems'][0]}"


# --------------------------------------------------------------------------------------------
# the output folder


def open_study(out: Path, record: dict) -> None:
    """Make ``out`` this study's folder: a new or empty one gets ``study.json`` first; one
    holding it must hold the same recipe and overrides (a rerun resumes); any other non-empty
    folder is refused, so no file of the user's is overwritten. ``record["format"]`` names the
    kind of study (benchmarks/genesis_noise.py keeps its own record in the same file), so one
    kind's folder is refused to another."""
    marker = out / STUDY
    entries = sorted(os.listdir(out)) if out.is_dir() else []
    if STUDY in entries:
        held = read_study(out, record["format"])
        if (held.get("recipe"), held.get("overrides")) != (record["recipe"], record["overrides"]):
            raise SystemExit(
                f"--out {out} holds a study of {held.get('recipe')} with --set "
                f"{held.get('overrides')}; this run has {record['recipe']} with --set "
                f"{record['overrides']}: choose another --out (or the same settings to resume)"
            )
        return
    # a sibling process may be writing the marker right now (one process per configuration)
    foreign = [e for e in entries if not e.startswith(f".{STUDY}.")]
    if out.exists() and (not out.is_dir() or foreign):
        shown = ", ".join(foreign[:5]) + (" ..." if len(foreign) > 5 else "")
        raise SystemExit(
            f"--out {out} is not empty and is not a study folder (no {STUDY}; it holds "
            f"{shown or 'a file'}): choose a new or empty folder, so no file of yours is "
            "overwritten"
        )
    out.mkdir(parents=True, exist_ok=True)
    temporary = out / f".{STUDY}.{os.getpid()}"
    temporary.write_text(json.dumps(record, indent=2) + "\n")
    os.replace(temporary, marker)


def read_study(out: Path, fmt: str = FORMAT) -> dict:
    try:
        held = json.loads((out / STUDY).read_text())
    except (OSError, ValueError) as exc:
        raise SystemExit(f"{out / STUDY}: not a readable study record ({exc})") from None
    if not isinstance(held, dict) or held.get("format") != fmt:
        raise SystemExit(f"{out / STUDY}: not a {fmt} record; choose another --out")
    return held


def part_path(out: Path, scene: str, grid: int, requested: int) -> Path:
    return out / "parts" / f"{scene}__g{grid}__s{requested}.json"


def finished(out: Path, plan: dict) -> bool:
    """Whether the configuration of ``plan`` ran before, with the substeps it would run now."""
    path = part_path(out, plan["scene"], plan["grid"], plan["substeps_requested"])
    if plan["substeps"] is None or not path.is_file():
        return False
    row = json.loads(path.read_text())
    return "error" not in row and "refused" not in row and row["substeps"] == plan["substeps"]


def load_rows(out: Path) -> list[dict]:
    """Every configuration's row under ``out/parts``."""
    return [json.loads(p.read_text()) for p in sorted((out / "parts").glob("*.json"))]


# --------------------------------------------------------------------------------------------
# running


def scene_data(scene: Path) -> dict:
    """What a row says of its scene's origin (as genesis_identify's rows)."""
    gt = json.loads((scene / "gt" / "params.json").read_text())
    seed = (gt.get("generator_params") or {}).get("seed")
    return {"generator": gt.get("generator"), "ranges": gt.get("ranges"), "seed": seed}


def run_configuration(scene: Path, plan: dict, *, recipe: Path, out: Path, sets: list) -> dict:
    """The row of one configuration: ``refused`` (nothing run), or genesis_identify's row of
    the scene identified with the planned grid and substeps (``error`` when it failed)."""
    keys = ("grid", "substeps_requested", "substeps", "need", "problems")
    plan_part = {k: plan[k] for k in keys}
    if plan["substeps"] is None:
        why = "; ".join(plan["problems"])
        row = {"scene": scene.name, **plan_part, "refused": why, "data": scene_data(scene)}
        return {**row, "code": code_version()}
    folder = out / "configs" / f"g{plan['grid']}-s{plan['substeps']}"
    folder.mkdir(parents=True, exist_ok=True)
    swept = [f"simulator.grid={plan['grid']}", f"simulator.substeps={plan['substeps']}"]
    return {**run_scene(scene, recipe=recipe, out=folder, sets=[*sets, *swept]), **plan_part}


def run_part(args, scene: Path, recipe: dict) -> int:
    """One configuration in this process: its row into ``parts/``; 2 when refused."""
    plan = plan_configuration(scene, recipe, args.grid, args.substeps[0], policy=args.unstable)
    print(f"[resolution] {describe(plan)}", flush=True)
    path = part_path(args.out, scene.name, args.grid, args.substeps[0])
    if finished(args.out, plan):
        print(f"[resolution] finished before: {path.name}", flush=True)
        return 0
    path.parent.mkdir(parents=True, exist_ok=True)
    row = run_configuration(scene, plan, recipe=args.recipe, out=args.out, sets=args.set)
    path.write_text(json.dumps(row, indent=2) + "\n")
    if "refused" in row:
        print(
            f"[resolution] refused {scene.name} at grid {args.grid} with {args.substeps[0]} "
            f"substeps: {row['refused']} (--unstable raise runs {plan['need']} instead)",
            file=sys.stderr,
        )
        return 2
    return 1 if "error" in row else 0


def part_command(args, root: Path, plan: dict) -> list[str]:
    command = [sys.executable, str(Path(__file__).resolve()), "--scenes", str(args.scenes)]
    command += ["--only", plan["scene"]] if args.scenes == root else []
    command += ["--grid", str(plan["grid"]), "--substeps", str(plan["substeps_requested"])]
    command += ["--out", str(args.out), "--recipe", str(args.recipe)]
    command += ["--unstable", args.unstable, "--part"]
    return command + [x for s in args.set for x in ("--set", s)]


def run_study(args, root: Path, plans: list[dict], scale: dict) -> None:
    """Every planned configuration not finished before: refused ones get their row here, the
    others run as ``--part`` processes (one after another, or ``--jobs`` at once)."""
    parts = args.out / "parts"
    parts.mkdir(parents=True, exist_ok=True)
    tasks = []
    for plan in plans:
        name = f"{plan['scene']}__g{plan['grid']}__s{plan['substeps_requested']}"
        if finished(args.out, plan):
            print(f"[resolution] {name}: finished before", flush=True)
        elif plan["substeps"] is None:
            row = run_configuration(
                root / plan["scene"], plan, recipe=args.recipe, out=args.out, sets=args.set
            )
            (parts / f"{name}.json").write_text(json.dumps(row, indent=2) + "\n")
        else:
            (parts / f"{name}.json").unlink(missing_ok=True)  # no stale row of a crash
            (parts / f"{name}.log").unlink(missing_ok=True)  # the task appends to it
            command = part_command(args, root, plan)
            tasks.append(Task(name, run_command, (command,), parts / f"{name}.log"))
    for name, outcome in run_tasks(tasks, **scale).items():
        code = outcome.result if outcome.ok else repr(outcome.error)
        print(f"[resolution] {name}: {'done' if code == 0 else f'FAILED ({code})'}", flush=True)
        part = parts / f"{name}.json"
        if not part.is_file():  # the process died before writing its row
            scene, grid, requested = name.rsplit("__", 2)
            row = {"scene": scene, "grid": int(grid[1:]), "substeps_requested": int(requested[1:])}
            row |= {"substeps": None, "error": f"the process wrote no row (see parts/{name}.log)"}
            part.write_text(json.dumps(row, indent=2) + "\n")


def merge(args, argv: list[str]) -> dict:
    """table.json, table.csv, table.md and convergence.png from every row in ``parts/``, and
    the RESULTS section with ``--write-results``."""
    record = read_study(args.out)
    rows = load_rows(args.out)
    if not rows:
        raise SystemExit(f"--out {args.out}: no configuration rows in parts/ to merge")
    study = make_study(rows, tolerance=args.tolerance, tolerance_deg=args.tolerance_deg)
    study["study"] = record
    (args.out / "table.json").write_text(json.dumps(study, indent=2) + "\n")
    write_csv(args.out / "table.csv", study)
    plot(study, args.out / "convergence.png")
    (args.out / "table.md").write_text(markdown(study, plot_link="convergence.png"))
    if args.write_results is not None:
        command = command_line(argv, script=SCRIPT)
        write_results(args.write_results, study, command=command, png=args.out / "convergence.png")
        print(f"[resolution] wrote the section '{SECTION}' of {args.write_results}")
    return study


# --------------------------------------------------------------------------------------------
# command line


def parse(argv: list[str]) -> argparse.Namespace:
    here = Path(__file__).resolve().parent
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", type=Path, help="a mosiv data suite folder, or one scene")
    parser.add_argument("--only", default=None, help="comma-separated scene names (E-S,...)")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--recipe", type=Path, default=here.parent / "recipes/genesis_oracle.yaml")
    parser.add_argument("--grids", type=int, nargs="+", default=[48, 64, 96, 128])
    parser.add_argument("--substeps", type=int, nargs="+", default=[400, 800])
    parser.add_argument("--grid", type=int, help="with --part: the one grid to run")
    parser.add_argument(
        "--unstable",
        choices=("refuse", "raise"),
        default="refuse",
        help="a substep count too few for a grid: refuse the configuration (default) or run "
        "the fewest substeps that are enough",
    )
    parser.add_argument("--set", action="append", default=[], help="key=value recipe override")
    parser.add_argument(
        "--tolerance", type=float, default=5.0, help="chosen defaults: percentage points"
    )
    parser.add_argument("--tolerance-deg", type=float, default=1.0, help="friction angle (deg)")
    parser.add_argument("--write-results", type=Path, default=None, help="e.g. docs/RESULTS.md")
    parser.add_argument("--plan", action="store_true", help="print the configurations only")
    parser.add_argument("--part", action="store_true", help="run one configuration (--grid)")
    parser.add_argument("--merge", action="store_true", help="only merge the rows in OUT/parts")
    add_scale_flags(parser, "configurations")
    args = parser.parse_args(argv)
    counts = [("--grids", g) for g in args.grids] + [("--substeps", s) for s in args.substeps]
    bad = [f"{flag} {v}" for flag, v in counts if v < 1]
    if bad:
        parser.error(f"{bad[0]}: grids and substep counts must be at least 1")
    if not args.merge and args.scenes is None:
        parser.error("--scenes is required (except with --merge)")
    if args.part and (args.grid is None or len(args.substeps) != 1):
        parser.error("--part runs one configuration: give --grid G and one --substeps S")
    return args


def scene_folders(path: Path, only: str | None) -> tuple[Path, list[str]]:
    """(folder holding the scenes, their names): ``path`` is a suite folder or one scene."""
    if not (path / "scene.json").is_file():
        return path, find_scenes(path, only)
    if not (path / "gt" / "params.json").is_file():
        raise SystemExit(f"--scenes {path}: the scene has no gt/params.json (no truth to score)")
    if only and only != path.name:
        raise SystemExit(f"--only {only}: --scenes {path} is the one scene {path.name}")
    return path.parent, [path.name]


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    args = parse(argv)
    if args.merge:
        print(markdown(merge(args, argv), plot_link="convergence.png"))
        return 0
    scale = scale_options(args)
    root, names = scene_folders(args.scenes, args.only)
    recipe = study_recipe(args.recipe, args.set)
    if args.part and len(names) != 1:
        raise SystemExit(f"--part runs one scene: give --only with one of {', '.join(names)}")
    record = {"format": FORMAT, "recipe": _portable(str(args.recipe)), "overrides": args.set}
    if args.part:
        open_study(args.out, record)
        return run_part(args, root / names[0], recipe)
    plans = [
        plan_configuration(root / name, recipe, grid, count, policy=args.unstable)
        for name in names
        for grid in args.grids
        for count in args.substeps
    ]
    for plan in plans:
        print(f"[resolution] {describe(plan)}", flush=True)
    if args.plan:
        for plan in plans:
            if plan["substeps"] is not None:
                print(" ".join(part_command(args, root, plan)))
        return 0
    open_study(args.out, record)
    run_study(args, root, plans, scale)
    print(markdown(merge(args, argv), plot_link="convergence.png"))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
