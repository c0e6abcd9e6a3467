"""The tables of ``benchmarks/genesis_video.py``: a run's row from its metrics.json, table 1 per
scene and method, the from-video targets, runtime and memory per method, the supervision
ablation with its run-to-run spread, and the docs/RESULTS.md section. Pure functions of the
rows (no runs here), so the tables can be rebuilt from the parts at any time."""

from __future__ import annotations

import datetime
import math
import statistics
from pathlib import Path

import genesis_identify as gi
from video_suite import OURS, VARIANTS, paired_p_value

#: the section of docs/RESULTS.md this benchmark owns; a new one goes after ``AFTER``'s
SECTION = "From video on Genesis scenes"
AFTER = "From video"
#: table 1's methods in the paper's order, with their names there
LABELS = {
    "library": "OmniPhysGS-RGB",
    "library-oracle": "OmniPhysGS-RGB w/ Oracle",
    "coupnerf": "CoupNeRF*",
    "ours": "MOSIV (ours)",
}
BLOCKS = ("observed", "future")
#: table 1's quantities: (key, title, which is better)
QUANTITIES = (("psnr", "PSNR dB", max), ("ssim", "SSIM", max))
QUANTITIES += (("cd_mm2", "CD mm^2", min), ("emd_mm", "EMD mm", min))
#: what a row keeps of each metrics.json block
BLOCK_KEYS = ("psnr", "ssim", "cd_mm2", "emd_mm", "psnr_objects")
#: the from-video targets for ours: (key, title, comparison, target, unit)
TARGETS = (
    ("observed_psnr", "mean observed PSNR", ">=", 31.5, "dB"),
    ("future_psnr", "mean future PSNR", ">=", 29.0, "dB"),
    ("future_cd", "mean future CD", "<=", 894.0, "mm^2"),
    ("gaussian_cd", "Gaussian CD per object, worst frame / the scene's floor", "<=", 3.0, "x"),
    ("iou", "mask IoU per object, worst frame", ">=", 0.9, ""),
    ("time", "end-to-end wall time per scene", "<", 600.0, "s"),
    ("memory", "peak memory per scene", "<", 16.0, "GB"),
)
#: ablation variant -> the method name its runs have (video_suite's ours is table 1's ours)
VARIANT_METHOD = {folder: ("ours" if folder == OURS else folder) for folder, *_ in VARIANTS}
VARIANT_LABEL = {folder: label for folder, label, *_ in VARIANTS}


def scores_of(metrics: dict) -> dict:
    """What a row keeps of a run's metrics.json: the observed and future blocks, the peak
    memory (the run's, its copied Stage I-II included) and each stage's, each stage's time,
    and, for a Gaussian Stage I, per object its worst-frame Chamfer, that as a multiple of the
    scene's Chamfer floor, and its worst-frame mask IoU."""
    out: dict = {"peak_memory_gb": metrics.get("peak_memory_gb")}
    out["stage_times_s"] = metrics.get("stage_times_s")
    out["stage_peak_memory_gb"] = metrics.get("stage_peak_memory_gb")
    for block in BLOCKS:
        values = metrics.get(block)
        out[block] = None if values is None else {k: values.get(k) for k in BLOCK_KEYS}
    recon = metrics.get("reconstruction")
    out["stage1"] = None
    if recon is not None:
        keep = ("cd_mm2_max", "cd_floor_multiple", "iou_min")
        out["stage1"] = {
            "chamfer_floor_mm2": recon.get("chamfer_floor_mm2"),
            "skipped_steps": recon.get("skipped_steps"),
            "per_object": {
                k: {key: o.get(key) for key in keep} for k, o in recon["per_object"].items()
            },
        }
    return out


def _ok(row) -> bool:
    return isinstance(row, dict) and "error" not in row


def _value(row: dict, block: str, key: str):
    return (row.get(block) or {}).get(key) if _ok(row) else None


def _mean(values) -> float | None:
    values = [v for v in values if v is not None and math.isfinite(v)]
    return statistics.fmean(values) if values else None


def _meets(value, op: str, target: float) -> bool | None:
    if value is None or not math.isfinite(value):
        return None
    return {"<=": value <= target, ">=": value >= target, "<": value < target}[op]


# --------------------------------------------------------------------------------------------
# table 1


