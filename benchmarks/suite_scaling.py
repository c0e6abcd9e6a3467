"""How a suite scales over the GPUs of one machine: the Genesis identification suite through Ray.

Runs the same identifications (every scene of a ``mosiv data suite`` folder, ``--repeats``
times each, one Ray task per run, ``--runs-per-gpu`` tasks sharing each GPU through Ray's GPU
fractions) once for each device count of ``--counts``, in one process and so on one machine:
for a count of N, the local Ray sees the first N GPUs (``CUDA_VISIBLE_DEVICES``). Each task is
one ``benchmarks/genesis_identify.py --part`` process, so a run is exactly a row of that
benchmark. Before the timed configurations, one untimed warm-up run per ``--warmup`` scene
compiles and caches the simulator's kernels, which every configuration would otherwise pay
for in its first tasks.

    python benchmarks/suite_scaling.py --scenes SCENES --out OUT --counts 4,1 \
        --set simulator.grid=32 --write-results docs/BENCHMARKS.md

Writes ``OUT/scaling.json`` (every task's time, attempts and row; resumable: a configuration
that finished is not run again), ``OUT/scaling.md`` and ``OUT/scaling.png``; with
``--write-results`` the section "A suite over several GPUs" of that markdown file (and the plot
into its ``img/`` folder). ``--unit cpu`` scales CPU worker slots instead (no GPU), which is
how CI runs it. The numbers are ``benchmarks/suite_scaling_report.py``'s.
"""

from __future__ import annotations

import argparse
import datetime
import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path

from genesis_identify import _portable, command_line, find_scenes
from genesis_identify_table import _fill, data_description, replace_section
from suite_scaling_report import agreement, markdown, plot, throughput

from mosiv_framework.scale import Task, run_command, run_tasks

SECTION = "A suite over several GPUs"
SECTION_BEFORE = "Determinism cost"
IDENTIFY = Path(__file__).resolve().parent / "genesis_identify.py"

#: the warm-up's overrides: every kernel of a run is compiled, in as few steps as possible
WARMUP_SETS = [
    "identify.velocity_iterations=1",
    "identify.param_iterations=1",
    "identify.contact_iterations=1",
    "identify.global_candidates=2",
    "identify.intervals=false",
]


def visible_devices(unit: str) -> list[str]:
    """The ids of the devices a configuration can use: the GPUs in ``CUDA_VISIBLE_DEVICES``
    (else every GPU torch sees), or for ``cpu`` one per CPU core."""
    if unit == "cpu":
        return [str(i) for i in range(os.cpu_count() or 1)]
    listed = os.environ.get("CUDA_VISIBLE_DEVICES")
    if listed is not None:
        return [d.strip() for d in listed.split(",") if d.strip()]
    import torch

    return [str(i) for i in range(torch.cuda.device_count())]


def parse_counts(text: str, available: int, unit: str) -> list[int]:
    """``--counts`` ("1,4", "all,1") as device counts in the order given (the configurations
    run in that order; the largest first ends its short run before the long one), each
    checked against ``available``, repeats dropped."""
    counts: list[int] = []
    for item in (t.strip() for t in text.split(",") if t.strip()):
        count = available if item == "all" else int(item) if item.isdigit() else None
        if count is None or count < 1:
            raise SystemExit(f"--counts {text!r}: {item!r} is not a positive count or 'all'")
        if count > available:
            raise SystemExit(
                f"--counts {text!r}: {count} {unit.upper()}s asked for, {available} visible "
                "(CUDA_VISIBLE_DEVICES or the machine's GPUs)"
            )
        if count not in counts:
            counts.append(count)
    if not counts:
        raise SystemExit(f"--counts {text!r}: name at least one count")
    return counts


def object_count(scene: Path) -> int:
    return len(json.loads((scene / "scene.json").read_text()).get("objects", []))


def planned_runs(root: Path, names: list[str], repeats: int) -> list[tuple[str, int]]:
    """``(scene, repeat)`` pairs, the scenes with most objects (the longest runs) first, so
    that no configuration ends waiting on a long run started last."""
    ordered = sorted(names, key=lambda n: (-object_count(root / n), names.index(n)))
    return [(name, r) for name in ordered for r in range(repeats)]


