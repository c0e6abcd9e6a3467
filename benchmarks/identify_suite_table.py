"""The identify suite's table: summary against the targets, markdown, and its RESULTS section.

``benchmarks/identify_suite.py`` runs the pairs; this module turns their rows into what is read:
per error kind the median and worst case against the own-synth targets (E within 15 %, yield
within 25 %, friction angle within 5 deg, v0 within 5 %, future-CD ratio library / ours at least
5), set for and met by the paper-range suite (docs/RESULTS.md, "Identification (oracle
reconstructor)"); the settings a table was run with (the generator's ranges, where
identification starts, its global stage); and, with ``--write-results``, the section of
docs/RESULTS.md those settings own.
"""

from __future__ import annotations

import datetime
import statistics
from pathlib import Path

#: error kinds of the gradient fit: (key, column title, target, unit of the target)
TARGETS = (
    ("E_pct", "E % (elastic)", 15.0, "%"),
    ("yield_pct", "yield %", 25.0, "%"),
    ("friction_angle_deg", "friction angle deg", 5.0, "deg"),
    ("v0_pct", "v0 %", 5.0, "%"),
)
#: reported without a target of the issue: E of the plastic and granular bodies, viscosity
EXTRA = (("E_other_pct", "E % (P, S)"), ("viscosity_pct", "viscosity %"))
RATIO_TARGET = 5.0
#: a new --write-results section goes before this one: after the paper-range section
RESULTS_BEFORE = "Identification on Genesis scenes"
#: where the targets come from: they were set for, and met by, the paper-range suite
TARGETS_SOURCE = 'docs/RESULTS.md, "Identification (oracle reconstructor)"'


def targets_json() -> dict:
    """The targets every table is compared with (``TARGETS``, ``RATIO_TARGET``) and where
    they come from."""
    limits = {key: {"at_most": target, "unit": unit} for key, _, target, unit in TARGETS}
    limits["future_cd_ratio"] = {"at_least": RATIO_TARGET, "unit": "x"}
    return {"source": TARGETS_SOURCE, **limits}


def describe_settings(settings: dict) -> str:
    """The settings in words: the ranges, the start and the global stage."""
    return f"{settings['ranges']} ranges, {_identification_words(settings)}"


def _identification_words(settings: dict) -> str:
    start = {
        "defaults": "the law defaults (near the centre of the paper ranges)",
        "centre": "the centre of each law's bounds",
    }.get(settings["start"], settings["start"])
    n = settings["global_candidates"]
    stage = f"a global stage of {n} candidates" if n else "no global stage"
    polish = settings.get("global_polish", 0)
    if polish:
        stage += f" and a scan of {polish} values along each parameter after it"
    return f"start at {start}, {stage}"


def _ok(row: dict) -> bool:
    return "error" not in row["gradient"] and "error" not in row["library"]


def summarise(rows: list[dict]) -> dict:
    """Per error kind over every object of every scene: count, median and worst, and whether
    the worst case meets its target; the same for the future-CD ratio (worst = least)."""
    good = [r for r in rows if _ok(r)]
    out: dict = {"scenes": len(rows), "failed": [r["scene"] for r in rows if not _ok(r)]}
    for key, _, target, _unit in TARGETS:
        values = [v for r in good for v in r["gradient"]["errors"][key]]
        out[key] = _stats(values, target=target, worst=max, meets=lambda v, t: v <= t)
    for key, _ in EXTRA:
        values = [v for r in good for v in r["gradient"]["errors"][key]]
        out[key] = _stats(values, target=None, worst=max, meets=None)
    ratios = [
        r["future_cd_ratio_library_over_ours"]
        for r in good
        if r["future_cd_ratio_library_over_ours"] is not None
    ]
    out["future_cd_ratio"] = _stats(
        ratios, target=RATIO_TARGET, worst=min, meets=lambda v, t: v >= t
    )
    # the ratio of the mean future CDs over the scenes (the paper's tables average per pair)
    means = {
        m: statistics.fmean([r[m]["future_cd_mm2"] for r in good]) if good else None
        for m in ("gradient", "library")
    }
    out["mean_future_cd_mm2"] = means
    out["ratio_of_mean_future_cd"] = (
        means["library"] / means["gradient"] if good and means["gradient"] else None
    )
    probe = [
        r["true_ground_ratio_library_over_ours"]
        for r in good
        if r.get("true_ground_ratio_library_over_ours") is not None
    ]
    out["true_ground_ratio"] = _stats(
        probe, target=RATIO_TARGET, worst=min, meets=lambda v, t: v >= t
    )
    out["median_time_s"] = {
        m: statistics.median([r[m]["time_s"] for r in good]) if good else None
        for m in ("gradient", "library")
    }
    return out


