"""The tables, plot, chosen defaults and RESULTS section of ``genesis_resolution.py``.

Pure functions of the configuration rows (``OUT/parts/*.json``): each row is one scene
identified at one (grid, substeps), as genesis_identify's ``scene_row`` plus ``grid``,
``substeps_requested``, ``substeps`` (what ran; None when refused), ``need`` and ``problems``,
or a ``refused`` / ``error`` row.
"""

from __future__ import annotations

import csv
import datetime
import math
import shutil
import statistics
import textwrap
from pathlib import Path

from genesis_identify import PARAMS, _fill, data_description, replace_section
from identify_suite import _fmt

#: the section of docs/RESULTS.md the study owns (a new one goes before "From video")
SECTION = "Resolution study on Genesis scenes"
#: the plot's file name in the results file's img/ folder
IMAGE = "genesis_resolution.png"
#: how the defaults are chosen (filled with the tolerances)
RULE = (
    "the coarsest grid, then the fewest substeps, among the configurations that ran on every "
    "scene, whose median error of every parameter is within {tolerance:g} percentage points "
    "({tolerance_deg:g} deg for the friction angle) of the finest configuration's (the finest "
    "grid, then the most substeps)"
)
TITLES = dict(PARAMS)
#: parameters whose error is absolute, in degrees; the others' are relative, in %
DEGREES = ("friction_angle",)


def _ok(row: dict) -> bool:
    return "error" not in row and "refused" not in row


def _errors(row: dict, name: str) -> list[float]:
    """The errors of parameter ``name`` over the objects of one configuration row."""
    params = (obj["params"].get(name) for obj in row.get("objects", {}).values())
    return [p["error"] for p in params if p is not None and p["error"] is not None]


def _spread(values: list[float]) -> dict:
    """Median and quartiles of ``values`` (None without values)."""
    if not values:
        return {"median": None, "q1": None, "q3": None, "n": 0}
    if len(values) == 1:
        q1 = q3 = values[0]
    else:
        q1, _, q3 = statistics.quantiles(values, n=4, method="inclusive")
    return {"median": statistics.median(values), "q1": q1, "q3": q3, "n": len(values)}


def config_summary(rows: list[dict], scenes: list[str], params: list[str]) -> dict:
    """One (grid, requested substeps) over the scenes: which ran, were refused or failed, the
    substeps that ran, wall time, peak memory and each parameter's error spread."""
    ok = [r for r in rows if _ok(r)]
    times = [r["time_s"] for r in ok if r.get("time_s") is not None]
    memory = [r["peak_memory_gb"] for r in ok if r.get("peak_memory_gb") is not None]
    return {
        "grid": rows[0]["grid"],
        "substeps_requested": rows[0]["substeps_requested"],
        "substeps_used": sorted({r["substeps"] for r in ok}),
        "scenes_run": [r["scene"] for r in ok],
        "refused": [r["scene"] for r in rows if "refused" in r],
        "failed": [r["scene"] for r in rows if "error" in r],
        # not run at all (no row: a part still to come, or one whose process was stopped);
        # unlike a refusal, which says the configuration cannot run there
        "missing": sorted(set(scenes) - {r["scene"] for r in rows}),
        "complete": sorted({r["scene"] for r in ok}) == scenes,
        "errors": {n: _spread([e for r in ok for e in _errors(r, n)]) for n in params},
        "observed_cd": _spread([r["observed_cd_mm2"] for r in ok if r.get("observed_cd_mm2")]),
        "future_cd": _spread([r["future_cd_mm2"] for r in ok if r.get("future_cd_mm2")]),
        "time_median_s": statistics.median(times) if times else None,
        "time_max_s": max(times) if times else None,
        "peak_memory_max_gb": max(memory) if memory else None,
    }


