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
from pathlib import Path

import results_sections
from identify_suite_table import _fmt
from results_sections import KEEP_MARKER, _fill  # noqa: F401 (re-exported)

from mosiv_framework.pipeline.uncertainty import INTERVALS_PHASE

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
#: interval methods (identify.interval_method), as the table abbreviates them
METHODS = {"sandwich": "sw", "laplace": "lap"}
#: the contact of a row made before rows recorded it: every such run identified with the
#: recipe's fixed simulator.contact, which recipes/genesis_oracle.yaml left at multi_field
UNRECORDED_CONTACT = {"choice": "fixed", "mode": "multi_field"}
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
#: the coverage target for the Laplace intervals of the same runs, shown where rows hold them
LAPLACE_TARGET = (
    "coverage_laplace",
    "95 % Laplace intervals of the same runs holding the truth",
    ">=",
    90.0,
    "%",
)


# --------------------------------------------------------------------------------------------
# per-scene rows (pure functions of metrics.json)


def object_entries(metrics: dict, laplace: dict | None = None) -> dict[str, dict]:
    """Per object of ``metrics`` (a run's metrics.json): its family and, per parameter, the
    errors and the 95 % interval's kind, method and coverage, and with ``laplace`` (the run's
    Laplace intervals, ``history_laplace``) the Laplace interval's kind and coverage.

    Each parameter entry has ``raw`` (relative error %, or None), ``gauge_free`` (% after the
    density gauge, for densities and stresses), ``deg`` (friction angle, absolute), ``error``
    (what the targets use: gauge-free, else degrees, else raw), ``kind`` (of the interval, None
    without one), ``covered`` (None without truth or interval), ``value`` (as identified; a
    density or stress in the truth's gauge, the value its gauge-free error compares) and
    ``true`` (None without truth), ``method`` (the interval's, None without one or where
    identified.json does not name it) and ``laplace`` (``{"kind", "covered"}`` of the Laplace
    interval, None without ``laplace``). Coverage of a density or stress is judged in the gauge
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
        truth, own = errors.get(str(k), {}), intervals.get(f"obj{k}", {})
        names = [n for n, _ in PARAMS if n in truth or n in own]
        params = {}
        for name in names:
            params[name] = _param_entry(truth.get(name), own.get(name), gauge)
            if laplace is not None:
                other = laplace.get(f"obj{k}", {}).get(name)
                params[name]["laplace"] = _laplace_entry(truth.get(name), other, gauge)
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
    entry["method"] = interval.get("method") if interval else None
    entry["covered"] = entry["value"] = entry["true"] = entry["laplace"] = None
    if err is None:
        return entry
    if "abs_error_deg" in err:
        entry["deg"] = entry["error"] = float(err["abs_error_deg"])
    else:
        entry["raw"] = 100.0 * float(err["rel_error"])
        if "rel_error_gauge_free" in err:
            entry["gauge_free"] = 100.0 * float(err["rel_error_gauge_free"])
        entry["error"] = entry["raw"] if entry["gauge_free"] is None else entry["gauge_free"]
    scale = _scale(err, gauge)
    value = err.get("value")
    entry["value"] = value * scale if isinstance(value, (int, float)) else value
    entry["true"] = err.get("true")
    entry["covered"] = _covers(interval, err.get("true"), scale)
    return entry


def _laplace_entry(err: dict | None, interval: dict | None, gauge: float | None) -> dict | None:
    """The Laplace interval's kind and whether it holds the truth (judged as ``_param_entry``
    judges the run's own interval); None without an interval."""
    if interval is None:
        return None
    covered = None if err is None else _covers(interval, err.get("true"), _scale(err, gauge))
    return {"kind": interval.get("kind"), "covered": covered}


def _scale(err: dict, gauge: float | None) -> float:
    """What takes an identified density or stress (one with a gauge-free error) into the
    truth's gauge; 1 for anything else."""
    gauge_free = "rel_error_gauge_free" in err and "abs_error_deg" not in err
    return gauge if (gauge_free and gauge) else 1.0


def _covers(interval: dict | None, true, scale: float) -> bool | None:
    """Whether ``interval``, times ``scale`` (into the truth's gauge), holds ``true``; None
    without an interval or a scalar truth."""
    if interval is None or not isinstance(true, (int, float)):
        return None
    low, high = interval.get("low"), interval.get("high")
    return (low is None or true >= low * scale) and (high is None or true <= high * scale)


