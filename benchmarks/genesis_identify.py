"""Identification on scenes another engine simulated: the Genesis oracle benchmark.

Runs one recipe (default ``recipes/genesis_oracle.yaml``: oracle reconstructor, gt-points
lifter, warp-mpm, a data-independent start and a global search before gradient descent) on
every scene of a suite folder that ``mosiv data suite OUT --source genesis --ranges wide``
made, and tabulates per scene and object the raw and gauge-free errors of every parameter,
whether its 95 % interval holds the truth and what kind of interval it is, the observed and
future Chamfer (CD) and earth mover's distance (EMD), wall time and peak memory; then the
suite against its targets. warp-mpm is not the engine that made these scenes, so unlike
``benchmarks/identify_suite.py`` the model is not exact here.

    python benchmarks/genesis_identify.py --scenes runs/genesis --out runs/genesis_identify
    python benchmarks/genesis_identify.py --scenes runs/genesis --out runs/genesis_identify \
        --jobs 13 --gpus-per-task 0.07 --write-results docs/RESULTS.md
    python benchmarks/genesis_identify.py --scenes runs/genesis --only E-S \
        --out runs/genesis-cpu --set simulator.device=cpu --set simulator.grid=32

Writes ``OUT/table.json`` and ``OUT/table.md`` (a rerun into the same folder resumes finished
stages and keeps the rows of scenes it does not run); ``--write-results`` replaces the section
"Identification on Genesis scenes" of that markdown file with the table, the command, the
machine, the date, the code version and the data. With ``--jobs N`` each scene runs as a Ray
task in its own process (output in ``OUT/parts/SCENE.log``), as in identify_suite.
"""

from __future__ import annotations

import argparse
import datetime
import json
import math
import re
import shlex
import statistics
import sys
import textwrap
import time
import traceback
from pathlib import Path

from identify_suite import _fmt, _run_part, _timed, code_version

from mosiv_framework.scale import Task, run_tasks
from mosiv_framework.scale.flags import add_scale_flags, scale_options

#: the section of docs/RESULTS.md this benchmark owns
SECTION = "Identification on Genesis scenes"
#: a new section goes before this one (the file's order: oracle, then video results)
SECTION_BEFORE = "From video"
#: parameters in table order: (metrics name, column title)
PARAMS = (
    ("E", "E %"),
    ("nu", "nu %"),
    ("rho", "rho %"),
    ("yield_stress", "yield %"),
    ("viscosity", "viscosity %"),
    ("bulk_modulus", "bulk modulus %"),
    ("friction_angle", "friction angle deg"),
    ("friction", "friction %"),
    ("initial_velocity", "v0 %"),
)
#: interval kinds, as the table abbreviates them
KINDS = {"two-sided": "2s", "lower-bound": ">=", "upper-bound": "<=", "unconstrained": "free"}
#: the suite's targets: (key, title, comparison, target, unit)
TARGETS = (
    ("E_finite", "median E error, objects with a two-sided E interval", "<=", 20.0, "%"),
    ("E_within_50", "share of objects with E error <= 50 %", ">=", 90.0, "%"),
    ("E_not_finite", "share of E intervals not two-sided", "<=", 25.0, "%"),
    ("yield_stress", "median yield stress error", "<=", 30.0, "%"),
    ("friction_angle", "median friction angle error", "<=", 5.0, "deg"),
    ("viscosity", "median viscosity error", "<=", 30.0, "%"),
    ("initial_velocity", "median v0 error", "<=", 5.0, "%"),
    ("coverage", "95 % intervals holding the truth", ">=", 90.0, "%"),
    ("future_cd", "mean future CD", "<=", 450.0, "mm^2"),
    ("time", "longest wall time per scene", "<", 600.0, "s"),
)


# --------------------------------------------------------------------------------------------
# per-scene rows (pure functions of metrics.json)


