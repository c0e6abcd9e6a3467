"""Sensitivity to reconstruction noise on Genesis scenes: the Genesis mode of
``benchmarks/noise_suite.py`` (run through it, with ``--scenes`` or ``--merge``).

Every scene of a suite folder that ``mosiv data suite DIR --source genesis --ranges wide`` made
is identified as ``benchmarks/genesis_identify.py`` identifies it (its ``run_scene``; recipe
``recipes/genesis_oracle.yaml`` unless ``--recipe``: centre start, global search, the contact
chosen from the data, sandwich intervals), once without noise (the reference, alpha 0) and once
per noise kind and level of noise_suite: the oracle's points perturbed by Gaussian noise of
standard deviation alpha * (xyz_max - xyz_min) per object, i.i.d. per point or shared by an
object's points (the paper's levels 0.005, 0.02, 0.05 unless ``--levels``). Each (scene, noise
setting) runs in its own process (noise_suite.py with ``--part``; one after another, or
``--jobs N`` at once as Ray tasks), its row in ``OUT/parts/SCENE__SETTING.json``; the table
is always merged from those, so parts made on several machines merge into one.

    python benchmarks/noise_suite.py --scenes runs/genesis --out runs/genesis_noise \\
        --jobs 8 --gpus-per-task 0.125 --write-results docs/RESULTS.md
    python benchmarks/noise_suite.py --scenes runs/genesis --out runs/genesis_noise \\
        --only E-S --noise iid --alpha 0.02 --part     # one run per process on a device
    python benchmarks/noise_suite.py --out runs/genesis_noise --merge \\
        --write-results docs/RESULTS.md

``OUT`` holds ``study.json`` (the recipe and ``--set`` overrides; a non-empty folder without
it is refused, and so is a run with other settings), the runs in ``settings/SETTING/runs/SCENE``
(a rerun resumes their finished stages) and after the merge ``table.json``, ``table.md`` and
``noise.png``. ``--write-results FILE`` replaces the section "Sensitivity to reconstruction
noise on Genesis scenes" of FILE and copies the plot to ``img/genesis_noise.png`` beside it.
"""

from __future__ import annotations

import datetime
import json
import math
import os
import shutil
import statistics
import sys
import textwrap
from pathlib import Path

from genesis_identify import _fill, _portable, command_line, find_scenes, run_scene
from genesis_identify_table import (
    _median_stat,
    contact_label,
    data_description,
    replace_section,
    summarise,
)
from genesis_resolution import open_study, read_study
from identify_suite import _fmt
from noise_suite import KINDS, noise_overrides, plot, setting_name, settings

from mosiv_framework.scale import Task, run_command, run_tasks
from mosiv_framework.scale.flags import scale_options

HERE = Path(__file__).resolve().parent
#: the command the section names, and the script every --part process runs
SCRIPT = "benchmarks/noise_suite.py"
RECIPE = HERE.parent / "recipes" / "genesis_oracle.yaml"
#: what study.json holds for this benchmark (genesis_resolution's record format is another)
FORMAT = "mosiv-genesis-noise/1"
SECTION = "Sensitivity to reconstruction noise on Genesis scenes"
#: a new section goes before this one: after the own-synth noise section
SECTION_BEFORE = "Ablations"
IMAGE = "genesis_noise.png"
#: parameter errors pooled over a setting's objects: (key, parameter, family, column title);
#: family "elastic" takes elastic objects only, "other" every other family, None all
ERRORS = (
    ("E_elastic", "E", "elastic", "E % (elastic)"),
    ("E_other", "E", "other", "E % (P, S)"),
    ("yield_stress", "yield_stress", None, "yield %"),
    ("viscosity", "viscosity", None, "viscosity %"),
    ("friction_angle", "friction_angle", None, "friction angle deg"),
    ("initial_velocity", "initial_velocity", None, "v0 %"),
)
#: per-scene parameter columns: (parameter, title)
SCENE_PARAMS = (
    ("E", "E %"),
    ("yield_stress", "yield %"),
    ("viscosity", "viscosity %"),
    ("friction_angle", "friction angle deg"),
    ("initial_velocity", "v0 %"),
)
CD_KEYS = ("observed_cd_mm2", "observed_emd_mm", "future_cd_mm2", "future_emd_mm")