def table_rows(rows: list[dict]) -> dict[str, dict[str, dict]]:
    """Table 1's runs (Stage I seed 0): method -> scene -> row, methods in LABELS' order."""
    cells: dict[str, dict[str, dict]] = {}
    for method in LABELS:
        found = {r["scene"]: r for r in rows if r["method"] == method and r.get("seed", 0) == 0}
        if found:
            cells[method] = found
    return cells


#: the pipeline's stages, as metrics.json's stage_times_s names them, and their short names
STAGE_NAMES = {"reconstruct": "I", "lift": "II", "identify": "III", "evaluate": "eval"}


def _median_stage_times(good: list[dict]) -> dict[str, float | None]:
    """Per stage, the median over the runs that recorded its time."""
    out = {}
    for stage in STAGE_NAMES:
        times = [(r.get("stage_times_s") or {}).get(stage) for r in good]
        times = [t for t in times if t is not None]
        out[stage] = statistics.median(times) if times else None
    return out


def _block_means(good: list[dict]) -> dict:
    return {
        block: {
            key: {"value": _mean(_value(r, block, key) for r in good), "n": len(good)}
            for key in BLOCK_KEYS
        }
        for block in BLOCKS
    }


def summarise(rows: list[dict], development: list[str] | tuple = ()) -> dict:
    """Means per method and block over the scenes it ran, ours against TARGETS, runtime and
    memory per method, and the failed runs. ``development``: the scenes that settings were
    chosen on; the targets are then judged on the other (test) scenes, and the means over the
    test scenes come beside those over all scenes."""
    cells = table_rows(rows)
    scenes = sorted({s for found in cells.values() for s in found})
    development = sorted(s for s in development if s in scenes)
    test = [s for s in scenes if s not in development]
    out: dict = {"scenes": scenes, "methods": list(cells), "means": {}, "runtime": {}}
    out["development"] = development
    out["test_means"] = {}
    for method, found in cells.items():
        good = [r for r in found.values() if _ok(r)]
        out["means"][method] = _block_means(good)
        if development:
            out["test_means"][method] = _block_means([r for r in good if r["scene"] in test])
        times = [r["time_s"] for r in good]
        memory = [r["peak_memory_gb"] for r in good if r.get("peak_memory_gb") is not None]
        out["runtime"][method] = {
            "n": len(good),
            "median_stage_s": _median_stage_times(good),
            "median_time_s": statistics.median(times) if times else None,
            "max_time_s": max(times) if times else None,
            "median_peak_gb": statistics.median(memory) if memory else None,
            "max_peak_gb": max(memory) if memory else None,
            "memory": sorted({r.get("memory", "-") for r in good}),
        }
    out["failed"] = [
        {"scene": r["scene"], "method": m, "error": r["error"]}
        for m, found in cells.items()
        for r in found.values()
        if not _ok(r)
    ]
    ours = cells.get("ours", {})
    out["targets"] = targets({s: r for s, r in ours.items() if s in test}, test)
    if development:
        out["targets_all"] = targets(ours, scenes)
    return out


def targets(ours: dict[str, dict], scenes: list[str]) -> dict:
    """Every target of TARGETS for ours: ``{key: {"value", "n", "op", "target", "met", ...}}``.
    A scene where ours failed or did not run leaves every target not met (it says which)."""
    good = [r for r in ours.values() if _ok(r)]
    missing = [s for s in scenes if not _ok(ours.get(s))]
    objects = [o for r in good for o in ((r.get("stage1") or {}).get("per_object") or {}).values()]
    multiples = [o["cd_floor_multiple"] for o in objects if o.get("cd_floor_multiple") is not None]
    ious = [o["iou_min"] for o in objects if o.get("iou_min") is not None]
    memory = [r["peak_memory_gb"] for r in good if r.get("peak_memory_gb") is not None]
    stats = {
        "observed_psnr": _stat([_value(r, "observed", "psnr") for r in good], _mean),
        "future_psnr": _stat([_value(r, "future", "psnr") for r in good], _mean),
        "future_cd": _stat([_value(r, "future", "cd_mm2") for r in good], _mean),
        "gaussian_cd": _stat(multiples, max),
        "iou": _stat(ious, min),
        "time": _stat([r["time_s"] for r in good], max),
        "memory": _stat(memory, max),
    }
    stats["memory"]["kinds"] = sorted({r.get("memory", "-") for r in good})
    for key, _title, op, target, _unit in TARGETS:
        stat = stats[key]
        met = _meets(stat["value"], op, target)
        if key in ("gaussian_cd", "iou"):
            stat["count"] = sum(bool(_meets(v, op, target)) for v in stat.pop("values"))
        else:
            stat.pop("values")
        stat.update(op=op, target=target, met=(met and not missing) if met is not None else None)
        stat["missing"] = missing
    return stats