def object_entries(metrics: dict) -> dict[str, dict]:
    """Per object of ``metrics`` (a run's metrics.json): its family and, per parameter, the
    errors and the 95 % interval's kind and coverage.

    Each parameter entry has ``raw`` (relative error %, or None), ``gauge_free`` (% after the
    density gauge, for densities and stresses), ``deg`` (friction angle, absolute), ``error``
    (what the targets use: gauge-free, else degrees, else raw), ``kind`` (of the interval, None
    without one), ``covered`` (None without truth or interval), ``value`` (as identified; a
    density or stress in the truth's gauge, the value its gauge-free error compares) and
    ``true`` (None without truth). Coverage of a density or stress is judged in the gauge
    too: the interval is of the identified value, which holds the first object's density at
    its assumed value, so it is rescaled by true / assumed density of that object before it
    is compared with the truth.
    """
    errors = metrics.get("param_error") or {}
    identified = metrics.get("params") or {}
    intervals = identified.get("intervals") or {}
    gauge = _gauge(errors)
    out: dict[str, dict] = {}
    for k, obj in (identified.get("objects") or {}).items():
        truth = errors.get(str(k), {})
        names = [n for n, _ in PARAMS if n in truth or n in intervals.get(f"obj{k}", {})]
        params = {}
        for name in names:
            err, interval = truth.get(name), intervals.get(f"obj{k}", {}).get(name)
            params[name] = _param_entry(err, interval, gauge)
        out[str(k)] = {"family": obj.get("family"), "params": params}
    return out


def _gauge(errors: dict) -> float | None:
    """True / assumed density of the gauge object (the lowest id), None if unknown."""
    if not errors:
        return None
    rho = errors[min(errors, key=int)].get("rho")
    if not rho or not rho.get("value"):
        return None
    return float(rho["true"]) / float(rho["value"])


def _param_entry(err: dict | None, interval: dict | None, gauge: float | None) -> dict:
    entry = {"raw": None, "gauge_free": None, "deg": None, "error": None}
    entry["kind"] = interval.get("kind") if interval else None
    entry["covered"] = entry["value"] = entry["true"] = None
    if err is None:
        return entry
    if "abs_error_deg" in err:
        entry["deg"] = entry["error"] = float(err["abs_error_deg"])
    else:
        entry["raw"] = 100.0 * float(err["rel_error"])
        if "rel_error_gauge_free" in err:
            entry["gauge_free"] = 100.0 * float(err["rel_error_gauge_free"])
        entry["error"] = entry["raw"] if entry["gauge_free"] is None else entry["gauge_free"]
    scale = gauge if (entry["gauge_free"] is not None and gauge) else 1.0
    value = err.get("value")
    entry["value"] = value * scale if isinstance(value, (int, float)) else value
    entry["true"] = err.get("true")
    if interval is not None and isinstance(err.get("true"), (int, float)):
        low, high = interval.get("low"), interval.get("high")
        true = float(err["true"])
        entry["covered"] = (low is None or true >= low * scale) and (
            high is None or true <= high * scale
        )
    return entry


def scene_row(
    name: str, metrics: dict, *, time_s: float, data: dict, device: str, code: str
) -> dict:
    """One table row: the scene's objects (``object_entries``), its CD and EMD over the
    observed and future frames, wall time and peak memory, and where it came from."""
    future = metrics.get("future") or {}
    return {
        "scene": name,
        "objects": object_entries(metrics),
        "observed_cd_mm2": metrics["observed"]["cd_mm2"],
        "observed_emd_mm": metrics["observed"]["emd_mm"],
        "future_cd_mm2": future.get("cd_mm2"),
        "future_emd_mm": future.get("emd_mm"),
        "time_s": time_s,
        "peak_memory_gb": metrics.get("peak_memory_gb"),
        "data": data,
        "device": device,
        "code": code,
    }


# --------------------------------------------------------------------------------------------
# the suite against its targets