# --------------------------------------------------------------------------------------------
# one run (the --part process)


def run_setting(scene: Path, kind: str, alpha: float, *, recipe: Path, out: Path, sets) -> dict:
    """genesis_identify's row of ``scene`` identified with the noise ``kind`` at ``alpha`` (an
    ``error`` row when it fails), with the setting it ran."""
    name = setting_name(kind, alpha)
    noise = noise_overrides(kind, alpha)
    row = run_scene(scene, recipe=recipe, out=out / "settings" / name, sets=[*sets, *noise])
    return {**row, "kind": kind, "alpha": alpha, "setting": name, "noise_overrides": noise}


def part_path(out: Path, scene: str, kind: str, alpha: float) -> Path:
    return out / "parts" / f"{scene}__{setting_name(kind, alpha)}.json"


def write_part(path: Path, row: dict) -> None:
    """The row into its part file, whole or not at all (a merge may read it any time)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    partial = path.with_suffix(f".json.{os.getpid()}")
    partial.write_text(json.dumps(row, indent=2) + "\n")
    os.replace(partial, path)


def part_setting(args) -> tuple[str, float]:
    """(kind, alpha) of a ``--part`` run from ``--noise`` and ``--alpha``."""
    if args.noise is None or (args.noise != "none" and args.alpha is None):
        raise SystemExit("--part: give --noise none, or --noise iid|shared with --alpha A")
    alpha = 0.0 if args.alpha is None else args.alpha
    if (args.noise == "none") != (alpha == 0) or alpha < 0:
        raise SystemExit(
            f"--noise {args.noise} --alpha {alpha:g}: alpha is 0 without noise and > 0 with it"
        )
    return args.noise, alpha


def run_part(args, root: Path, name: str, kind: str, alpha: float) -> int:
    """One (scene, noise setting) in this process: its row into ``parts/``; 1 when it failed."""
    recipe = args.recipe or RECIPE
    row = run_setting(root / name, kind, alpha, recipe=recipe, out=args.out, sets=args.set)
    write_part(part_path(args.out, name, kind, alpha), row)
    return 1 if "error" in row else 0


# --------------------------------------------------------------------------------------------
# the suite: one process per (scene, setting), then the merge


def part_command(args, recipe: Path, scene: str, kind: str, alpha: float) -> list[str]:
    command = [sys.executable, str(HERE / "noise_suite.py"), "--scenes", str(args.scenes)]
    command += ["--only", scene, "--out", str(args.out), "--recipe", str(recipe)]
    command += ["--noise", kind, "--alpha", repr(alpha), "--part"]
    return command + [x for s in args.set for x in ("--set", s)]


def run_study(args, recipe: Path, names: list[str], scale: dict) -> None:
    """Every scene at every noise setting as a ``--part`` process; a process that died before
    writing its row gets an error row naming its log."""
    tasks, which = [], {}
    for name in names:
        for kind, alpha in settings(args.levels):
            part = part_path(args.out, name, kind, alpha)
            part.parent.mkdir(parents=True, exist_ok=True)
            part.unlink(missing_ok=True)  # no stale row of a crash
            log = part.with_suffix(".log")
            log.unlink(missing_ok=True)  # a Ray task appends to it
            command = part_command(args, recipe, name, kind, alpha)
            tasks.append(Task(part.stem, run_command, (command,), log))
            which[part.stem] = (name, kind, alpha, part)
    for task, outcome in run_tasks(tasks, **scale).items():
        code = outcome.result if outcome.ok else repr(outcome.error)
        print(f"[genesis-noise] {task}: {'done' if code == 0 else f'FAILED ({code})'}", flush=True)
        name, kind, alpha, part = which[task]
        if not part.is_file():
            row = {"scene": name, "kind": kind, "alpha": alpha}
            row |= {"setting": setting_name(kind, alpha), "error": f"no row (see parts/{task}.log)"}
            write_part(part, row)


def merge(out: Path) -> dict:
    """table.json, table.md and noise.png from every row under ``out/parts``."""
    record = read_study(out, FORMAT)
    rows = [json.loads(p.read_text()) for p in sorted((out / "parts").glob("*.json"))]
    if not rows:
        raise SystemExit(f"--merge: no rows under {out / 'parts'}; run the suite first")
    table = make_table(rows, record)
    (out / "table.json").write_text(json.dumps(table, indent=2) + "\n")
    (out / "table.md").write_text(markdown(table))
    plot(plot_rows(table), out / "noise.png", data=plot_data(table))
    return table


def _sources(rows: list[dict]) -> tuple[list[dict], list[str]]:
    """(one row per scene, preferring one that says where the scene came from (an error row
    of a dead process does not); the devices the runs used)."""
    one_per_scene = list({r["scene"]: r for r in sorted(rows, key=lambda r: "data" in r)}.values())
    return one_per_scene, sorted({r["device"] for r in rows if _ok(r) and r.get("device")})


def plot_data(table: dict) -> str:
    """The plot's data line: the scenes, where they come from, the machine and the settings."""
    record = table.get("study") or {}
    one_per_scene, devices = _sources(table["rows"])
    scenes = ", ".join(sorted(r["scene"] for r in one_per_scene))
    sets = " ".join(record.get("overrides") or []) or "no overrides"
    text = (
        f"Genesis scenes {scenes}: {data_description(one_per_scene)}; "
        f"{record.get('recipe', 'unknown recipe')} with {sets}; {', '.join(devices) or '?'}"
    )
    return textwrap.fill(text, 120, break_long_words=False, break_on_hyphens=False)