def _stats(values: list[float], *, target, worst, meets) -> dict:
    if not values:
        return {"n": 0, "median": None, "worst": None, "target": target, "met": None, "n_met": None}
    w = worst(values)
    return {
        "n": len(values),
        "median": statistics.median(values),
        "worst": w,
        "target": target,
        "met": None if meets is None else bool(meets(w, target)),
        "n_met": None if meets is None else sum(bool(meets(v, target)) for v in values),
    }


def _fmt(value) -> str:
    if value is None:
        return "-"
    if isinstance(value, list):
        return " / ".join(_fmt(v) for v in value) if value else "-"
    return f"{value:.3g}"


def settings_lines(settings: dict) -> list[str]:
    """What a table was run with and what it is held to, as markdown paragraphs."""
    from genesis_identify import _fill  # genesis_identify imports this module

    limits = [f"{title} <= {target:g} {unit}" for _, title, target, unit in TARGETS]
    limits.append(f"future CD ratio library / ours >= {RATIO_TARGET:g}")
    return [
        _fill(
            f"Scenes drawn from the {settings['ranges']} ranges of mosiv-synth; identification: "
            f"{_identification_words(settings)}."
        ),
        "",
        _fill(f"Targets, those of the paper-range suite ({TARGETS_SOURCE}): {', '.join(limits)}."),
        "",
    ]


def markdown(rows: list[dict], summary: dict, *, settings: dict | None = None) -> str:
    """The settings and targets (with ``settings``), the per-scene table (every object's
    error, '/'-separated) and the summary against the targets."""
    kinds = [(k, title) for k, title, *_ in TARGETS] + list(EXTRA)
    head = [title for _, title in kinds] + [
        "observed CD ours / library (mm^2)",
        "future CD ours / library (mm^2)",
        "ratio library / ours",
        "future CD with true table friction ours / library (mm^2)",
    ]
    lines = [] if settings is None else settings_lines(settings)
    lines += ["| scene | " + " | ".join(head) + " |", "|---" * (len(head) + 1) + "|"]
    for r in rows:
        if not _ok(r):
            why = r["gradient"].get("error") or r["library"].get("error")
            lines.append(f"| {r['pair']} | failed: {why} |" + " |" * (len(head) - 1))
            continue
        g, lib = r["gradient"], r["library"]
        cells = [_fmt(g["errors"][k]) for k, _ in kinds] + [
            f"{_fmt(g['observed_cd_mm2'])} / {_fmt(lib['observed_cd_mm2'])}",
            f"{_fmt(g['future_cd_mm2'])} / {_fmt(lib['future_cd_mm2'])}",
            _fmt(r["future_cd_ratio_library_over_ours"]),
            f"{_fmt(g.get('future_cd_true_ground_mm2'))} / "
            f"{_fmt(lib.get('future_cd_true_ground_mm2'))}",
        ]
        lines.append(f"| {r['pair']} | " + " | ".join(cells) + " |")
    lines += [
        "",
        "| quantity | n | median | worst | target | status |",
        "|---|---|---|---|---|---|",
    ]
    for key, title, target, unit in TARGETS:
        lines.append(_summary_line(title, summary[key], f"<= {target:g} {unit}"))
    for key, title in EXTRA:
        lines.append(_summary_line(title, summary[key], "-"))
    lines.append(
        _summary_line(
            "future CD ratio library / ours", summary["future_cd_ratio"], f">= {RATIO_TARGET:g}"
        )
    )
    lines.append(
        _summary_line(
            "same ratio, table friction set to its true value (diagnostic)",
            summary["true_ground_ratio"],
            f">= {RATIO_TARGET:g}",
        )
    )
    means = summary["mean_future_cd_mm2"]
    lines.append(
        f"\nmean future CD over the scenes: ours {_fmt(means['gradient'])} mm^2, library "
        f"{_fmt(means['library'])} mm^2, ratio {_fmt(summary['ratio_of_mean_future_cd'])}; "
        f"median wall time per scene: ours {_fmt(summary['median_time_s']['gradient'])} s, "
        f"library {_fmt(summary['median_time_s']['library'])} s"
    )
    if summary["failed"]:
        lines.append(f"\nfailed scenes: {', '.join(summary['failed'])}")
    versions: dict[str, list[str]] = {}
    for row in rows:
        versions.setdefault(row.get("code", "unknown"), []).append(row["pair"])
    lines.append(
        "\ncode version per row: "
        + "; ".join(f"{v}: {', '.join(pairs)}" for v, pairs in sorted(versions.items()))
    )
    return "\n".join(lines) + "\n"


