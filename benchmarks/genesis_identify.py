"""Identification on scenes another engine simulated: the Genesis oracle benchmark.

Runs one recipe (default ``recipes/genesis_oracle.yaml``: oracle reconstructor, gt-points
lifter, warp-mpm, a data-independent start and a global search before gradient descent) on
every scene of a suite folder that ``mosiv data suite OUT --source genesis --ranges wide``
made, and tabulates per scene and object the raw and gauge-free errors of every parameter,
whether its 95 % interval holds the truth, what kind of interval it is and by which method
(and, for a sandwich interval, the same of the Laplace interval from the same probes, which
the run's identify history keeps), per scene the contact between objects it identified with
(under ``identify.contact: auto`` with both modes' losses), the observed and future Chamfer
(CD) and earth mover's distance (EMD), wall time and peak memory; then the suite against its
targets, the interval coverage for the method used and for the Laplace intervals of the same
runs. warp-mpm is not the engine that made these scenes, so unlike
``benchmarks/identify_suite.py`` the model is not exact here. The rows, tables and the
RESULTS section are ``benchmarks/genesis_identify_table.py``'s.

    python benchmarks/genesis_identify.py --scenes runs/genesis --out runs/genesis_identify
    python benchmarks/genesis_identify.py --scenes runs/genesis --out runs/genesis_identify \
        --jobs 13 --gpus-per-task 0.07 --write-results docs/RESULTS.md
    python benchmarks/genesis_identify.py --scenes runs/genesis --only E-S \
        --out runs/genesis-cpu --set simulator.device=cpu --set simulator.grid=32

Writes ``OUT/table.json`` and ``OUT/table.md`` (a rerun into the same folder resumes finished
stages and keeps the rows of scenes it does not run); ``--write-results`` replaces the section
"Identification on Genesis scenes" of that markdown file with the table, the command, the
machine, the date, the code version and the data. With ``--jobs N`` each scene runs as a Ray
task in its own process (output in ``OUT/parts/SCENE.log``), as in identify_suite. Where Ray
is not installed (a GPU machine without a package index), run one ``--part`` process per scene
yourself (each writes ``OUT/parts/SCENE.json``), then ``--merge`` builds the table from those
rows (and with ``--write-results`` the section):

    python benchmarks/genesis_identify.py --scenes runs/genesis --out runs/gid --only E-S --part
    python benchmarks/genesis_identify.py --scenes runs/genesis --out runs/gid --merge \
        --write-results docs/RESULTS.md

On the GPU machine, ``--job-file JOBS`` writes those ``--part`` runs as jobs for
benchmarks/device_queue.py, which runs a few at a time per GPU (each in a snapshot of the
checkout; with ``--mps`` side by side on the GPU); ``--merge`` as above once they have ended.
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
import time
import traceback
from pathlib import Path

from genesis_identify_table import (  # noqa: F401 (other benchmarks import these from here)
    KEEP_MARKER,
    KINDS,
    PARAMS,
    SECTION,
    SECTION_BEFORE,
    TARGETS,
    _fill,
    data_description,
    make_table,
    markdown,
    object_entries,
    replace_section,
    scene_row,
    section_text,
    summarise,
    write_results,
)
from identify_suite import _timed, code_version

from mosiv_framework.logs import configure_logging, level_from_flags
from mosiv_framework.scale import Task, run_command, run_tasks
from mosiv_framework.scale.flags import add_scale_flags, scale_options

# --------------------------------------------------------------------------------------------
# running


def find_scenes(root: Path, only: str | None) -> list[str]:
    """Scene folders of the suite folder ``root`` (with scene.json and gt/params.json), in
    suite.json's order where it lists them, else by name; ``only`` selects by name."""
    names = sorted(p.parent.name for p in root.glob("*/scene.json"))
    names = [n for n in names if (root / n / "gt" / "params.json").is_file()]
    index = root / "suite.json"
    if index.is_file():
        listed = list(json.loads(index.read_text()).get("scenes", {}))
        names = [n for n in listed if n in names] + [n for n in names if n not in listed]
    if not names:
        raise SystemExit(f"--scenes {root}: no scene folders with gt/params.json")
    if only:
        wanted = [n.strip() for n in only.split(",") if n.strip()]
        unknown = [n for n in wanted if n not in names]
        if unknown:
            raise SystemExit(f"--only: unknown scene(s) {unknown}; valid: {', '.join(names)}")
        names = [n for n in names if n in wanted]
    return names