# --------------------------------------------------------------------------------------------
# the table


def _order(kind: str, alpha: float) -> tuple:
    """The reference first, then each kind by level (noise_suite's order)."""
    return (kind != "none", kind, alpha)


def _ok(row: dict) -> bool:
    return "error" not in row


def pooled(rows: list[dict], key: str) -> list[float]:
    """The errors of ``key`` (of ERRORS) over every object of the rows that ran."""
    _, param, family, _ = next(e for e in ERRORS if e[0] == key)
    out = []
    for r in filter(_ok, rows):
        for obj in r["objects"].values():
            p = obj["params"].get(param)
            elastic = obj.get("family") == "elastic"
            wanted = family is None or (family == "elastic") == elastic
            if wanted and p is not None and p["error"] is not None:
                out.append(p["error"])
    return out


def _mean(values: list) -> float | None:
    values = [v for v in values if v is not None]
    return statistics.fmean(values) if values else None


def future_ratio(row: dict, reference: dict[str, dict]) -> float | None:
    """The row's future CD over its scene's reference run's (None where either is missing)."""
    ref = reference.get(row["scene"])
    if not _ok(row) or ref is None or row.get("future_cd_mm2") is None:
        return None
    base = ref.get("future_cd_mm2")
    return row["future_cd_mm2"] / base if base else None


def summarise_setting(rows: list[dict], reference: dict[str, dict]) -> dict:
    """One noise setting over its scenes: the mean CD and EMD, the median over scenes of the
    future CD relative to the same scene's reference, the median of each parameter error
    pooled over the objects, genesis_identify's interval coverage and contact counts, and the
    longest wall time."""
    good = [r for r in rows if _ok(r)]
    stats = summarise(rows)
    ratios = [x for x in (future_ratio(r, reference) for r in good) if x is not None]
    out = {"kind": rows[0]["kind"], "alpha": rows[0]["alpha"], "setting": rows[0]["setting"]}
    out |= {"scenes": len(good), "failed": [r["scene"] for r in rows if not _ok(r)]}
    out |= {key: _mean([r.get(key) for r in good]) for key in CD_KEYS}
    out["future_cd_ratio"] = _median_stat(ratios)
    out["errors"] = {key: _median_stat(pooled(rows, key)) for key, *_ in ERRORS}
    out["coverage"] = stats["coverage"]
    out["contact"] = stats["contact"]
    out["time_s"] = max((r["time_s"] for r in good), default=None)
    return out


def make_table(rows: list[dict], record: dict) -> dict:
    """What table.json holds: the study record, the rows by scene and setting, and per
    setting its summary."""
    ordered = sorted(rows, key=lambda r: (r["scene"], _order(r["kind"], r["alpha"])))
    reference = {r["scene"]: r for r in ordered if r["kind"] == "none" and _ok(r)}
    keys = sorted({(r["kind"], r["alpha"]) for r in rows}, key=lambda k: _order(*k))
    summary = [
        summarise_setting([r for r in ordered if (r["kind"], r["alpha"]) == key], reference)
        for key in keys
    ]
    return {"study": record, "rows": ordered, "settings": summary}