def choose_defaults(
    configs: list[dict], params: list[str], *, tolerance: float, tolerance_deg: float
) -> dict:
    """The grid and substeps ``RULE`` picks, with the reference it compared against."""
    rule = RULE.format(tolerance=tolerance, tolerance_deg=tolerance_deg)
    complete = [c for c in configs if c["complete"]]
    # a configuration with scenes still to run may be the finest, or may be the one the rule
    # would pick: nothing is chosen until every part is in
    unfinished = [
        {"grid": c["grid"], "substeps": c["substeps_requested"], "missing": c["missing"]}
        for c in configs
        if c["missing"]
    ]
    if not complete or unfinished:
        return {
            "grid": None,
            "substeps": None,
            "reference": None,
            "rule": rule,
            "unfinished": unfinished,
        }

    def cost(c: dict) -> tuple:
        return c["grid"], max(c["substeps_used"])

    reference = max(complete, key=cost)

    def within(c: dict) -> bool:
        for name in params:
            ref, mine = reference["errors"][name]["median"], c["errors"][name]["median"]
            allowed = tolerance_deg if name in DEGREES else tolerance
            if ref is not None and (mine is None or mine > ref + allowed):
                return False
        return True

    chosen = min((c for c in complete if within(c)), key=cost)  # the reference always is
    return {
        "grid": chosen["grid"],
        "substeps": max(chosen["substeps_used"]),
        "reference": {"grid": reference["grid"], "substeps": max(reference["substeps_used"])},
        "rule": rule,
    }


def make_study(rows: list[dict], *, tolerance: float, tolerance_deg: float) -> dict:
    """What table.json holds: the rows, the scenes, the parameters with errors, one summary per
    configuration (by grid, then requested substeps) and the chosen defaults."""
    rows = sorted(rows, key=lambda r: (r["scene"], r["grid"], r["substeps_requested"]))
    scenes = sorted({r["scene"] for r in rows})
    params = [n for n, _ in PARAMS if any(_errors(r, n) for r in rows if _ok(r))]
    keys = sorted({(r["grid"], r["substeps_requested"]) for r in rows})
    configs = [
        config_summary(
            [r for r in rows if (r["grid"], r["substeps_requested"]) == key], scenes, params
        )
        for key in keys
    ]
    defaults = choose_defaults(configs, params, tolerance=tolerance, tolerance_deg=tolerance_deg)
    return {
        "rows": rows,
        "scenes": scenes,
        "params": params,
        "configs": configs,
        "defaults": defaults,
        "paired": paired_summary(rows, configs, scenes, params),
    }


def paired_summary(rows: list[dict], configs: list[dict], scenes: list[str], params: list[str]):
    """Each configuration's median errors over the scenes that every configuration ran, so
    that configurations are compared on the same scenes while some have not run everywhere
    (None when every configuration ran every scene, or no scene was run by all)."""
    common = [s for s in scenes if all(s in c["scenes_run"] for c in configs)]
    if not common or common == scenes:
        return None
    summaries = []
    for c in configs:
        key = (c["grid"], c["substeps_requested"])
        mine = [
            r
            for r in rows
            if (r["grid"], r["substeps_requested"]) == key and r["scene"] in common and _ok(r)
        ]
        errors = {n: _spread([e for r in mine for e in _errors(r, n)]) for n in params}
        future = _spread([r["future_cd_mm2"] for r in mine if r.get("future_cd_mm2")])
        summaries.append(
            {"grid": key[0], "substeps_requested": key[1], "errors": errors, "future_cd": future}
        )
    return {"scenes": common, "configs": summaries}


# --------------------------------------------------------------------------------------------
# files


def write_csv(path: Path, study: dict) -> None:
    """One line per scene, object, parameter and configuration (one per scene and
    configuration, without a parameter, for a refused or failed one)."""
    columns = ["scene", "object", "family", "parameter", "unit", "grid", "substeps_requested"]
    columns += ["substeps", "status", "value", "true", "error", "time_s", "peak_memory_gb"]
    with path.open("w", newline="") as handle:
        writer = csv.DictWriter(handle, columns)
        writer.writeheader()
        for r in study["rows"]:
            base = {k: r.get(k) for k in ("scene", "grid", "substeps_requested", "substeps")}
            base |= {"time_s": r.get("time_s"), "peak_memory_gb": r.get("peak_memory_gb")}
            if not _ok(r):
                status = "refused" if "refused" in r else "failed"
                writer.writerow({**base, "status": status})
                continue
            for k, obj in r["objects"].items():
                for name in study["params"]:
                    p = obj["params"].get(name)
                    if p is None or p["error"] is None:
                        continue
                    writer.writerow(
                        {
                            **base,
                            "object": k,
                            "family": obj["family"],
                            "parameter": name,
                            "unit": "deg" if name in DEGREES else "%",
                            "status": "ok",
                            "value": _plain(p.get("value")),
                            "true": _plain(p.get("true")),
                            "error": p["error"],
                        }
                    )