def _device_name(cfg) -> str:
    """The GPU's name when the recipe's simulator runs on CUDA, else "CPU"."""
    import torch

    on_cuda = str(cfg.simulator.get("device", "cuda")).startswith("cuda")
    return torch.cuda.get_device_name(0) if on_cuda and torch.cuda.is_available() else "CPU"


def run_scene(scene: Path, *, recipe: Path, out: Path, sets: list[str]) -> dict:
    """``run_pipeline`` on one scene into ``out/runs/NAME``; its table row (an ``error`` row
    when it fails, so one scene cannot lose the others)."""
    from mosiv_framework.pipeline import run_pipeline
    from mosiv_framework.recipes import load_recipe

    run_dir = out / "runs" / scene.name
    gt = json.loads((scene / "gt" / "params.json").read_text())
    data = {
        "generator": gt.get("generator"),
        "ranges": gt.get("ranges"),
        "seed": (gt.get("generator_params") or {}).get("seed"),
    }
    marker = run_dir / "stages" / "identify.json"
    before = marker.read_text() if marker.is_file() else None
    started = time.perf_counter()
    try:
        cfg = load_recipe(recipe, [f"scene.path={scene}", f"output.dir={run_dir}", *sets])
        metrics = run_pipeline(cfg, run_dir=run_dir)
    except Exception as exc:  # one failed scene must not lose the others' rows
        traceback.print_exc()
        # the message goes into a results file: the scene folder by its name, not its path
        why = f"{type(exc).__name__}: {exc}".replace(str(scene.parent), "SCENES")
        return {"scene": scene.name, "error": why, "data": data}
    elapsed = _timed(run_dir, before, time.perf_counter() - started)
    return scene_row(
        scene.name,
        metrics,
        time_s=elapsed,
        data=data,
        device=_device_name(cfg),
        code=code_version(),
        history=_history(run_dir),
    )


def _history(run_dir: Path) -> list[dict] | None:
    """The run's identify/history.json records (None without one: a run that did not
    identify), whose interval record holds the Laplace intervals beside the sandwich ones."""
    from mosiv_framework.pipeline.formats import read_history

    path = run_dir / "identify" / "history.json"
    return read_history(path) if path.is_file() else None


def _earlier(out: Path) -> dict[str, dict]:
    table = out / "table.json"
    return {r["scene"]: r for r in json.loads(table.read_text())["rows"]} if table.is_file() else {}


def save_table(out: Path, rows: dict[str, dict], *, recipe: Path, sets: list[str]) -> dict:
    table = {"recipe": _portable(str(recipe)), "overrides": sets, **make_table(list(rows.values()))}
    (out / "table.json").write_text(json.dumps(table, indent=2) + "\n")
    (out / "table.md").write_text(markdown(table))
    return table


def run_serial(args, names: list[str]) -> dict:
    """The scenes one after another in this process, table.json saved after each."""
    rows = _earlier(args.out)
    for name in names:
        rows[name] = run_scene(args.scenes / name, recipe=args.recipe, out=args.out, sets=args.set)
        save_table(args.out, rows, recipe=args.recipe, sets=args.set)
    return save_table(args.out, rows, recipe=args.recipe, sets=args.set)


def run_part(args, name: str) -> None:
    """One scene of a parallel run: its row into ``out/parts/NAME.json`` for the parent."""
    row = run_scene(args.scenes / name, recipe=args.recipe, out=args.out, sets=args.set)
    (args.out / "parts" / f"{name}.json").write_text(json.dumps(row, indent=2) + "\n")