def plot_rows(table: dict) -> list[dict]:
    """noise_suite.plot's rows: per setting, the mean future CD and the elastic E errors."""
    out = []
    for s in table["settings"]:
        if s["scenes"]:
            future = s["future_cd_mm2"]
            rows = [r for r in table["rows"] if r["setting"] == s["setting"]]
            out.append(
                {
                    "kind": s["kind"],
                    "alpha": s["alpha"],
                    "future_cd_mm2": math.nan if future is None else future,
                    "E_pct": pooled(rows, "E_elastic"),
                }
            )
    return out


# --------------------------------------------------------------------------------------------
# markdown and docs/RESULTS.md


def _used(table: dict) -> list[tuple[str, str]]:
    """ERRORS with a value in some setting: (key, title)."""
    return [
        (key, title)
        for key, *_, title in ERRORS
        if any(s["errors"][key]["n"] for s in table["settings"])
    ]


def settings_table(table: dict) -> list[str]:
    used = _used(table)
    head = ["noise", "alpha", "scenes", "observed CD mm^2", "future CD mm^2"]
    head += ["future CD / reference"] + [t for _, t in used]
    head += ["intervals holding the truth", "contact", "longest time s"]
    lines = ["| " + " | ".join(head) + " |", "|---" * len(head) + "|"]
    for s in table["settings"]:
        cover = s["coverage"]
        cells = [s["kind"], f"{s['alpha']:g}", f"{s['scenes']}"]
        cells += [_fmt(s["observed_cd_mm2"]), _fmt(s["future_cd_mm2"])]
        cells += [_fmt(s["future_cd_ratio"]["value"])]
        cells += [_fmt(s["errors"][key]["value"]) for key, _ in used]
        share = (
            f"{_fmt(cover['value'])} % ({cover['count']} of {cover['n']})" if cover["n"] else "-"
        )
        contact = ", ".join(f"{k} {v}" for k, v in s["contact"].items()) or "-"
        cells += [share, contact, _fmt(s["time_s"])]
        lines.append("| " + " | ".join(cells) + " |")
    return lines


def _objects_cell(row: dict, param: str) -> str:
    """The parameter's error of each object that has it, in object order."""
    values = [o["params"][param]["error"] for o in row["objects"].values() if param in o["params"]]
    return " / ".join(_fmt(v) for v in values) if values else "-"


def scene_table(table: dict) -> list[str]:
    rows = table["rows"]
    used = [
        (p, t)
        for p, t in SCENE_PARAMS
        if any(p in o["params"] for r in rows if _ok(r) for o in r["objects"].values())
    ]
    reference = {r["scene"]: r for r in rows if r["kind"] == "none" and _ok(r)}
    head = ["scene", "noise", "alpha", "contact", "observed CD mm^2", "future CD mm^2"]
    head += ["future CD / reference"] + [t for _, t in used] + ["time s"]
    lines = ["| " + " | ".join(head) + " |", "|---" * len(head) + "|"]
    for r in rows:
        cells = [r["scene"], r["kind"], f"{r['alpha']:g}"]
        if not _ok(r):
            lines.append("| " + " | ".join(cells) + f" | failed: {r['error']} |")
            continue
        cells += [contact_label(r), _fmt(r["observed_cd_mm2"]), _fmt(r["future_cd_mm2"])]
        cells += [_fmt(future_ratio(r, reference))]
        cells += [_objects_cell(r, p) for p, _ in used] + [_fmt(r["time_s"])]
        lines.append("| " + " | ".join(cells) + " |")
    return lines


NOTES = (
    "Per noise setting: CD and EMD are means over the scenes; future CD / reference is the "
    "median over scenes of each scene's future CD over its own noise-free run's; parameter "
    "errors are medians over the objects of every scene (E, yield stress and viscosity "
    "gauge-free, %; friction angle absolute, deg; v0 |v - v_true| / |v_true|, %); the interval "
    "coverage and the contact counts are as in the section on identification on Genesis scenes. "
    "Per scene, a parameter column lists each object's error in object order."
)