def gpu_fraction(runs_per_gpu: int) -> float:
    """``1 / runs_per_gpu`` rounded down to Ray's resolution (1e-4), so that that many fit."""
    return math.floor(10000 / runs_per_gpu) / 10000


def identify_command(args, scene: str, out: Path, sets: list[str]) -> list[str]:
    command = [sys.executable, str(IDENTIFY), "--scenes", str(args.scenes), "--only", scene]
    command += ["--out", str(out), "--recipe", str(args.recipe), "--part"]
    return command + [x for s in sets for x in ("--set", s)]


def warm_up(args, devices: list[str]) -> dict:
    """One untimed run per ``--warmup`` scene on the first device, one after another."""
    env = dict(os.environ)
    if args.unit == "gpu":
        env["CUDA_VISIBLE_DEVICES"] = devices[0]
    out, sets = args.out / "warmup", [*args.set, *WARMUP_SETS]
    started = time.perf_counter()
    for scene in args.warmup:
        print(f"[scaling] warm-up on {scene} (kernels compiled and cached)", flush=True)
        log = out / "parts" / f"{scene}.log"
        log.parent.mkdir(parents=True, exist_ok=True)
        with open(log, "ab") as sink:
            subprocess.run(
                identify_command(args, scene, out, sets),
                env=env,
                stdout=sink,
                stderr=subprocess.STDOUT,
                check=False,
            )
    return {"scenes": args.warmup, "seconds": time.perf_counter() - started}


def run_configuration(args, count: int, devices: list[str], runs: list[tuple[str, int]]) -> dict:
    """Every run of ``runs`` as a Ray task on ``count`` devices; its wall time and tasks."""
    label = f"{count}{args.unit}"
    root = args.out / "runs" / label
    slots = count * args.runs_per_gpu
    tasks = []
    for scene, r in runs:
        out = root / f"r{r}"
        (out / "parts").mkdir(parents=True, exist_ok=True)
        log = out / "parts" / f"{scene}.log"
        command = identify_command(args, scene, out, args.set)
        tasks.append(Task(f"{scene}.r{r}", run_command, (command,), log))
    # every configuration runs through Ray (none in this process), its concurrency set by
    # Ray's resources: a GPU fraction each, or for CPU slots a share of the local Ray's CPUs
    if args.unit == "gpu":  # the local Ray started by run_tasks sees these GPUs only
        os.environ["CUDA_VISIBLE_DEVICES"] = ",".join(devices[:count])
        gpus, cpus = gpu_fraction(args.runs_per_gpu), 1.0
    else:
        gpus, cpus = 0.0, (os.cpu_count() or 1) / slots
    done = []

    def progress(outcome):
        done.append(outcome.name)
        print(
            f"[scaling] {count} {args.unit.upper()}(s): {len(done)}/{len(tasks)} done, "
            f"{outcome.name} in {outcome.seconds:.0f} s",
            flush=True,
        )

    print(
        f"[scaling] {count} {args.unit.upper()}(s), {slots} runs at once: {len(tasks)} runs",
        flush=True,
    )
    started = time.perf_counter()
    outcomes = run_tasks(
        tasks,
        jobs=None,
        gpus_per_task=gpus,
        cpus_per_task=cpus,
        retries=args.retries,
        on_done=progress,
        ray_address=None,
    )
    wall = time.perf_counter() - started
    entries = []
    for (scene, r), task in zip(runs, tasks):
        outcome = outcomes[task.name]
        part = root / f"r{r}" / "parts" / f"{scene}.json"
        row = json.loads(part.read_text()) if part.is_file() else None
        ok = outcome.ok and outcome.result == 0 and row is not None and "error" not in row
        entries.append(
            {
                "name": task.name,
                "scene": scene,
                "repeat": r,
                "ok": ok,
                "seconds": outcome.seconds,
                "attempts": outcome.attempts,
                "row": row,
            }
        )
    return {
        "label": label,
        "count": count,
        "unit": args.unit,
        "slots": slots,
        "devices": devices[:count],
        "wall_s": wall,
        "tasks": entries,
    }


def settings_of(args, runs: list[tuple[str, int]]) -> dict:
    """What the configurations must share to be compared (a resumed run checks it)."""
    return {
        "runs": [list(r) for r in runs],
        "runs_per_gpu": args.runs_per_gpu,
        "unit": args.unit,
        "recipe": _portable(str(args.recipe)),
        "sets": args.set,
    }