def merge(args, names: list[str]) -> dict:
    """The table from the rows that ``--part`` processes wrote into ``out/parts`` (a scene
    without a part file keeps its earlier row, if any). Pass the parts' --set flags again:
    the table records them."""
    rows = _earlier(args.out)
    parts = {n: args.out / "parts" / f"{n}.json" for n in names}
    found = {n: json.loads(p.read_text()) for n, p in parts.items() if p.is_file()}
    if not found:
        raise SystemExit(
            f"--merge: no rows in {args.out / 'parts'}; run the --part processes first"
        )
    rows.update(found)
    return save_table(args.out, rows, recipe=args.recipe, sets=args.set)


def run_parallel(args, names: list[str], scale: dict) -> dict:
    """Each scene as a Ray task running this script with ``--part``; rows merged after."""
    parts = args.out / "parts"
    parts.mkdir(parents=True, exist_ok=True)
    tasks = []
    for name in names:
        (parts / f"{name}.json").unlink(missing_ok=True)  # no stale row of a crash
        (parts / f"{name}.log").unlink(missing_ok=True)  # the task appends to it
        command = [sys.executable, __file__, "--scenes", str(args.scenes), "--only", name]
        command += ["--out", str(args.out), "--recipe", str(args.recipe), "--part"]
        command += [x for s in args.set for x in ("--set", s)]
        tasks.append(Task(name, run_command, (command,), parts / f"{name}.log"))
    for name, outcome in run_tasks(tasks, **scale).items():
        code = outcome.result if outcome.ok else repr(outcome.error)
        print(f"[genesis] {name}: {'done' if code == 0 else f'FAILED ({code})'}", flush=True)
    rows = _earlier(args.out)
    for name in names:
        part = parts / f"{name}.json"
        rows[name] = (
            json.loads(part.read_text())
            if part.is_file()
            else {"scene": name, "error": f"the task wrote no row (see parts/{name}.log)"}
        )
    return save_table(args.out, rows, recipe=args.recipe, sets=args.set)


def shown_command(script: str, argv: list[str], *, drop: tuple[str, ...] = ()) -> str:
    """``python script argv`` as a results file shows it, without the flags in ``drop`` and
    their values (text that describes the run, such as --data, is not part of its command)."""
    shown = list(argv)
    for flag in drop:
        if flag in shown:
            at = shown.index(flag)
            del shown[at : at + 2]
    return f"python {script} " + shlex.join(shown)


def command_line(argv: list[str], *, script: str = "benchmarks/genesis_identify.py") -> str:
    """The command as run (``script`` with ``argv``; genesis_resolution names its own), the
    scene and output folders named SCENES and OUT and other paths relative to the repository
    (a results file must not name a machine's paths)."""

    def written(flag: str, value: str) -> str:
        # the folders differ on every machine, so they are named; other paths are portable
        return flag[2:].upper() if flag in ("--scenes", "--out") else _portable(value)

    out, path_flag = ["python", script], None
    for arg in argv:
        flag, eq, value = arg.partition("=")
        if path_flag is not None:  # the value of a path flag given as a separate argument
            out.append(written(path_flag, arg))
            path_flag = None
        elif flag in PATH_FLAGS and eq:
            out.append(f"{flag}={written(flag, value)}")
        elif flag in PATH_FLAGS:
            out.append(flag)
            path_flag = flag
        else:
            out.append(arg)
    return shlex.join(out)


#: flags whose value is a path of the machine the benchmark ran on
PATH_FLAGS = ("--scenes", "--out", "--recipe", "--write-results")