def summarise(rows: list[dict]) -> dict:
    """Every quantity of ``TARGETS`` over the rows that ran (failed rows are listed apart):
    ``{key: {"value", "n", "target", "op", "met", ...}}`` plus ``scenes`` and ``failed``.

    The E statistics pool every object with an E (elastic, plasticine, sand); the interval
    coverage counts the intervals that claim something (unconstrained ones hold any value and
    are counted apart, ``unconstrained``), over parameters with a known truth.
    """
    good = [r for r in rows if "error" not in r]
    entries = [
        (name, p)
        for r in good
        for obj in r["objects"].values()
        for name, p in obj["params"].items()
    ]
    e = [p for name, p in entries if name == "E" and p["error"] is not None]
    e_kinds = [p["kind"] for p in e if p["kind"] is not None]
    finite = [p["error"] for p in e if p["kind"] == "two-sided"]
    claims = [p for _, p in entries if p["covered"] is not None and p["kind"] != "unconstrained"]
    out: dict = {"scenes": len(rows), "failed": [r["scene"] for r in rows if "error" in r]}
    out["E_finite"] = _median_stat(finite)
    out["E_within_50"] = _share([p["error"] <= 50.0 for p in e])
    out["E_not_finite"] = _share([k != "two-sided" for k in e_kinds])
    out["E_not_finite"]["one_sided"] = sum(k in ("lower-bound", "upper-bound") for k in e_kinds)
    for key in ("yield_stress", "friction_angle", "viscosity", "initial_velocity"):
        out[key] = _median_stat(
            [p["error"] for n, p in entries if n == key and p["error"] is not None]
        )
    out["coverage"] = _share([bool(p["covered"]) for p in claims])
    out["coverage"]["unconstrained"] = sum(
        p["kind"] == "unconstrained" and p["covered"] is not None for _, p in entries
    )
    futures = [r["future_cd_mm2"] for r in good if r["future_cd_mm2"] is not None]
    out["future_cd"] = {"value": statistics.fmean(futures) if futures else None, "n": len(futures)}
    times = [r["time_s"] for r in good]
    out["time"] = {"value": max(times) if times else None, "n": len(times)}
    for key, _title, op, target, _unit in TARGETS:
        stat = out[key]
        stat.update(op=op, target=target, met=_meets(stat["value"], op, target))
    return out


def _median_stat(values: list[float]) -> dict:
    if not values:
        return {"value": None, "n": 0, "worst": None}
    return {"value": statistics.median(values), "n": len(values), "worst": max(values)}


def _share(flags: list[bool]) -> dict:
    """Percentage of true ``flags`` (None when there are none) and the counts."""
    n = len(flags)
    return {"value": 100.0 * sum(flags) / n if n else None, "n": n, "count": sum(flags)}


def _meets(value: float | None, op: str, target: float) -> bool | None:
    if value is None or not math.isfinite(value):
        return None
    return {"<=": value <= target, ">=": value >= target, "<": value < target}[op]


def make_table(rows: list[dict]) -> dict:
    """The rows ordered by scene name with their summary: what table.json holds."""
    ordered = sorted(rows, key=lambda r: r["scene"])
    return {"rows": ordered, "summary": summarise(ordered)}


# --------------------------------------------------------------------------------------------
# markdown


def _cell(p: dict | None) -> str:
    """One parameter of one object: gauge-free / raw error (or degrees, or raw), then the
    interval's kind and whether it holds the truth."""
    if p is None:
        return "-"
    if p["deg"] is not None:
        text = _fmt(p["deg"])
    elif p["gauge_free"] is not None:
        text = f"{_fmt(p['gauge_free'])} / {_fmt(p['raw'])}"
    else:
        text = _fmt(p["raw"])
    if p["kind"] is not None:
        mark = "" if p["covered"] is None else (" in" if p["covered"] else " out")
        text += f" [{KINDS.get(p['kind'], p['kind'])}{mark}]"
    return text