def _plain(value):
    """A CSV cell: vectors as space-separated numbers."""
    return " ".join(f"{v:.6g}" for v in value) if isinstance(value, list) else value


def plot_title(study: dict) -> str:
    """What the plot shows and which data it comes from."""
    first = {r["scene"]: r for r in study["rows"]}
    record = study.get("study") or {}
    sets = " ".join(record.get("overrides") or []) or "no overrides"
    devices = sorted({r.get("device") for r in study["rows"] if _ok(r) and r.get("device")})
    head = (
        "Genesis resolution study: median error per parameter against the simulator grid "
        "(band: quartiles over objects; hollow marker: not every scene ran)"
    )
    source = (
        f"{data_description(list(first.values()))}; {record.get('recipe', 'recipe unknown')} "
        f"with {sets}; {', '.join(devices) or 'no run'}"
    )
    return head + "\n" + textwrap.fill(source, 150)


def plot(study: dict, path: Path) -> None:
    """Each parameter's median error against the grid, one line per requested substep count
    (a grid where some scene ran with raised substeps says so in the legend)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import NullLocator

    params = study["params"] or ["none"]
    cols = min(3, len(params))
    fig, axes = plt.subplots(
        math.ceil(len(params) / cols),
        cols,
        figsize=(4.6 * cols, 3.6 * math.ceil(len(params) / cols)),
        squeeze=False,
    )
    grids = sorted({c["grid"] for c in study["configs"]})
    counts = sorted({c["substeps_requested"] for c in study["configs"]})
    for ax, name in zip(axes.flat, params):
        for count in counts:
            mine = [
                c
                for c in study["configs"]
                if c["substeps_requested"] == count
                and c["errors"].get(name, {}).get("median") is not None
            ]
            if mine:
                _plot_line(ax, mine, name, _label(count, mine))
        ax.set_xscale("log", base=2)
        ax.xaxis.set_minor_locator(NullLocator())
        ax.set_xticks(grids, [str(g) for g in grids])
        ax.set_xlabel("simulator grid (cells)")
        unit = "deg" if name in DEGREES else "%"
        ax.set_ylabel(f"median error ({unit})")
        ax.set_title(TITLES.get(name, name).rsplit(" ", 1)[0])
        if ax.lines:
            ax.legend(fontsize=7)
    for ax in list(axes.flat)[len(params) :]:
        ax.set_visible(False)
    fig.suptitle(plot_title(study), fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _plot_line(ax, configs: list[dict], name: str, label: str) -> None:
    spread = [c["errors"][name] for c in configs]
    x = [c["grid"] for c in configs]
    (line,) = ax.plot(x, [s["median"] for s in spread], "-", label=label)
    color = line.get_color()
    ax.fill_between(
        x, [s["q1"] for s in spread], [s["q3"] for s in spread], color=color, alpha=0.15
    )
    for c, s in zip(configs, spread):
        face = color if c["complete"] else "none"
        ax.plot(c["grid"], s["median"], "o", color=color, markerfacecolor=face)


def _label(count: int, configs: list[dict]) -> str:
    raised = [str(c["grid"]) for c in configs if any(s != count for s in c["substeps_used"])]
    return f"{count} substeps" + (f" (raised at grid {', '.join(raised)})" if raised else "")


# --------------------------------------------------------------------------------------------
# markdown


def defaults_line(study: dict) -> str:
    d = study["defaults"]
    if d.get("unfinished"):
        waiting = "; ".join(
            f"grid {u['grid']} with {u['substeps']} substeps has no row for {', '.join(u['missing'])}"
            for u in d["unfinished"]
        )
        return (
            f"The study's choice: none: the study is unfinished ({waiting}). The rule, once every "
            f"configuration has run: {d['rule']}."
        )
    if d["grid"] is None:
        rule = d["rule"]
        return f"The study's choice: none (no configuration ran on every scene; the rule: {rule})."
    ref = d["reference"]
    return (
        f"The study's choice: `simulator.grid={d['grid']} simulator.substeps={d['substeps']}`, "
        f"{d['rule']}: grid {ref['grid']} with {ref['substeps']} substeps."
    )


def config_table(study: dict) -> list[str]:
    """One line per configuration: scenes, time, memory and each parameter's median error."""
    titles = [TITLES[n] for n in study["params"]]
    head = ["grid", "substeps", "scenes run / refused / failed", "median time s"]
    head += ["longest time s", "peak memory GB"] + [f"median {t}" for t in titles]
    head += ["median future CD mm^2"]
    lines = ["| " + " | ".join(head) + " |", "|---" * len(head) + "|"]
    for c in study["configs"]:
        used = [s for s in c["substeps_used"] if s != c["substeps_requested"]]
        substeps = str(c["substeps_requested"])
        substeps += f" (raised to {', '.join(map(str, used))})" if used else ""
        cells = [str(c["grid"]), substeps]
        cells.append(f"{len(c['scenes_run'])} / {len(c['refused'])} / {len(c['failed'])}")
        cells += [_fmt(c[k]) for k in ("time_median_s", "time_max_s", "peak_memory_max_gb")]
        cells += [_fmt(c["errors"][n]["median"]) for n in study["params"]]
        cells.append(_fmt((c.get("future_cd") or {}).get("median")))
        lines.append("| " + " | ".join(cells) + " |")
    return lines