def _portable(path: str) -> str:
    """``path`` relative to the repository when inside it; an outside absolute path by its
    file name only."""
    resolved, root = Path(path).resolve(), Path(__file__).resolve().parents[1]
    if resolved.is_relative_to(root):
        return str(resolved.relative_to(root))
    return Path(path).name if Path(path).is_absolute() else path


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    here = Path(__file__).resolve().parent
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", type=Path, required=True, help="a mosiv data suite folder")
    parser.add_argument("--only", default=None, help="comma-separated scene names (E-P,...)")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--recipe", type=Path, default=here.parent / "recipes/genesis_oracle.yaml")
    parser.add_argument("--set", action="append", default=[], help="key=value recipe override")
    parser.add_argument("--write-results", type=Path, default=None, help="e.g. docs/RESULTS.md")
    add_scale_flags(parser, "scenes")
    parser.add_argument("--part", action="store_true", help="run one scene (--only), row only")
    parser.add_argument(
        "--merge", action="store_true", help="the table from the --part rows in OUT/parts"
    )
    parser.add_argument(
        "--job-file",
        type=Path,
        default=None,
        help="write the --part run of each scene as a job of benchmarks/device_queue.py, run none",
    )
    args = parser.parse_args(argv)
    # the pipeline's progress (stages, global candidates) is logged at INFO: show it
    configure_logging(level_from_flags())
    if sum([args.part, args.merge, args.job_file is not None]) > 1:
        parser.error(
            "--part runs one scene, --merge tabulates the parts, --job-file lists the "
            "parts: give one of them"
        )
    scale = scale_options(args)
    names = find_scenes(args.scenes, args.only)
    if args.job_file is not None:
        write_job_file(args, names)
        return 0
    (args.out / "parts").mkdir(parents=True, exist_ok=True)
    if args.part:
        run_part(args, names[0])
        return 0
    if args.merge:
        table = merge(args, names)
    elif scale["jobs"] != 1 and len(names) > 1:
        table = run_parallel(args, names, scale)
    else:
        table = run_serial(args, names)
    print(markdown(table))
    if args.write_results is not None:
        command = merge_command_text(argv) if args.merge else command_line(argv)
        write_results(args.write_results, table, command=command)
        print(f"[genesis] wrote the section '{SECTION}' of {args.write_results}")
    return 0


def write_job_file(args: argparse.Namespace, names: list[str]) -> None:
    """One line per scene, ``gid_SCENE`` and its ``--part`` command, for
    benchmarks/device_queue.py. Paths are absolute: each job runs in its own snapshot of the
    checkout, and the rows must land in the one OUT (a recipe of the checkout stays relative,
    so that a job reads its snapshot's copy)."""
    script = Path(__file__).resolve()
    root = script.parents[1]
    recipe = args.recipe.resolve()
    if recipe.is_relative_to(root):
        recipe = recipe.relative_to(root)
    common = [
        f"--scenes {shlex.quote(str(args.scenes.resolve()))}",
        f"--out {shlex.quote(str(args.out.resolve()))}",
        f"--recipe {shlex.quote(str(recipe))}",
        *(f"--set {shlex.quote(item)}" for item in args.set),
    ]
    lines = [
        f"gid_{name} python3 {script.relative_to(root)} --only {name} --part " + " ".join(common)
        for name in names
    ]
    args.job_file.write_text("\n".join(lines) + "\n")
    print(
        f"[genesis] {len(lines)} jobs in {args.job_file}: python3 benchmarks/device_queue.py "
        f"start {args.job_file} --mps --slots 4 (MPS lets the jobs' kernels share a GPU: "
        "docs/BENCHMARKS.md, Several processes on one GPU)"
    )


def merge_command_text(argv: list[str]) -> str:
    """A merge's command as the results file gives it: the per-scene ``--part`` runs that made
    the rows, then the merge (the merge alone would not say how the rows were made)."""
    part_argv, skip = [], False
    for arg in argv:
        if skip:  # the value of --write-results given as a separate argument
            skip = False
        elif arg == "--merge":
            part_argv += ["--only", "SCENE", "--part"]
        elif arg.startswith("--write-results"):
            skip = "=" not in arg
        else:
            part_argv.append(arg)
    return f"{command_line(part_argv)}` for each scene, then `{command_line(argv)}"


if __name__ == "__main__":
    raise SystemExit(main())