def _stat(values: list, pick) -> dict:
    values = [v for v in values if v is not None and math.isfinite(v)]
    return {"value": pick(values) if values else None, "n": len(values), "values": values}


# --------------------------------------------------------------------------------------------
# the supervision ablation (paper table 3)


def ablation_summary(rows: list[dict]) -> dict | None:
    """Every variant on the scenes where all ran with every seed: per block and quantity the
    mean over scenes and seeds and the run-to-run spread (mean over scenes of the largest
    minus the smallest value over seeds); each object-wise variant against the scene-wise one
    with the same terms: the mean per-scene difference of the seed means, beside the spread
    of the two variants, the scenes where the difference exceeds both variants' spread there,
    and the Wilcoxon signed-rank p-value over the scenes. None without ablation runs."""
    methods = set(VARIANT_METHOD.values())
    variant_rows = [r for r in rows if r["method"] in methods - {"ours"}]
    if not variant_rows:
        return None
    seeds = sorted({r.get("seed", 0) for r in variant_rows})
    scenes = sorted({r["scene"] for r in variant_rows})
    runs = {(r["scene"], r["method"], r.get("seed", 0)): r for r in rows if _ok(r)}
    complete = [s for s in scenes if all((s, m, seed) in runs for m in methods for seed in seeds)]
    values = {
        (v, block, key, s): [_value(runs[(s, m, seed)], block, key) for seed in seeds]
        for v, m in VARIANT_METHOD.items()
        for block in BLOCKS
        for key, *_ in QUANTITIES
        for s in complete
    }
    spread = {k: _range(v) for k, v in values.items()}
    out: dict = {"seeds": seeds, "scenes": scenes, "complete": complete, "variants": {}}
    for v in VARIANT_METHOD:
        out["variants"][v] = {
            block: {
                key: {
                    "mean": _mean(x for s in complete for x in values[(v, block, key, s)]),
                    "spread": _mean(spread[(v, block, key, s)] for s in complete),
                }
                for key, *_ in QUANTITIES
            }
            for block in BLOCKS
        }
    out["differences"] = [
        _difference(obj, rival, block, key, complete, values, spread)
        for obj, _, granularity, terms in VARIANTS
        if granularity == "object"
        for rival, _, g, t in VARIANTS
        if g == "scene" and t == terms
        for block in BLOCKS
        for key, *_ in QUANTITIES
    ]
    return out


def _range(values: list) -> float | None:
    values = [v for v in values if v is not None]
    return max(values) - min(values) if len(values) > 1 else None


def _difference(obj, rival, block, key, complete, values, spread) -> dict:
    pairs, beyond = [], 0
    for s in complete:
        a, b = _mean(values[(obj, block, key, s)]), _mean(values[(rival, block, key, s)])
        if a is None or b is None:
            continue
        pairs.append((a, b))
        noise = [x for x in (spread[(obj, block, key, s)], spread[(rival, block, key, s)]) if x]
        beyond += bool(noise) and abs(a - b) > max(noise)
    noise = [spread[(v, block, key, s)] for v in (obj, rival) for s in complete]
    return {
        "object": obj,
        "scene": rival,
        "block": block,
        "key": key,
        "difference": _mean(a - b for a, b in pairs),
        "spread": _mean(noise),
        "beyond_spread": beyond,
        "n": len(pairs),
        "p": paired_p_value(pairs),
    }


def make_table(rows: list[dict], development: list[str] | tuple = ()) -> dict:
    """What table.json holds: the rows, table 1's summary and the ablation's."""
    summary = summarise(rows, development)
    return {"rows": rows, "summary": summary, "ablation": ablation_summary(rows)}


# --------------------------------------------------------------------------------------------
# markdown


def _num(value, key: str = "") -> str:
    if value is None:
        return "-"
    if key.startswith("psnr"):
        return f"{value:.2f}"
    if key in ("ssim", "iou"):
        return f"{value:.3f}"
    return f"{value:,.0f}" if abs(value) >= 100 else f"{value:.3g}"