def scene_row(
    name: str,
    metrics: dict,
    *,
    time_s: float,
    data: dict,
    device: str,
    code: str,
    history: list[dict] | None = None,
    date: str | None = None,
) -> dict:
    """One table row: the scene's objects (``object_entries``, with the Laplace intervals of
    ``history``, the run's identify/history.json entries), the contact the run identified
    with (``contact``: identified.json's ``choice``, ``mode`` and under ``auto`` the
    ``recipe_mode``, each mode's ``losses`` and the ``margin``; None for a simulator without
    contact modes), its CD and EMD over the observed and future frames, wall time and peak
    memory, and where it came from: the data, device and code, and ``date``, the day the run
    ended (the day the row is made unless given)."""
    future = metrics.get("future") or {}
    identified = metrics.get("params") or {}
    contact = identified.get("contact")
    if contact is not None:
        keep = ("choice", "mode", "recipe_mode", "losses", "margin", "laws")
        contact = {k: contact[k] for k in keep if k in contact}
    return {
        "scene": name,
        "contact": contact,
        "objects": object_entries(metrics, history_laplace(history)),
        "identified": identified_values(identified, history),
        "observed_cd_mm2": metrics["observed"]["cd_mm2"],
        "observed_emd_mm": metrics["observed"]["emd_mm"],
        "future_cd_mm2": future.get("cd_mm2"),
        "future_emd_mm": future.get("emd_mm"),
        "time_s": time_s,
        "peak_memory_gb": metrics.get("peak_memory_gb"),
        "data": data,
        "device": device,
        "code": code,
        # the day the run ended, which the RESULTS section names (a merge can be days later)
        "date": date or datetime.date.today().isoformat(),
    }


def run_dates(rows: list[dict]) -> str:
    """The days the rows' runs ended ('2026-11-30' or '2026-11-29 to 2026-11-30'); a row
    without a date (an older row file), or no row at all, counts as today."""
    today = datetime.date.today().isoformat()
    days = sorted({r.get("date") or today for r in rows}) or [today]
    return days[0] if len(days) == 1 else f"{days[0]} to {days[-1]}"


def identified_values(identified: dict, history: list[dict] | None = None) -> dict | None:
    """Every identified value of a run (identified.json): each object's law parameters and
    initial velocity, and the ground's friction, also those the truth has no value for, so
    that a row can be rolled out again without the run folder; None without them. With the
    run's identify ``history``, also where the ground's friction started
    (``ground_friction_start``, see ``ground_friction_start``)."""
    objects = identified.get("objects")
    if not objects:
        return None
    keep = ("family", "params", "initial_velocity")
    values = {
        "objects": {k: {n: o[n] for n in keep if n in o} for k, o in objects.items()},
        "ground_friction": identified.get("ground_friction"),
    }
    start = ground_friction_start(history)
    if start is not None:
        values["ground_friction_start"] = start
    return values


def ground_friction_start(history: list[dict] | None) -> float | None:
    """The ground's friction identification started from (the recipe's start, or the landings'
    reading with ``identify.ground_friction_start: landing``, the default 0.3 where none could
    be read): its value in the first record of the velocity phase, which moves only the initial
    velocities; None where the history has no such record (``identify.velocity_iterations``
    0). A scene without a ground records the default too."""
    for record in history or []:
        if record.get("phase") == "velocity":
            return (record.get("values") or {}).get("ground_friction")
    return None


def history_laplace(history: list[dict] | None) -> dict | None:
    """The Laplace intervals among a run's identify history records: the last interval
    record's ``laplace`` (a sandwich run keeps those of the same probes there), or its
    ``intervals`` where they are Laplace's; None without an interval record."""
    records = [h for h in history or [] if h.get("phase") == INTERVALS_PHASE]
    if not records:
        return None
    if "laplace" in records[-1]:
        return records[-1]["laplace"]
    # a record that names no method comes from before the sandwich existed: Laplace's
    laplace = records[-1].get("method", "laplace") == "laplace"
    return records[-1].get("intervals") if laplace else None


# --------------------------------------------------------------------------------------------
# the suite against its targets