def _summary_line(title: str, s: dict, target: str) -> str:
    if s["n"] == 0:
        status = "not measured"
    elif s["met"] is None:
        status = "-"
    else:  # the worst case decides; the count says how close the rest are
        status = f"{'met' if s['met'] else 'not met'} ({s['n_met']} of {s['n']} within)"
    return (
        f"| {title} | {s['n']} | {_fmt(s['median'])} | {_fmt(s['worst'])} | {target} | {status} |"
    )


def results_title(settings: dict) -> str:
    """The docs/RESULTS.md section a table of these settings owns (``--write-results``); never
    the hand-written paper-range section "Identification (oracle reconstructor)"."""
    title = f"Identification on own-synth scenes, {settings['ranges']} ranges"
    if settings["start"] != "defaults":
        title += f", {settings['start']} start"
    return title


def section_text(result: dict, *, command: str, date: str) -> str:
    """The RESULTS.md section of a suite's ``result`` (write_table's): what ran, on what and
    how, then the table."""
    from genesis_identify import _fill  # genesis_identify imports this module

    rows, settings = result["rows"], result["settings"]
    devices = sorted({r["device"] for r in rows if r.get("device")})
    codes = sorted({r.get("code", "unknown") for r in rows})
    substeps = sorted({r["substeps"] for r in rows if r.get("substeps") is not None})
    intro = (
        "`benchmarks/identify_suite.py` on one scene per material pair, gradient "
        "identification (ours) against the discrete-library baseline, as in "
        '"Identification (oracle reconstructor)" but with the settings below.'
    )
    items = [
        f"Command: `{command}`",
        f"Machine: {', '.join(devices) or 'unknown'}. Date {date}. Code {', '.join(codes)}.",
        f"Data: {len(rows)} scene(s) generated by mosiv-synth (warp-mpm) from the "
        f"{settings['ranges']} ranges, seed = {_seed_words(settings)}; identification at "
        f"{', '.join(map(str, substeps)) or '-'} substeps per frame (the recipe's, or more where "
        "the generator made a scene with more).",
    ]
    wrapped = [_fill(i, initial_indent="- ", subsequent_indent="  ") for i in items]
    table = markdown(rows, result["summary"], settings=settings)
    return (
        f"## {results_title(settings)}\n\n{_fill(intro)}\n\n" + "\n".join(wrapped) + "\n\n" + table
    )


def _seed_words(settings: dict) -> str:
    first = settings.get("seed", 0)
    return f"{first} + the pair's index" if first else "the pair's index"


def write_results(path: Path, result: dict, *, argv: list[str]) -> str:
    """Replace (or add, after the paper-range section) the section of ``result``'s settings
    in the markdown file ``path``; returns its title."""
    from genesis_identify import command_line, replace_section

    title = results_title(result["settings"])
    command = command_line(argv, script="benchmarks/identify_suite.py")
    body = section_text(result, command=command, date=datetime.date.today().isoformat())
    text = path.read_text() if path.is_file() else "# Results\n"
    path.write_text(replace_section(text, body, title=title, before=RESULTS_BEFORE))
    return title