def table_one(table: dict, block: str) -> list[str]:
    """Table 1 of one block: a row per quantity and method, a column per scene and the mean."""
    summary, cells = table["summary"], table_rows(table["rows"])
    scenes, development = summary["scenes"], summary.get("development") or []
    heads = [f"{s} (dev)" if s in development else s for s in scenes] + ["mean"]
    n_test = len(scenes) - len(development)
    if development:
        heads.append("test mean")
    lines = ["| metric | method | " + " | ".join(heads) + " |"]
    lines.append("|---|---|" + "---:|" * len(heads))
    for key, title, _ in QUANTITIES:
        for method in summary["methods"]:
            found = cells[method]
            values = [_value(found[s], block, key) if s in found else None for s in scenes]
            cells_text = [_num(v, key) for v in values]
            means = [(summary["means"][method][block][key], len(scenes))]
            if development:
                means.append((summary["test_means"][method][block][key], n_test))
            for mean, full in means:
                n = f" (n={mean['n']})" if mean["n"] != full else ""
                cells_text.append(_num(mean["value"], key) + n)
            lines.append(f"| {title} | {LABELS[method]} | " + " | ".join(cells_text) + " |")
    return lines


def stage_one(table: dict) -> list[str]:
    """Ours' Stage I per scene and object: worst-frame Gaussian Chamfer, the floor, the
    multiple and the worst-frame mask IoU; below it, the scenes whose Stage I skipped steps for
    a non-finite loss or gradient."""
    skipped = []
    lines = ["| scene | object | family | Gaussian CD, worst frame mm^2 | scene floor mm^2 |"]
    lines[0] += " multiple of the floor | mask IoU, worst frame |"
    lines.append("|---|---|---|---:|---:|---:|---:|")
    for scene, row in sorted(table_rows(table["rows"]).get("ours", {}).items()):
        stage1 = row.get("stage1") if _ok(row) else None
        if not stage1:
            continue
        if stage1.get("skipped_steps"):
            skipped.append(f"{scene} {stage1['skipped_steps']}")
        families = (row.get("data") or {}).get("materials") or []
        for k, o in stage1["per_object"].items():
            family = families[int(k) - 1] if 0 < int(k) <= len(families) else "-"
            cells = [
                _num(o["cd_mm2_max"]),
                _num(stage1["chamfer_floor_mm2"]),
                _num(o["cd_floor_multiple"]),
                _num(o["iou_min"], "iou"),
            ]
            lines.append(f"| {scene} | {k} | {family} | " + " | ".join(cells) + " |")
    if skipped:
        lines += [
            "",
            "Stage I steps skipped for a non-finite loss or gradient: " + ", ".join(skipped),
        ]
    return lines


def _target_value(s: dict, key: str, unit: str) -> str:
    if s["value"] is None:
        return "-"
    value = f"{_num(s['value'], key.replace('observed_', '').replace('future_', ''))}"
    value = f"{value} {unit}".strip()
    if "count" in s:
        value += f" ({s['count']} of {s['n']} objects within)"
    if key == "memory":
        value += f" ({', '.join(s['kinds'])})"
    return value


def target_lines(summary: dict) -> list[str]:
    """The targets of ours; with development scenes, judged on the test scenes, and the value
    over all scenes beside."""
    development = summary.get("development") or []
    lines = []
    if development:
        n_test = len(summary["scenes"]) - len(development)
        lines += [
            f"Judged on the {n_test} test scenes; settings were chosen on the development "
            f"scenes {', '.join(development)} (marked dev above).",
            "",
            "| quantity (ours) | n | value, test scenes | all scenes | target | status |",
            "|---|---|---|---|---|---|",
        ]
    else:
        lines += ["| quantity (ours) | n | value | target | status |", "|---|---|---|---|---|"]
    for key, title, op, target, unit in TARGETS:
        s = summary["targets"][key]
        value = _target_value(s, key, unit)
        if development:
            value += " | " + _target_value(summary["targets_all"][key], key, unit)
        if s["value"] is None:
            status = "not measured"
        else:
            status = "met" if s["met"] else "not met"
            if s["missing"]:
                n_missing = len(s["missing"])
                scenes = "scene" if n_missing == 1 else "scenes"
                status += f" ({n_missing} {scenes} without a run: {', '.join(s['missing'])})"
        goal = f"{op} {target:g} {unit}".strip()
        lines.append(f"| {title} | {s['n']} | {value} | {goal} | {status} |")
    return lines