def summarise(rows: list[dict]) -> dict:
    """Every quantity of ``TARGETS`` over the rows that ran (failed rows are listed apart):
    ``{key: {"value", "n", "target", "op", "met", ...}}`` plus ``scenes`` and ``failed``.

    The E statistics pool every object with an E (elastic, plasticine, sand); the interval
    coverage counts the intervals that claim something (unconstrained ones hold any value and
    are counted apart, ``unconstrained``), over parameters with a known truth, and counts
    those intervals by ``methods``. ``coverage_laplace`` is the same of the Laplace intervals
    of the runs whose history holds them (a sandwich run's from the same probes; ``n`` 0 where
    no row has them), against the same target; ``contact`` counts the rows by the contact
    they identified with (``contact_label``).
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
    out: dict = {"scenes": len(rows), "failed": [r["scene"] for r in rows if "error" in r]}
    out["E_finite"] = _median_stat(finite)
    out["E_within_50"] = _share([p["error"] <= 50.0 for p in e])
    out["E_not_finite"] = _share([k != "two-sided" for k in e_kinds])
    out["E_not_finite"]["one_sided"] = sum(k in ("lower-bound", "upper-bound") for k in e_kinds)
    for key in ("yield_stress", "friction_angle", "viscosity", "initial_velocity"):
        out[key] = _median_stat(
            [p["error"] for n, p in entries if n == key and p["error"] is not None]
        )
    out["coverage"] = _coverage([(p["kind"], p["covered"]) for _, p in entries])
    out["coverage"]["methods"] = _counts(
        p.get("method") or "not recorded" for _, p in entries if p["covered"] is not None
    )
    laplace = [p.get("laplace") for _, p in entries if p.get("laplace") is not None]
    out["coverage_laplace"] = _coverage([(p["kind"], p["covered"]) for p in laplace])
    out["contact"] = _counts(contact_label(r) for r in good)
    futures = [r["future_cd_mm2"] for r in good if r["future_cd_mm2"] is not None]
    out["future_cd"] = {"value": statistics.fmean(futures) if futures else None, "n": len(futures)}
    times = [r["time_s"] for r in good]
    out["time"] = {"value": max(times) if times else None, "n": len(times)}
    for key, _title, op, target, _unit in (*TARGETS, LAPLACE_TARGET):
        stat = out[key]
        stat.update(op=op, target=target, met=_meets(stat["value"], op, target))
    return out


def _coverage(intervals: list[tuple[str | None, bool | None]]) -> dict:
    """Of (kind, covered) pairs with a known truth: the share of those that claim something
    holding it, and the number of unconstrained ones (which hold any value)."""
    judged = [(kind, covered) for kind, covered in intervals if covered is not None]
    out = _share([bool(covered) for kind, covered in judged if kind != "unconstrained"])
    out["unconstrained"] = sum(kind == "unconstrained" for kind, _ in judged)
    return out


def _counts(labels) -> dict[str, int]:
    """How often each label occurs, most frequent first."""
    counts: dict[str, int] = {}
    for label in labels:
        counts[label] = counts.get(label, 0) + 1
    return dict(sorted(counts.items(), key=lambda item: -item[1]))


def contact_label(row: dict) -> str:
    """The contact a row identified with: 'single_field (auto)', 'multi_field (recipe)' (the
    recipe's fixed mode; also for rows from before rows recorded it), or '-' (a simulator
    without contact modes)."""
    contact = row.get("contact", UNRECORDED_CONTACT)
    if not contact:
        return "-"
    how = "auto" if contact.get("choice") == "auto" else "recipe"
    laws = contact.get("laws")
    variant = contact.get("mode") if laws in (None, "recipe") else f"{contact['mode']} + {laws}"
    return f"{variant} ({how})"


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
    interval's method, kind and whether it holds the truth, and after ';' the same of the
    Laplace interval from the same probes where the run's interval is another method's (a
    ';' because a '|' would end the markdown cell)."""
    if p is None:
        return "-"
    if p["deg"] is not None:
        text = _fmt(p["deg"])
    elif p["gauge_free"] is not None:
        text = f"{_fmt(p['gauge_free'])} / {_fmt(p['raw'])}"
    else:
        text = _fmt(p["raw"])
    if p["kind"] is not None:
        method = p.get("method")
        own = _interval_text(p["kind"], p["covered"], method)
        laplace = p.get("laplace")
        if laplace is not None and method not in (None, "laplace"):  # else they are the same
            own += "; " + _interval_text(laplace["kind"], laplace["covered"], "laplace")
        text += f" [{own}]"
    return text


def _interval_text(kind: str, covered: bool | None, method: str | None) -> str:
    """'sw 2s in': the method (left out where not recorded), the kind, whether it holds."""
    mark = "" if covered is None else (" in" if covered else " out")
    name = "" if method is None else f"{METHODS.get(method, method)} "
    return f"{name}{KINDS.get(kind, kind)}{mark}"


def markdown(table: dict) -> str:
    """Per object errors, per scene contact/CD/EMD/time/memory, and the summary against the
    targets."""
    rows = table["rows"]
    return "\n\n".join([_object_table(rows), _scene_table(rows), _summary(table["summary"])])


def _object_table(rows: list[dict]) -> str:
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
        " truth (densities and stresses after the density gauge); sw / lap: a sandwich / Laplace"
        " interval (no name: the row does not record the method), after ';' the Laplace interval"
        " from the same probes, kept in the run's identify history.",
    ]
    return "\n".join(lines)