def load_state(out: Path, settings: dict) -> dict:
    """``OUT/scaling.json`` of an earlier call with the same settings, else a fresh state;
    an ``OUT`` that holds something else is refused (it is not this benchmark's)."""
    state_file = out / "scaling.json"
    if state_file.is_file():
        state = json.loads(state_file.read_text())
        if state["settings"] != settings:
            differ = sorted(k for k in settings if state["settings"].get(k) != settings[k])
            raise SystemExit(
                f"--out {out}: its scaling.json was made with other settings "
                f"({', '.join(differ)}); use another --out"
            )
        return state
    if out.exists() and any(out.iterdir()):
        raise SystemExit(f"--out {out}: not empty and holds no scaling.json; use a new folder")
    return {"settings": settings, "configurations": {}}


def save_state(out: Path, state: dict) -> None:
    out.mkdir(parents=True, exist_ok=True)
    (out / "scaling.json").write_text(json.dumps(state, indent=1) + "\n")


def scene_rows(state: dict) -> list[dict]:
    """One successful row per scene (its first), for what the data were."""
    rows: dict[str, dict] = {}
    for config in state["configurations"].values():
        for task in config["tasks"]:
            row = task.get("row")
            if row and "error" not in row:
                rows.setdefault(task["scene"], row)
    return [rows[name] for name in sorted(rows)]


def make_report(state: dict) -> dict:
    """Throughput and agreement of the measured configurations, and a title naming the data
    and the card for the plot."""
    configs = state["configurations"]
    base = min(configs.values(), key=lambda c: c["count"])["label"]
    rows = scene_rows(state)
    devices = sorted({r.get("device", "unknown") for r in rows}) or ["unknown"]
    repeats = 1 + max(t["repeat"] for c in configs.values() for t in c["tasks"])
    title = f"{len(rows)} Genesis scenes x {repeats} runs each, {', '.join(devices)}"
    return {
        "throughput": throughput(configs),
        "agreement": agreement(configs, base),
        "base": base,
        "title": title,
    }


def section_text(state: dict, report: dict, *, command: str, plot_path: str | None) -> str:
    """The BENCHMARKS.md section: what ran, on what, the two tables and the plot."""
    tasks = [t for c in state["configurations"].values() for t in c["tasks"]]
    rows = scene_rows(state)
    devices = sorted({r.get("device", "unknown") for r in rows}) or ["unknown"]
    codes = sorted({t["row"].get("code", "unknown") for t in tasks if t.get("row")})
    largest = max(c["count"] for c in state["configurations"].values())
    repeats = 1 + max(t["repeat"] for t in tasks)
    intro = (
        "`benchmarks/suite_scaling.py` runs the Genesis identification suite "
        "(`benchmarks/genesis_identify.py`, one Ray task per run, a run being one scene "
        "identified and evaluated) once on each number of GPUs of one machine, in one process. "
        f"Each configuration identifies every scene {repeats} times; the repeats measure the "
        "run-to-run spread that the results of different GPU counts are compared against (a "
        "one-sided Mann-Whitney test on the symmetric relative differences, "
        "benchmarks/suite_scaling_report.py)."
    )
    warm = state.get("warmup") or {}
    items = [
        f"Command: `{command}` (the section is written from OUT/scaling.json by the same command "
        "with `--report --write-results docs/BENCHMARKS.md`, on any machine)",
        f"Machine: {largest} x {', '.join(devices)}. Date {state.get('date', 'unknown')}. "
        f"Code {', '.join(codes) or 'unknown'}.",
        f"Data: {data_description(rows)} ({', '.join(r['scene'] for r in rows)}); each run "
        f"`{state['settings']['recipe']}` with "
        f"{', '.join(state['settings']['sets']) or 'no overrides'}. Every task's time, "
        "attempts and row: `benchmarks/data/suite_scaling/scaling.json`.",
        f"Warm-up (untimed, kernels compiled): {', '.join(warm.get('scenes', [])) or 'none'}, "
        f"{warm.get('seconds', 0):.0f} s.",
    ]
    text = f"## {SECTION}\n\n{_fill(intro)}\n\n"
    text += "\n".join(_fill(i, initial_indent="- ", subsequent_indent="  ") for i in items)
    text += "\n\n" + markdown(report)
    if plot_path:
        text += f"\n![{report['title']}: scenes identified per hour against GPUs]({plot_path})\n"
    return text