def runtime_lines(summary: dict) -> list[str]:
    """Wall time and peak memory per method, and the median time of each stage (I
    reconstruction, II lifting, III identification, evaluation; - where no run recorded it)."""
    stages = " / ".join(STAGE_NAMES.values())
    lines = ["| method | runs | median wall time s | longest s | median peak GB | largest GB |"]
    lines[0] += f" memory | median s, stage {stages} |"
    lines.append("|---|---:|---:|---:|---:|---:|---|---|")
    for method, r in summary["runtime"].items():
        cells = [str(r["n"]), _num(r["median_time_s"]), _num(r["max_time_s"])]
        cells += [_num(r["median_peak_gb"]), _num(r["max_peak_gb"]), ", ".join(r["memory"])]
        per_stage = r.get("median_stage_s") or {}
        cells.append(" / ".join(_num(per_stage.get(stage)) for stage in STAGE_NAMES))
        lines.append(f"| {LABELS[method]} | " + " | ".join(cells) + " |")
    return lines


def ablation_lines(ablation: dict) -> list[str]:
    """Means with the run-to-run spread per variant, then object- against scene-wise."""
    complete = ablation["complete"]
    seeds = ", ".join(str(s) for s in ablation["seeds"])
    lines = [
        f"Supervision ablation (paper table 3): {len(complete)} scenes with every variant and "
        f"every Stage I seed ({seeds}): {', '.join(complete) or 'none'}. Each cell: mean over "
        "scenes and seeds +- the run-to-run spread (mean over scenes of the largest minus the "
        "smallest value over the seeds).",
        "",
    ]
    head = [f"{b} {title}" for b in BLOCKS for _, title, _ in QUANTITIES]
    lines += ["| losses | " + " | ".join(head) + " |", "|---" + "|---:" * len(head) + "|"]
    for v, blocks in ablation["variants"].items():
        cells = [
            f"{_num(blocks[b][k]['mean'], k)} +- {_num(blocks[b][k]['spread'], k)}"
            for b in BLOCKS
            for k, *_ in QUANTITIES
        ]
        lines.append(f"| {VARIANT_LABEL[v]} | " + " | ".join(cells) + " |")
    lines += [
        "",
        "Object-wise minus scene-wise (same terms), mean over scenes of the seed means, beside "
        "the two variants' run-to-run spread; scenes beyond: where the difference exceeds both "
        "variants' spread on that scene; p: two-sided Wilcoxon signed-rank over the scenes "
        "(none below 6 scenes).",
        "",
        "| object-wise | against | quantity | difference | spread | scenes beyond | p |",
        "|---|---|---|---:|---:|---:|---:|",
    ]
    titles = {k: t for k, t, _ in QUANTITIES}
    for d in ablation["differences"]:
        p = "-" if d["p"] is None else f"{d['p']:.2g}"
        cells = [
            VARIANT_LABEL[d["object"]],
            VARIANT_LABEL[d["scene"]],
            f"{d['block']} {titles[d['key']]}",
            _num(d["difference"], d["key"]),
            _num(d["spread"], d["key"]),
            f"{d['beyond_spread']} of {d['n']}",
            p,
        ]
        lines.append("| " + " | ".join(cells) + " |")
    return lines


def markdown(table: dict) -> str:
    """Table 1 (observed, future), ours' Stage I per object, the targets, runtime and memory,
    the ablation, and the failed runs."""
    summary = table["summary"]
    lines = ["Observed frames:", "", *table_one(table, "observed"), ""]
    lines += ["Future frames:", "", *table_one(table, "future"), ""]
    lines += ["(PSNR in dB over the full images of every camera, CD in mm^2, EMD in mm.)", ""]
    lines += ["Stage I of ours per object:", "", *stage_one(table), ""]
    lines += [*target_lines(summary), "", *runtime_lines(summary)]
    if table.get("ablation"):
        lines += ["", *ablation_lines(table["ablation"])]
    if summary["failed"]:
        lines += ["", "Failed runs:", ""]
        lines += [f"- {f['scene']} {LABELS[f['method']]}: {f['error']}" for f in summary["failed"]]
    return "\n".join(lines) + "\n"


# --------------------------------------------------------------------------------------------
# docs/RESULTS.md