def _scene_table(rows: list[dict]) -> str:
    lines = [
        "| scene | contact | observed CD mm^2 | observed EMD mm | future CD mm^2 | future EMD mm"
        " | time s | peak memory GB | ground friction (start) |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        if "error" in r:
            continue
        values = " | ".join(_fmt(r[key]) for key in _SCENE_COLUMNS)
        lines.append(f"| {r['scene']} | {_contact_cell(r)} | {values} | {_ground_cell(r)} |")
    lines += [
        "",
        "contact: the contact between objects identification used: (recipe) the recipe's fixed"
        " simulator.contact; (auto) chosen from the observed frames, followed by each mode's"
        " loss over them after its brief fit (docs/PHYSICS.md, Choosing the contact from the"
        " data). ground friction: the table's Coulomb coefficient as identified (Genesis's is"
        " 0.1; '-': the row does not record it), in brackets where identification started it"
        " (the recipe's start; with identify.ground_friction_start: landing the landings'"
        " reading, or the default 0.3 where none could be read); the future is sensitive to it"
        " (docs/RESULTS.md, Future error on Genesis scenes).",
    ]
    return "\n".join(lines)


def _ground_cell(row: dict) -> str:
    """'0.151 (0.126)': the identified coefficient and, where the row records it, its start."""
    identified = row.get("identified") or {}
    start = identified.get("ground_friction_start")
    cell = _fmt(identified.get("ground_friction"))
    return cell if start is None else f"{cell} ({_fmt(start)})"


def _contact_cell(row: dict) -> str:
    """``contact_label`` and, for a choice from the data, each mode's loss."""
    losses = (row.get("contact") or {}).get("losses")
    if not losses:
        return contact_label(row)
    each = ", ".join(f"{m} {'diverged' if v is None else _fmt(v)}" for m, v in losses.items())
    return f"{contact_label(row)}: {each}"


def _summary(summary: dict) -> str:
    """The quantities against their targets, the Laplace intervals' coverage where the rows
    hold them, and the counts behind them."""
    lines = ["| quantity | n | value | target | status |", "|---|---|---|---|---|"]
    laplace = summary.get("coverage_laplace") or {"n": 0, "unconstrained": 0}
    shown = (*TARGETS, LAPLACE_TARGET) if laplace["n"] + laplace["unconstrained"] else TARGETS
    for key, title, op, target, unit in shown:
        lines.append(_summary_line(title, summary[key], f"{op} {target:g} {unit}", unit))
    extra = [
        f"E intervals one-sided: {summary['E_not_finite'].get('one_sided', 0)}",
        f"unconstrained intervals (not counted in the coverage): "
        f"{summary['coverage'].get('unconstrained', 0)}",
    ]
    if laplace["n"] + laplace["unconstrained"]:
        extra.append(f"unconstrained Laplace intervals: {laplace['unconstrained']}")
    for name, counts in (
        ("interval methods", summary["coverage"].get("methods")),
        ("contact", summary.get("contact")),
    ):
        if counts:
            extra.append(f"{name}: " + ", ".join(f"{k} {v}" for k, v in counts.items()))
    text = "\n".join(lines) + "\n\n" + "; ".join(extra) + "."
    if summary["failed"]:
        text += f"\n\nfailed scenes: {', '.join(summary['failed'])}"
    return text + "\n"


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
        "the centre of each law's bounds, the ground's friction read off the landings, a "
        "global search before gradient descent, and the contact between the bodies and each "
        "material's stress chosen from the observed frames) on scenes "
        "that another engine simulated, so the model no longer matches the data exactly."
    )
    items = [
        f"Command: `{command}`",
        f"Machine: {', '.join(devices) or 'unknown'}. Date {date}. Code {', '.join(codes)}.",
        f"Data: {data_description(rows)}.",
    ]
    wrapped = [_fill(i, initial_indent="- ", subsequent_indent="  ") for i in items]
    return f"## {SECTION}\n\n{_fill(intro)}\n\n" + "\n".join(wrapped) + "\n\n" + markdown(table)


def replace_section(
    text: str, body: str, *, title: str = SECTION, before: str = SECTION_BEFORE
) -> str:
    """``results_sections.replace_section`` with this section's title and place as defaults."""
    return results_sections.replace_section(text, body, title=title, before=before)


def write_results(path: Path, table: dict, *, command: str) -> None:
    date = run_dates([r for r in table["rows"] if "error" not in r])
    text = path.read_text() if path.is_file() else "# Results\n"
    path.write_text(replace_section(text, section_text(table, command=command, date=date)))
