"""What ``benchmarks/suite_scaling.py`` measured, as numbers, a verdict, a plot and markdown.

Two questions, each answered from the runs alone:

- **Throughput.** Each configuration ran the same identifications (every scene, ``repeats``
  times). Its runs per hour are ``runs / wall time``; the speed-up is that throughput over the
  smallest configuration's, and the scaling efficiency is the speed-up divided by the ratio of
  their device counts (1.0: every added GPU did as much as the first ones).
- **Same results.** Identification on a GPU is not bit-reproducible (float atomics), so two
  runs of one scene differ a little even on one GPU. Each configuration ran every scene twice
  (or more): the differences between those repeats are the run-to-run spread. The
  differences between configurations (the same scene and repeat on 1 and on N GPUs) should be
  drawn from the same distribution. A one-sided Mann-Whitney U test asks whether they are
  larger, for each quantity compared: the future and the observed Chamfer distance and every
  identified parameter, each as the symmetric relative difference ``|a - b| / ((|a| + |b|) /
  2)``. The results match when no group's test rejects at 5 % family-wise (Bonferroni: each
  of the three groups at 5 % / 3), so that identical distributions are called different in at
  most 5 % of suites.
"""

from __future__ import annotations

import statistics
from itertools import combinations

#: the quantity groups compared between runs, as named in the table
GROUPS = ("future CD", "observed CD", "parameters")

#: family-wise error rate of the agreement verdict; each group's test runs at ALPHA / 3
ALPHA = 0.05


def symmetric_difference(a: float, b: float) -> float:
    """``|a - b|`` relative to the pair's mean magnitude; 0 where both are 0."""
    scale = (abs(a) + abs(b)) / 2.0
    return abs(a - b) / scale if scale > 0 else 0.0


def quantities(row: dict) -> dict[str, dict[str, float]]:
    """The comparable numbers of one run's table row (a ``genesis_identify`` row), by group:
    ``{"future CD": {"": cd}, "observed CD": {"": cd}, "parameters": {"1.E": value, ...}}``.
    A failed row (``error``) has none."""
    if "error" in row:
        return {}
    out: dict[str, dict[str, float]] = {g: {} for g in GROUPS}
    for group, key in (("future CD", "future_cd_mm2"), ("observed CD", "observed_cd_mm2")):
        if row.get(key) is not None:
            out[group][""] = float(row[key])
    for obj, entry in (row.get("objects") or {}).items():
        for name, param in (entry.get("params") or {}).items():
            if param.get("value") is not None and not isinstance(param["value"], list):
                out["parameters"][f"{obj}.{name}"] = float(param["value"])
    return out


def differences(first: dict, second: dict) -> dict[str, list[float]]:
    """Per group, the symmetric differences of every quantity that both rows have."""
    a, b = quantities(first), quantities(second)
    out: dict[str, list[float]] = {g: [] for g in GROUPS}
    for group in GROUPS:
        shared = sorted(set(a.get(group, {})) & set(b.get(group, {})))
        out[group] = [symmetric_difference(a[group][k], b[group][k]) for k in shared]
    return out


def _pool(into: dict[str, list[float]], more: dict[str, list[float]]) -> None:
    for group, values in more.items():
        into.setdefault(group, []).extend(values)


def repeat_spread(configs: dict[str, dict]) -> dict[str, list[float]]:
    """The run-to-run spread: per group, the differences between repeats of one scene within
    one configuration, pooled over scenes and configurations."""
    pooled: dict[str, list[float]] = {g: [] for g in GROUPS}
    for config in configs.values():
        by_scene: dict[str, dict[int, dict]] = {}
        for task in config["tasks"]:
            if task.get("row") is not None:
                by_scene.setdefault(task["scene"], {})[task["repeat"]] = task["row"]
        for repeats in by_scene.values():
            for r1, r2 in combinations(sorted(repeats), 2):
                _pool(pooled, differences(repeats[r1], repeats[r2]))
    return pooled


def cross_differences(configs: dict[str, dict], base: str) -> dict[str, list[float]]:
    """Per group, the differences between configuration ``base`` and every other one, on the
    same scene and repeat."""
    rows = {
        label: {(t["scene"], t["repeat"]): t["row"] for t in c["tasks"] if t.get("row")}
        for label, c in configs.items()
    }
    pooled: dict[str, list[float]] = {g: [] for g in GROUPS}
    for label in rows:
        if label == base:
            continue
        for key in sorted(set(rows[base]) & set(rows[label])):
            _pool(pooled, differences(rows[base][key], rows[label][key]))
    return pooled


