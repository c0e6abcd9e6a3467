"""The tables of ``benchmarks/genesis_identify.py``: per-scene rows from a run's metrics.json,
the suite's summary against its targets, the markdown of ``OUT/table.md`` and the section
"Identification on Genesis scenes" of docs/RESULTS.md. Pure functions of the rows, so the
committed rows (``benchmarks/data/genesis_identify/``) render without running anything.
"""

from __future__ import annotations

import datetime
import math
import re
import statistics
import textwrap
from pathlib import Path

from identify_suite_table import _fmt

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