def effective_overrides(overrides: list[str]) -> list[str]:
    """``overrides`` as the recipe reader applies them: a later ``key=value`` replaces an earlier
    one of the same key (the tool's own defaults come first, the user's ``--set`` after)."""
    last = {o.split("=", 1)[0]: o for o in overrides}
    return list(last.values())


def settings_lines(rows: list[dict]) -> list[str]:
    """Each method's recipe and the overrides its runs had (every distinct set)."""
    out = []
    for method in [*LABELS, *(m for m in VARIANT_METHOD.values() if m not in LABELS)]:
        found = [r for r in rows if r["method"] == method and "overrides" in r]
        if not found:
            continue
        distinct = []
        for r in found:
            effective = effective_overrides(r["overrides"])
            if effective not in distinct:
                distinct.append(effective)
        sets = "; ".join(" ".join(f"`{o}`" for o in d) or "none" for d in distinct)
        label = LABELS.get(method, VARIANT_LABEL.get(method, method))
        out.append(f"{label}: {found[0].get('recipe', '-')}; overrides {sets}")
    return out


def data_text(rows: list[dict]) -> str:
    """The scenes: gi.data_description of one row per scene, their names and size."""
    per_scene = {r["scene"]: r for r in rows if r.get("data")}
    first = next(iter(per_scene.values()), {}).get("data", {})
    size = (
        f"{first.get('frames')} frames ({first.get('observed_frames')} observed), "
        f"{first.get('cameras')} cameras at {first.get('resolution')} px"
    )
    return (
        f"{gi.data_description(list(per_scene.values()))} (`mosiv data suite SCENES --source "
        f"genesis`): {', '.join(sorted(per_scene))}; {size}"
    )


#: how each row of a merged table was made (the merge only reads them)
PART_COMMAND = (
    "python benchmarks/genesis_video.py --scenes SCENES --out OUT --only SCENE --method METHOD "
    "--part"
)


def section_text(table: dict, *, command: str, date: str, merged: bool = False) -> str:
    """The RESULTS.md section: what was run, on what, and the tables. ``merged``: the table was
    merged from --part runs, whose command (with each run's overrides as --set) comes first."""
    rows = table["rows"]
    devices = sorted({r.get("device", "unknown") for r in rows if _ok(r)})
    codes = sorted({r["code"] for r in rows if r.get("code")})
    intro = (
        "`benchmarks/genesis_video.py` runs the paper's table 1 from the recorded videos and "
        "masks of scenes the Genesis engine made: ours, the discrete-library baseline "
        "(OmniPhysGS-RGB, with and without the true material family) on the same from-video "
        "Stages I-II, and CoupNeRF*, one process per scene and method, each end to end."
    )
    runs = f"`{PART_COMMAND}` per scene and method, the overrides below as `--set`, then "
    items = [
        f"Command: {runs if merged else ''}`{command}`",
        f"Machine: {', '.join(devices) or 'unknown'}. Date {date}. Code {', '.join(codes) or 'unknown'}.",
        f"Data: {data_text(rows)}.",
        *(f"Settings of {line}." for line in settings_lines(rows)),
    ]
    wrapped = [gi._fill(i, initial_indent="- ", subsequent_indent="  ") for i in items]
    head = f"## {SECTION}\n\n{gi._fill(intro)}\n\n" + "\n".join(wrapped) + "\n\n"
    return head + markdown(table)


def place_section(text: str, body: str) -> str:
    """``text`` with the section replaced in place, or, when it has none, inserted after the
    ``## AFTER`` section (before the next level-2 heading), else at the end."""
    lines = text.splitlines(keepends=True)
    if any(line.strip() == f"## {SECTION}" for line in lines):
        return gi.replace_section(text, body, title=SECTION)
    heads = [i for i, line in enumerate(lines) if line.startswith("## ")]
    after = next((i for i in heads if lines[i].strip() == f"## {AFTER}"), None)
    following = next((i for i in heads if after is not None and i > after), None)
    if following is None:
        return text.rstrip("\n") + "\n\n" + body.rstrip("\n") + "\n"
    return "".join(lines[:following]) + body.rstrip("\n") + "\n\n" + "".join(lines[following:])


def write_results(path: Path, table: dict, *, command: str, merged: bool = False) -> None:
    date = datetime.date.today().isoformat()
    text = path.read_text() if path.is_file() else "# Results\n"
    body = section_text(table, command=command, date=date, merged=merged)
    path.write_text(place_section(text, body))