def paired_table(study: dict) -> list[str]:
    """The configurations on the scenes all of them ran (empty when there is no such subset)."""
    paired = study.get("paired")
    if not paired:
        return []
    titles = [TITLES[n] for n in study["params"]]
    head = ["grid", "substeps"] + [f"median {t}" for t in titles] + ["median future CD mm^2"]
    lines = ["", _fill(f"On the scenes every configuration ran ({', '.join(paired['scenes'])}):")]
    lines += ["", "| " + " | ".join(head) + " |", "|---" * len(head) + "|"]
    for c in paired["configs"]:
        cells = [str(c["grid"]), str(c["substeps_requested"])]
        cells += [_fmt(c["errors"][n]["median"]) for n in study["params"]]
        cells.append(_fmt(c["future_cd"]["median"]))
        lines.append("| " + " | ".join(cells) + " |")
    return lines


def notes(study: dict) -> list[str]:
    """The configurations that did not run as asked: refused, raised or failed."""
    out = []
    for r in study["rows"]:
        where = f"{r['scene']} at grid {r['grid']} with {r['substeps_requested']} substeps"
        need = f"needs at least {r.get('need')}" if r.get("need") else "no count is enough"
        why = (r.get("problems") or ["-"])[0]
        if "refused" in r:
            out.append(f"{where}: refused ({need}): {why}")
        elif "error" in r:
            out.append(f"{where}: failed: {r['error']}")
        elif r["substeps"] != r["substeps_requested"]:
            out.append(f"{where}: ran with {r['substeps']} ({need}): {why}")
    return out


def scene_table(study: dict) -> list[str]:
    """Per scene, object and parameter: the truth, then error (identified value) per
    configuration; refused and failed configurations say so."""
    keys = [(c["grid"], c["substeps_requested"]) for c in study["configs"]]
    head = ["scene", "object", "parameter", "truth"] + [f"g{g} s{s}" for g, s in keys]
    lines = ["| " + " | ".join(head) + " |", "|---" * len(head) + "|"]
    for scene in study["scenes"]:
        rows = {
            (r["grid"], r["substeps_requested"]): r for r in study["rows"] if r["scene"] == scene
        }
        ran = [r for r in rows.values() if _ok(r)]
        objects = {k: o["family"] for r in ran for k, o in r["objects"].items()}
        for k, family in objects.items():
            for name in study["params"]:
                entries = [_entry(rows.get(key), k, name) for key in keys]
                if not any(e and e["error"] is not None for e in entries):
                    continue
                true = next(e["true"] for e in entries if e and e["error"] is not None)
                cells = [_scene_cell(rows.get(key), e) for key, e in zip(keys, entries)]
                lines.append(
                    f"| {scene} | {k} {family} | {TITLES[name]} | {_fmt(true)} | "
                    + " | ".join(cells)
                    + " |"
                )
    return lines