def parse_args(argv: list[str]) -> argparse.Namespace:
    here = Path(__file__).resolve().parent
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", type=Path, required=True, help="a mosiv data suite folder")
    parser.add_argument("--only", default=None, help="comma-separated scene names")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--counts", default="all,1", help="device counts, e.g. 4,1 or all,2,1")
    parser.add_argument(
        "--unit",
        choices=("gpu", "cpu"),
        default="gpu",
        help="scale GPUs (default) or CPU worker slots (no GPU)",
    )
    parser.add_argument(
        "--runs-per-gpu",
        type=int,
        default=4,
        help="runs sharing one device at once (Ray GPU fraction 1/N)",
    )
    parser.add_argument("--repeats", type=int, default=2, help="runs of each scene (>= 2)")
    parser.add_argument(
        "--warmup",
        default=None,
        help="scenes of the untimed warm-up (default: the first planned; none)",
    )
    parser.add_argument(
        "--retries", type=int, default=2, help="re-runs of a task whose worker died"
    )
    parser.add_argument("--recipe", type=Path, default=here.parent / "recipes/genesis_oracle.yaml")
    parser.add_argument("--set", action="append", default=[], help="key=value recipe override")
    parser.add_argument("--write-results", type=Path, default=None, help="e.g. docs/BENCHMARKS.md")
    parser.add_argument(
        "--report",
        action="store_true",
        help="run nothing: the tables (and section) from OUT/scaling.json, e.g. "
        "on another machine than the one that measured",
    )
    args = parser.parse_args(argv)
    if args.repeats < 2:
        parser.error(f"--repeats {args.repeats}: at least 2 (the spread is measured from them)")
    if args.runs_per_gpu < 1:
        parser.error(f"--runs-per-gpu {args.runs_per_gpu}: at least 1")
    return args


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    args = parse_args(argv)
    if args.report:
        state_file = args.out / "scaling.json"
        if not state_file.is_file():
            raise SystemExit(f"--report: no {state_file}; measure first (without --report)")
        return write_report(args, json.loads(state_file.read_text()))
    devices = visible_devices(args.unit)
    counts = parse_counts(args.counts, len(devices), args.unit)
    runs = planned_runs(args.scenes, find_scenes(args.scenes, args.only), args.repeats)
    if args.warmup is None:
        args.warmup = [runs[0][0]]
    else:
        args.warmup = [] if args.warmup == "none" else [s for s in args.warmup.split(",") if s]
    state = load_state(args.out, settings_of(args, runs))
    state["command"] = command_line(argv, script="benchmarks/suite_scaling.py")
    state["date"] = datetime.date.today().isoformat()  # of the measurement, not of a --report
    if "warmup" not in state:
        state["warmup"] = warm_up(args, devices)
        save_state(args.out, state)
    for count in counts:
        label = f"{count}{args.unit}"
        if label in state["configurations"]:
            print(f"[scaling] {label}: measured earlier, kept", flush=True)
            continue
        state["configurations"][label] = run_configuration(args, count, devices, runs)
        save_state(args.out, state)
    return write_report(args, state)


def write_report(args, state: dict) -> int:
    """``OUT/scaling.md`` and ``OUT/scaling.png``, printed; with ``--write-results`` the
    section of that file and the plot in its ``img/`` folder."""
    report = make_report(state)
    (args.out / "scaling.md").write_text(markdown(report))
    plot(report, args.out / "scaling.png")
    print(markdown(report))
    if args.write_results is not None:
        image = args.write_results.parent / "img" / "suite_scaling.png"
        image.parent.mkdir(parents=True, exist_ok=True)
        plot(report, image)
        text = args.write_results.read_text() if args.write_results.is_file() else "# Benchmarks\n"
        body = section_text(
            state, report, command=state["command"], plot_path="img/suite_scaling.png"
        )
        args.write_results.write_text(
            replace_section(text, body, title=SECTION, before=SECTION_BEFORE)
        )
        print(f"[scaling] wrote the section '{SECTION}' of {args.write_results}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