def agreement(configs: dict[str, dict], base: str) -> dict[str, dict]:
    """Per group: the median repeat and cross differences, their counts, the one-sided
    Mann-Whitney p-value (cross larger than repeat) and ``match`` (p >= ``ALPHA`` / the number
    of groups; None where either side has fewer than three differences)."""
    from scipy.stats import mannwhitneyu

    spread, cross = repeat_spread(configs), cross_differences(configs, base)
    out = {}
    for group in GROUPS:
        rep, crs = spread[group], cross[group]
        entry = {
            "repeat_median": statistics.median(rep) if rep else None,
            "cross_median": statistics.median(crs) if crs else None,
            "repeat_n": len(rep),
            "cross_n": len(crs),
            "p_value": None,
            "match": None,
        }
        if len(rep) >= 3 and len(crs) >= 3:
            p = float(mannwhitneyu(crs, rep, alternative="greater").pvalue)
            entry["p_value"], entry["match"] = p, p >= ALPHA / len(GROUPS)
        out[group] = entry
    return out


def throughput(configs: dict[str, dict]) -> list[dict]:
    """One entry per configuration, by device count: runs, wall time, runs per hour, the
    speed-up and scaling efficiency against the smallest count, the tasks Ray retried and
    those that failed, and the median run's own wall time."""
    ordered = sorted(configs.values(), key=lambda c: c["count"])
    base = ordered[0]
    base_rate = len(base["tasks"]) / base["wall_s"]
    out = []
    for config in ordered:
        rate = len(config["tasks"]) / config["wall_s"]
        speedup = rate / base_rate
        # a run's own wall time (its row's), not the task's, which counts its wait in the queue
        times = [t["row"]["time_s"] for t in config["tasks"] if (t.get("row") or {}).get("time_s")]
        out.append(
            {
                "label": config["label"],
                "count": config["count"],
                "unit": config["unit"],
                "slots": config["slots"],
                "runs": len(config["tasks"]),
                "wall_s": config["wall_s"],
                "runs_per_hour": 3600.0 * rate,
                "speedup": speedup,
                "efficiency": speedup / (config["count"] / base["count"]),
                "retried": sorted(
                    f"{t['name']} ({t['attempts'] - 1}x)"
                    for t in config["tasks"]
                    if t.get("attempts", 1) > 1
                ),
                "failed": sorted(t["name"] for t in config["tasks"] if not t.get("ok", True)),
                "median_task_s": statistics.median(times) if times else None,
            }
        )
    return out


def _num(value: float | None, digits: int = 3) -> str:
    return "-" if value is None else f"{value:.{digits}g}"


def markdown(report: dict) -> str:
    """The throughput table and the agreement table of ``report`` (``suite_scaling``'s)."""
    unit = report["throughput"][0]["unit"].upper()
    lines = [
        f"| {unit}s | runs at once | runs | wall time | scenes identified per hour | speed-up | "
        "scaling efficiency | median run | retried by Ray | failed |",
        "|---:|---:|---:|---:|---:|---:|---:|---:|---|---|",
    ]
    for t in report["throughput"]:
        lines.append(
            f"| {t['count']} | {t['slots']} | {t['runs']} | {t['wall_s']:.0f} s | "
            f"{t['runs_per_hour']:.0f} | {t['speedup']:.2f}x | {t['efficiency']:.0%} | "
            f"{_num(t['median_task_s'], 3)} s | {', '.join(t['retried']) or 'none'} | "
            f"{', '.join(t['failed']) or 'none'} |"
        )
    lines += [
        "",
        f"| quantity | spread: repeats in one configuration (median, n) | {unit}s 1 vs N "
        "(median, n) | Mann-Whitney p (N larger) | within the spread |",
        "|---|---:|---:|---:|---|",
    ]
    for group, a in report["agreement"].items():
        verdict = {True: "yes", False: "**no**", None: "too few runs"}[a["match"]]
        lines.append(
            f"| {group} | {_pct(a['repeat_median'])} ({a['repeat_n']}) | "
            f"{_pct(a['cross_median'])} ({a['cross_n']}) | {_num(a['p_value'], 2)} | {verdict} |"
        )
    return "\n".join(lines) + "\n"


def _pct(value: float | None) -> str:
    return "-" if value is None else f"{100 * value:.2g} %"


def plot(report: dict, path) -> None:
    """Runs per hour against the device count, with the ideal line through the smallest
    count, and the efficiency written beside each point."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = report["throughput"]
    counts = [t["count"] for t in rows]
    rates = [t["runs_per_hour"] for t in rows]
    fig, ax = plt.subplots(figsize=(5, 3.6))
    ideal = [rates[0] * c / counts[0] for c in counts]
    ax.plot(counts, ideal, "--", color="0.6", label="ideal (linear)")
    ax.plot(counts, rates, "o-", color="C0", label="measured")
    for c, r, t in zip(counts, rates, rows):
        ax.annotate(f"{t['efficiency']:.0%}", (c, r), textcoords="offset points", xytext=(6, -12))
    unit = rows[0]["unit"].upper()
    ax.set_xlabel(f"{unit}s")
    ax.set_ylabel("scenes identified per hour")
    ax.set_xticks(counts)
    ax.set_title(report.get("title", "suite scaling"), fontsize=9)
    ax.legend(loc="upper left", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
