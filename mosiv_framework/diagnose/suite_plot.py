"""One figure of a scored diagnosis suite (``suite.png``): per entry, how strong its residual
was, whether the verdict was right, how close the fitted coefficient came and how much the
accepted term cut the future error, with the targets (coefficient error at most 15 %, future
error at least halved) drawn in."""

from __future__ import annotations

from pathlib import Path

from mosiv_framework.diagnose.suite import entry_group

#: the targets, drawn as reference lines
TARGET_COEFFICIENT_ERROR = 0.15
TARGET_FUTURE_REDUCTION = 0.5
#: coefficient errors below this are drawn at it (an exact fit has no place on a log axis)
SMALLEST_DRAWN_ERROR = 1e-3


def _data_line(summary: dict) -> str:
    """Which suite the figure shows (``suite.suite_selection``'s source and split)."""
    source, split = summary.get("source") or "synth", summary.get("split")
    made = "the Genesis engine" if source == "genesis" else "mosiv-synth (warp-mpm)"
    which = f"{split} split of the {source} suite" if split else f"{source} suite"
    return f"data: the {which}, scenes made by {made}, oracle geometry"


def plot_suite(summary: dict, path: str | Path) -> Path:
    """Write the figure of ``summary`` (``suite.summarise``'s output) to ``path``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

    scores = summary["scores"]
    if not scores:
        raise ValueError(f"no scored entries to plot into {path}")
    # each row says what the diagnosis named: the accepted term, or its verdict
    names = [f"{s['name']}: {s['accepted'] or s['verdict']}" for s in scores]
    rows = list(range(len(scores)))[::-1]  # first entry at the top
    colours = ["tab:green" if s["correct"] else "tab:red" for s in scores]
    markers = {"concealed": "o", "control": "s", "outside": "D"}

    fig, axes = plt.subplots(
        1, 3, figsize=(13, 0.32 * len(scores) + 1.6), sharey=True, constrained_layout=True
    )
    snr_ax, coef_ax, future_ax = axes
    for row, s, colour in zip(rows, scores, colours):
        snr_ax.scatter(
            max(s["signal_to_noise"], 1e-3),
            row,
            color=colour,
            marker=markers[entry_group(s["name"], s["concealed"])],
        )
        if s["coefficient_error"] is not None:
            coef_ax.scatter(
                max(s["coefficient_error"], SMALLEST_DRAWN_ERROR), row, color=colour, marker="o"
            )
        law_future = s["extra"].get("law_future_reduction")
        if s["future_reduction"] is not None:
            future_ax.barh(row, 100 * s["future_reduction"], color=colour, height=0.6)
        elif law_future is not None:  # the discovered law, tested as a model, not accepted
            future_ax.barh(
                row, 100 * law_future, height=0.6, color="none", edgecolor="grey", hatch="//"
            )
    for log_ax in (snr_ax, coef_ax):
        # the minor ticks' labels overlap once a log axis spans less than a decade or two
        log_ax.set_xscale("log")
        log_ax.xaxis.set_major_locator(LogLocator(base=10, subs=(1.0, 2.0, 5.0)))
        log_ax.xaxis.set_minor_formatter(NullFormatter())
    snr_ax.xaxis.set_major_formatter(FuncFormatter(lambda x, _: f"{x:g}"))
    coef_ax.xaxis.set_major_formatter(FuncFormatter(lambda x, _: f"{100 * x:g} %"))
    snr_ax.axvline(3.0, color="grey", ls=":", lw=1)
    snr_ax.set_xlabel("residual / noise floor (SNR); square: control, diamond: outside")
    snr_ax.set_yticks(rows, names, fontsize=8)
    coef_ax.axvline(TARGET_COEFFICIENT_ERROR, color="grey", ls="--", lw=1)
    coef_ax.set_xlabel("coefficient error (target <= 15 %)")
    future_ax.axvline(100 * TARGET_FUTURE_REDUCTION, color="grey", ls="--", lw=1)
    future_ax.set_xlabel(
        "future Chamfer reduction, % (target >= 50 %)\nhatched: discovered law, not accepted"
    )
    reductions = [
        100 * r
        for s in scores
        for r in (s["future_reduction"], s["extra"].get("law_future_reduction"))
        if r is not None
    ]
    future_ax.set_xlim(min([0.0, *reductions]) - 5, 105)  # a term can make the future worse

    def pct(x):
        return "-" if x is None else f"{100 * x:.0f} %"

    fig.suptitle(
        f"{_data_line(summary)}\n"
        f"correct first {pct(summary['correct_first_rate'])}, "
        f"false controls {pct(summary['control_false_discovery_rate'])}, "
        f"outside unexplained {pct(summary['outside_reported_unexplained_rate'])}, "
        f"median coef. error {pct(summary['median_coefficient_error'])}, "
        f"median future reduction {pct(summary['median_future_reduction'])} "
        "(green: right verdict, red: wrong)",
        fontsize=9,
    )
    path = Path(path)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