def markdown(table: dict, *, plot_link: str | None = None) -> str:
    lines = [*settings_table(table), "", *scene_table(table), "", _fill(NOTES)]
    failed = [f"{r['scene']} {r['setting']}" for r in table["rows"] if not _ok(r)]
    if failed:
        lines += ["", f"Failed runs: {', '.join(failed)}."]
    if plot_link:
        lines += ["", f"![noise on Genesis scenes]({plot_link})"]
    return "\n".join(lines) + "\n"


def section_text(table: dict, *, command: str, date: str) -> str:
    """The RESULTS.md section: what was run, on what, and the tables."""
    rows, record = table["rows"], table.get("study") or {}
    one_per_scene, devices = _sources(rows)
    codes = sorted({r["code"] for r in rows if r.get("code")})
    levels = sorted({r["alpha"] for r in rows if r["kind"] != "none"})
    kinds = [k for k in KINDS if any(r["kind"] == k for r in rows)]
    sets = " ".join(f"--set {s}" for s in record.get("overrides") or []) or "none"
    intro = (
        f"`{SCRIPT} --scenes` adds the noise of the section above to the oracle's points of "
        "scenes the Genesis engine made and identifies each scene as `benchmarks/"
        "genesis_identify.py` does, once without noise (alpha 0, the reference) and once per "
        "noise kind and level, each run in its own process."
    )
    items = [
        f"Command: `{command}`",
        f"Recipe: `{record.get('recipe', 'unknown')}`; overrides of every run: `{sets}`.",
        f"Noise: {', '.join(kinds) or 'none'} at alpha {', '.join(f'{a:g}' for a in levels)}.",
        f"Machine: {', '.join(devices) or 'unknown'}. Date {date}. "
        f"Code {', '.join(codes) or 'unknown'}.",
        f"Data: {data_description(one_per_scene)} (`mosiv data suite SCENES --source genesis`): "
        f"{', '.join(sorted(r['scene'] for r in one_per_scene))}.",
    ]
    wrapped = [_fill(i, initial_indent="- ", subsequent_indent="  ") for i in items]
    body = markdown(table, plot_link=f"img/{IMAGE}")
    return f"## {SECTION}\n\n{_fill(intro)}\n\n" + "\n".join(wrapped) + "\n\n" + body


def write_results(path: Path, table: dict, *, command: str, png: Path) -> None:
    """Replace (or add, before the Ablations) the section in ``path``; the plot goes to
    ``img/`` beside it."""
    image = path.parent / "img" / IMAGE
    image.parent.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(png, image)
    body = section_text(table, command=command, date=datetime.date.today().isoformat())
    text = path.read_text() if path.is_file() else "# Results\n"
    path.write_text(replace_section(text, body, title=SECTION, before=SECTION_BEFORE))


# --------------------------------------------------------------------------------------------
# noise_suite.py's Genesis mode


def run(args, argv: list[str]) -> int:
    """noise_suite.main with ``--scenes`` or ``--merge`` (``args`` its parsed flags)."""
    if args.part and (args.merge or args.write_results is not None):
        raise SystemExit("--part runs one setting: no --merge or --write-results with it")
    if (args.noise is not None or args.alpha is not None) and not args.part:
        raise SystemExit("--noise and --alpha choose the one setting of a --part run")
    if args.merge:
        table = merge(args.out)
    else:
        recipe = args.recipe or RECIPE
        names = find_scenes(args.scenes, args.only)
        record = {"format": FORMAT, "recipe": _portable(str(recipe)), "overrides": args.set}
        if args.part:
            if len(names) != 1:
                raise SystemExit(f"--part runs one scene: give --only one of {', '.join(names)}")
            kind, alpha = part_setting(args)
            open_study(args.out, record)
            return run_part(args, args.scenes, names[0], kind, alpha)
        scale = scale_options(args)
        open_study(args.out, record)
        run_study(args, recipe, names, scale)
        table = merge(args.out)
    print(markdown(table))
    if args.write_results is not None:
        command = command_line(argv, script=SCRIPT)
        write_results(args.write_results, table, command=command, png=args.out / "noise.png")
        print(f"[genesis-noise] wrote the section '{SECTION}' of {args.write_results}")
    return 0