def _entry(row: dict | None, k: str, name: str) -> dict | None:
    """Parameter ``name`` of object ``k`` in a configuration row that ran (else None)."""
    if row is None or not _ok(row):
        return None
    return row["objects"].get(k, {}).get("params", {}).get(name)


def _scene_cell(row: dict | None, entry: dict | None) -> str:
    if row is None:
        return "-"
    if "refused" in row:
        return "refused"
    if "error" in row:
        return "failed"
    if entry is None or entry["error"] is None:
        return "-"
    text = _fmt(entry["error"])
    if isinstance(entry.get("value"), (int, float)):
        text += f" ({_fmt(entry['value'])})"
    return text


def markdown(study: dict, *, plot_link: str) -> str:
    """The chosen defaults, the plot, the configuration table, the notes and the per-scene
    table (folded)."""
    lines = [_fill(defaults_line(study)), "", f"![error against grid]({plot_link})", ""]
    lines += config_table(study)
    legend = (
        "Errors: densities and stresses gauge-free (%), friction angle absolute (deg), v0 "
        "|v - v_true| / |v_true| (%); median over every object of the scenes that ran."
    )
    lines += ["", _fill(legend)]
    lines += paired_table(study)
    if notes(study):
        lines += [
            "",
            *(_fill(n, initial_indent="- ", subsequent_indent="  ") for n in notes(study)),
        ]
    lines += [
        "",
        "<details><summary>Per scene, object and parameter: error (identified value, "
        "in the truth's density gauge)</summary>",
        "",
        *scene_table(study),
        "",
        "</details>",
    ]
    return "\n".join(lines) + "\n"


def section_text(study: dict, *, command: str, date: str, plot_link: str) -> str:
    """The RESULTS.md section: what was run, on what, and the study."""
    rows = study["rows"]
    record = study.get("study") or {}
    one_per_scene = list({r["scene"]: r for r in rows}.values())
    devices = sorted({r["device"] for r in rows if _ok(r) and r.get("device")})
    codes = sorted({r["code"] for r in rows if r.get("code")})
    sets = " ".join(f"--set {s}" for s in record.get("overrides") or []) or "none"
    intro = (
        "`benchmarks/genesis_resolution.py` identifies every scene as "
        "`benchmarks/genesis_identify.py` does, at each simulator grid and substep count, each "
        "configuration in its own process, and shows how each parameter's error (as in the "
        "section above) changes with resolution. Before a configuration runs, its substep count "
        "is checked at its grid: the recipe validator's stiffness caps must lie above the values "
        "identification starts from and above every object's true stiffness in the density "
        "gauge; a count that fails is refused, or raised with `--unstable raise`."
    )
    items = [
        f"Command: `{command}`",
        f"Recipe: `{record.get('recipe', 'unknown')}`; overrides of every configuration: `{sets}`.",
        f"Machine: {', '.join(devices) or 'unknown'}. Date {date}. Code {', '.join(codes) or 'unknown'}.",
        f"Data: {data_description(one_per_scene)}.",
    ]
    wrapped = [_fill(i, initial_indent="- ", subsequent_indent="  ") for i in items]
    body = markdown(study, plot_link=plot_link)
    return f"## {SECTION}\n\n{_fill(intro)}\n\n" + "\n".join(wrapped) + "\n\n" + body


def write_results(path: Path, study: dict, *, command: str, png: Path) -> None:
    """Replace (or add) the section in ``path``; the plot goes to ``img/`` beside it."""
    image = path.parent / "img" / IMAGE
    image.parent.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(png, image)
    date = datetime.date.today().isoformat()
    body = section_text(study, command=command, date=date, plot_link=f"img/{IMAGE}")
    text = path.read_text() if path.is_file() else "# Results\n"
    path.write_text(replace_section(text, body, title=SECTION))