def markdown(table: dict) -> str:
    """Per object errors, per scene CD/EMD/time/memory, and the summary against the targets."""
    rows, summary = table["rows"], table["summary"]
    used = [
        (n, title)
        for n, title in PARAMS
        if any(n in o["params"] for r in rows if "error" not in r for o in r["objects"].values())
    ]
    lines = ["| scene | object | " + " | ".join(t for _, t in used) + " |"]
    lines.append("|---" * (len(used) + 2) + "|")
    for r in rows:
        if "error" in r:
            lines.append(f"| {r['scene']} | failed: {r['error']} |" + " |" * len(used))
            continue
        for k, obj in r["objects"].items():
            cells = [_cell(obj["params"].get(n)) for n, _ in used]
            lines.append(f"| {r['scene']} | {k} {obj['family']} | " + " | ".join(cells) + " |")
    lines += [
        "",
        "Errors of densities and stresses: gauge-free / raw (%); friction angle: absolute (deg);"
        " v0: |v - v_true| / |v_true| (%). [2s] two-sided 95 % interval, [>=] lower bound only,"
        " [<=] upper bound only, [free] unconstrained; in / out: the interval holds / misses the"
        " truth (densities and stresses after the density gauge).",
        "",
        "| scene | observed CD mm^2 | observed EMD mm | future CD mm^2 | future EMD mm | time s"
        " | peak memory GB |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        if "error" in r:
            continue
        values = [r[key] for key in _SCENE_COLUMNS]
        lines.append(f"| {r['scene']} | " + " | ".join(_fmt(v) for v in values) + " |")
    lines += ["", "| quantity | n | value | target | status |", "|---|---|---|---|---|"]
    for key, title, op, target, unit in TARGETS:
        lines.append(_summary_line(title, summary[key], f"{op} {target:g} {unit}", unit))
    extra = [
        f"E intervals one-sided: {summary['E_not_finite'].get('one_sided', 0)}",
        f"unconstrained intervals (not counted in the coverage): "
        f"{summary['coverage'].get('unconstrained', 0)}",
    ]
    lines.append("\n" + "; ".join(extra) + ".")
    if summary["failed"]:
        lines.append(f"\nfailed scenes: {', '.join(summary['failed'])}")
    return "\n".join(lines) + "\n"


_SCENE_COLUMNS = (
    "observed_cd_mm2",
    "observed_emd_mm",
    "future_cd_mm2",
    "future_emd_mm",
    "time_s",
    "peak_memory_gb",
)


def _summary_line(title: str, s: dict, target: str, unit: str) -> str:
    if s["n"] == 0 or s["value"] is None:
        status, value = "not measured", "-"
    else:
        status = {True: "met", False: "not met", None: "-"}[s["met"]]
        value = f"{_fmt(s['value'])} {unit}"
        if "count" in s:
            value += f" ({s['count']} of {s['n']})"
        elif s.get("worst") is not None:
            value += f" (worst {_fmt(s['worst'])})"
    return f"| {title} | {s['n']} | {value} | {target} | {status} |"


# --------------------------------------------------------------------------------------------
# docs/RESULTS.md


def data_description(rows: list[dict]) -> str:
    """What the scenes are, from the rows' ``data`` (each scene's gt/params.json): engine and
    version, parameter ranges and seeds."""
    data = [r["data"] for r in rows if r.get("data")]
    engines = sorted({_engine(d.get("generator", "")) for d in data})
    ranges = sorted({str(d.get("ranges")) for d in data})
    seeds = sorted({int(d["seed"]) for d in data if d.get("seed") is not None})
    return (
        f"{len(rows)} scene{'s' if len(rows) != 1 else ''} made by the Genesis engine ({', '.join(engines) or 'unknown'}), "
        f"{', '.join(ranges) or 'unknown'} ranges, seeds {_spans(seeds) or 'unknown'}"
    )


def _engine(generator: str) -> str:
    """'mosiv-genesis (Genesis 1.4.5, MPM, cpu)' -> 'genesis-world 1.4.5, cpu backend'."""
    found = re.search(r"Genesis ([^,)]+)(?:, [^,)]+)?(?:, ([^,)]+))?", generator)
    if not found:
        return generator or "unknown"
    backend = f", {found.group(2)} backend" if found.group(2) else ""
    return f"genesis-world {found.group(1)}{backend}"


def _spans(values: list[int]) -> str:
    """[0, 1, 2, 5] -> '0-2, 5'."""
    spans: list[list[int]] = []
    for v in values:
        if spans and v == spans[-1][1] + 1:
            spans[-1][1] = v
        else:
            spans.append([v, v])
    return ", ".join(str(a) if a == b else f"{a}-{b}" for a, b in spans)


def section_text(table: dict, *, command: str, date: str) -> str:
    """The RESULTS.md section: what was run, on what, and the table."""
    rows = table["rows"]
    devices = sorted({r.get("device", "unknown") for r in rows if "error" not in r})
    codes = sorted({r.get("code", "unknown") for r in rows})
    intro = (
        "`benchmarks/genesis_identify.py` runs `recipes/genesis_oracle.yaml` (oracle "
        "reconstructor, gt-points lifter, warp-mpm, the paper's loss and iterations, a start at "
        "the centre of each law's bounds and a global search before gradient descent) on scenes "
        "that another engine simulated, so the model no longer matches the data exactly."
    )
    items = [
        f"Command: `{command}`",
        f"Machine: {', '.join(devices) or 'unknown'}. Date {date}. Code {', '.join(codes)}.",
        f"Data: {data_description(rows)}.",
    ]
    wrapped = [_fill(i, initial_indent="- ", subsequent_indent="  ") for i in items]
    return f"## {SECTION}\n\n{_fill(intro)}\n\n" + "\n".join(wrapped) + "\n\n" + markdown(table)


def _fill(text: str, **indents) -> str:
    """``text`` wrapped at 100 columns, never inside a word or a hyphenated name (E-P-S)."""
    return textwrap.fill(text, 100, break_long_words=False, break_on_hyphens=False, **indents)


def replace_section(
    text: str, body: str, *, title: str = SECTION, before: str = SECTION_BEFORE
) -> str:
    """``text`` with its ``## title`` section (up to the next level-2 heading) replaced by
    ``body``; a missing section goes before ``## before``, else at the end."""
    lines = text.splitlines(keepends=True)
    heads = [i for i, line in enumerate(lines) if line.startswith("## ")]
    body = body.rstrip("\n") + "\n\n"
    start = next((i for i in heads if lines[i].strip() == f"## {title}"), None)
    if start is None:
        at = next((i for i in heads if lines[i].strip() == f"## {before}"), None)
        if at is None:
            return text.rstrip("\n") + "\n\n" + body.rstrip("\n") + "\n"
        return "".join(lines[:at]) + body + "".join(lines[at:])
    end = next((i for i in heads if i > start), len(lines))
    if end == len(lines):
        body = body.rstrip("\n") + "\n"
    return "".join(lines[:start]) + body + "".join(lines[end:])


def write_results(path: Path, table: dict, *, command: str) -> None:
    date = datetime.date.today().isoformat()
    text = path.read_text() if path.is_file() else "# Results\n"
    path.write_text(replace_section(text, section_text(table, command=command, date=date)))


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
    )


def _earlier(out: Path) -> dict[str, dict]:
    table = out / "table.json"
    return {r["scene"]: r for r in json.loads(table.read_text())["rows"]} if table.is_file() else {}


def save_table(out: Path, rows: dict[str, dict], *, recipe: Path, sets: list[str]) -> dict:
    table = {"recipe": str(recipe), "overrides": sets, **make_table(list(rows.values()))}
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
        tasks.append(Task(name, _run_part, (command,), parts / f"{name}.log"))
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
    parser.add_argument("--part", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    scale = scale_options(args)
    names = find_scenes(args.scenes, args.only)
    (args.out / "parts").mkdir(parents=True, exist_ok=True)
    if args.part:
        run_part(args, names[0])
        return 0
    if scale["jobs"] != 1 and len(names) > 1:
        table = run_parallel(args, names, scale)
    else:
        table = run_serial(args, names)
    print(markdown(table))
    if args.write_results is not None:
        write_results(args.write_results, table, command=command_line(argv))
        print(f"[genesis] wrote the section '{SECTION}' of {args.write_results}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
