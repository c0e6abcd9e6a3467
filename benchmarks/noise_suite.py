"""Sensitivity to reconstruction noise (paper appendix, tables of i.i.d. and shared noise).

The oracle reconstructor's ground-truth points are perturbed before identification with
Gaussian noise of standard deviation alpha * (xyz_max - xyz_min) per object: i.i.d. (every
point its own offset, every frame) or shared (one offset per object and frame). For each kind
and level, the same scene is identified and scored (observed and future CD and EMD, parameter
errors); alpha = 0 is the noise-free reference. Writes ``table.json``, ``table.md`` and
``noise.png`` (future CD and elastic-E error against alpha) into the output folder; a rerun
reuses finished runs.

    python benchmarks/noise_suite.py --recipe recipes/quickstart.yaml --out runs/noise_suite \\
        --jobs 2 scene.source.n_frames=14 scene.source.observed_frames=9
    python benchmarks/noise_suite.py --recipe recipes/paper.yaml --out runs/noise_paper  # GPU

PSNR and SSIM need images of the prediction, which the oracle path (no Gaussians) does not
have; the paper's noise tables perturb Gaussians and report them.

That is the own-synth mode: one scene the recipe generates. With ``--scenes DIR`` (a suite
folder of ``mosiv data suite DIR --source genesis --ranges wide``) every Genesis scene is
identified as ``benchmarks/genesis_identify.py`` does (``recipes/genesis_oracle.yaml``), at each
noise setting, one process per (scene, setting) (``--part``; ``--merge`` builds the table), and
``--write-results`` writes the section "Sensitivity to reconstruction noise on Genesis scenes";
see ``benchmarks/genesis_noise.py``:

    python benchmarks/noise_suite.py --scenes runs/genesis --out runs/genesis_noise \\
        --jobs 8 --gpus-per-task 0.125 --write-results docs/RESULTS.md
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
import traceback
from pathlib import Path

from identify_suite import _fmt, _timed, errors_of

from mosiv_framework.logs import configure_logging, level_from_flags
from mosiv_framework.scale import Task, run_tasks
from mosiv_framework.scale.flags import add_scale_flags, scale_options

#: the paper's noise levels (alpha, relative to each object's extent)
LEVELS = (0.005, 0.02, 0.05)
KINDS = {"iid": "noise_iid_rel", "shared": "noise_shared_rel"}
#: (metrics block, key, column title)
COLUMNS = (
    ("observed", "cd_mm2", "observed CD mm^2"),
    ("observed", "emd_mm", "observed EMD mm"),
    ("future", "cd_mm2", "future CD mm^2"),
    ("future", "emd_mm", "future EMD mm"),
)
#: parameter errors tabulated (errors_of keys): median over the scene's objects
ERRORS = (("E_pct", "E % (elastic)"), ("yield_pct", "yield %"), ("v0_pct", "v0 %"))


def _run_one(job: dict) -> dict:
    """One noise setting, in a worker process; returns its scores or its error."""
    import torch

    from mosiv_framework.pipeline import run_pipeline
    from mosiv_framework.recipes import load_recipe

    torch.set_num_threads(job["threads"])
    run_dir = Path(job["run_dir"])
    try:
        cfg = load_recipe(Path(job["recipe"]), job["overrides"])
        marker = run_dir / "stages" / "identify.json"
        before = marker.read_text() if marker.is_file() else None
        started = time.perf_counter()
        metrics = run_pipeline(cfg, run_dir=run_dir)
        elapsed = _timed(run_dir, before, time.perf_counter() - started)
    except Exception as exc:  # one failed setting must not lose the others' rows
        traceback.print_exc()
        return {"error": f"{type(exc).__name__}: {exc}"}
    row = {f"{block}_{key}": (metrics.get(block) or {}).get(key) for block, key, _ in COLUMNS}
    errors = errors_of(metrics)
    row.update({key: errors[key] for key, _ in ERRORS})
    row.update({"time_s": elapsed, "peak_memory_gb": metrics.get("peak_memory_gb")})
    return row


def settings(levels) -> list[tuple[str, float]]:
    """(kind, alpha) of every run: the reference ("none", 0) first, then every kind at every
    level."""
    return [("none", 0.0)] + [(kind, alpha) for kind in KINDS for alpha in levels]


def setting_name(kind: str, alpha: float) -> str:
    """The run's folder name: "reference", or "iid-0.02" (kind and alpha)."""
    return "reference" if kind == "none" else f"{kind}-{alpha:g}"


def noise_overrides(kind: str, alpha: float) -> list[str]:
    """The recipe overrides that add the noise of ``kind`` at ``alpha`` to the oracle's points."""
    return [] if kind == "none" else [f"reconstructor.{KINDS[kind]}={alpha}"]


def jobs_for(*, recipe: Path, out: Path, extra: list[str], threads: int, levels) -> list[dict]:
    """The reference (alpha 0) first, then every kind at every level; one shared scene."""
    jobs = []
    for kind, alpha in settings(levels):
        name = setting_name(kind, alpha)
        noise = noise_overrides(kind, alpha)
        overrides = [f"scene.path={out / 'scene'}", *extra, *noise, f"output.dir={out / name}"]
        jobs.append(
            {
                "name": name,
                "kind": kind,
                "alpha": alpha,
                "recipe": str(recipe),
                "overrides": overrides,
                "run_dir": str(out / name),
                "threads": threads,
            }
        )
    return jobs


def run_suite(*, recipe: Path, out: Path, extra: list[str], threads: int, levels, scale: dict):
    """Every noise setting as a task of its own (``run_tasks`` with ``scale``, the keyword
    arguments of the ``--jobs``/``--ray-address``/``--gpus-per-task`` flags)."""
    out.mkdir(parents=True, exist_ok=True)
    table = out / "table.json"
    rows = {r["name"]: r for r in json.loads(table.read_text())["rows"]} if table.is_file() else {}
    todo = jobs_for(recipe=recipe, out=out, extra=extra, threads=threads, levels=levels)
    # the reference runs alone first: it generates the scene every other setting reads
    by_name = {job["name"]: job for job in todo}

    def record(outcome) -> None:
        job = by_name[outcome.name]
        result = outcome.result if outcome.ok else {"error": repr(outcome.error)}
        rows[job["name"]] = {"name": job["name"], "kind": job["kind"], "alpha": job["alpha"]}
        rows[job["name"]].update(result)
        print(f"[noise-suite] {job['name']}: {_brief(result)}", flush=True)
        table.write_text(json.dumps({"rows": list(rows.values())}, indent=2) + "\n")

    for phase in (todo[:1], todo[1:]):
        run_tasks([Task(j["name"], _run_one, (j,)) for j in phase], on_done=record, **scale)
    ordered = sorted(rows.values(), key=lambda r: (r["kind"] != "none", r["kind"], r["alpha"]))
    result = {"recipe": str(recipe), "overrides": extra, "rows": ordered}
    table.write_text(json.dumps(result, indent=2) + "\n")
    (out / "table.md").write_text(markdown(ordered))
    plot(ordered, out / "noise.png")
    return result


def _brief(result: dict) -> str:
    if "error" in result:
        return f"failed: {result['error']}"
    return (
        f"CD {_fmt(result['observed_cd_mm2'])} / {_fmt(result['future_cd_mm2'])} mm^2 "
        f"(observed / future), {result['time_s']:.0f} s"
    )


def _median(values) -> float | None:
    return statistics.median(values) if values else None


def markdown(rows: list[dict]) -> str:
    head = ["noise", "alpha"] + [title for *_, title in COLUMNS]
    head += [f"{title} (median)" for _, title in ERRORS] + ["time s"]
    lines = ["| " + " | ".join(head) + " |", "|---" * len(head) + "|"]
    for r in rows:
        if "error" in r:
            lines.append(f"| {r['kind']} | {r['alpha']:g} | failed: {r['error']} |")
            continue
        cells = [r["kind"], f"{r['alpha']:g}"]
        cells += [_fmt(r[f"{block}_{key}"]) for block, key, _ in COLUMNS]
        cells += [_fmt(_median(r[key])) for key, _ in ERRORS] + [_fmt(r["time_s"])]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def plot(rows: list[dict], path: Path, data: str | None = None) -> None:
    """Future CD and the elastic-E error against alpha, one line per noise kind; ``data``
    (where the scenes and runs come from) goes under the title."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    good = [r for r in rows if "error" not in r]
    reference = next((r for r in good if r["kind"] == "none"), None)
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for kind in KINDS:
        mine = sorted((r for r in good if r["kind"] == kind), key=lambda r: r["alpha"])
        if reference is not None:
            mine = [reference] + mine
        alphas = [r["alpha"] for r in mine]
        axes[0].plot(alphas, [r["future_cd_mm2"] for r in mine], "o-", label=kind)
        axes[1].plot(alphas, [_median(r["E_pct"]) or 0.0 for r in mine], "o-", label=kind)
    axes[0].set_ylabel("future CD (mm^2)")
    axes[0].set_yscale("log")
    axes[1].set_ylabel("elastic E error (%, median)")
    for ax in axes:
        ax.set_xlabel("noise level alpha (x object extent)")
        ax.legend()
    title = "sensitivity to reconstruction noise (oracle points perturbed)"
    fig.suptitle(title if data is None else f"{title}\n{data}", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


#: flags of the Genesis mode only (given without --scenes or --merge they are refused)
GENESIS_FLAGS = ("only", "set", "write_results", "part", "noise", "alpha")


def parse_args(argv: list[str]) -> argparse.Namespace:
    """Both modes' flags; the mode's checks (``check_mode``) follow."""
    parser = argparse.ArgumentParser(
        description=__doc__.splitlines()[0],
        epilog="Own-synth mode: --recipe, --out, --levels, --threads and key=value overrides. "
        "Genesis mode (with --scenes, or --merge): benchmarks/genesis_noise.py.",
    )
    parser.add_argument(
        "--recipe",
        type=Path,
        default=None,
        help="default: recipes/paper.yaml, with --scenes recipes/genesis_oracle.yaml",
    )
    parser.add_argument("--out", type=Path, default=None, help="default: runs/noise_suite")
    add_scale_flags(parser, "settings")
    parser.add_argument("--threads", type=int, default=None, help="torch threads per run (1)")
    parser.add_argument(
        "--levels", default=",".join(f"{a:g}" for a in LEVELS), help="comma-separated alphas"
    )
    genesis = parser.add_argument_group("Genesis mode")
    genesis.add_argument("--scenes", type=Path, help="a `mosiv data suite --source genesis` folder")
    genesis.add_argument("--only", default=None, help="comma-separated scene names (E-P,...)")
    genesis.add_argument("--set", action="append", default=[], help="key=value recipe override")
    genesis.add_argument("--write-results", type=Path, default=None, help="e.g. docs/RESULTS.md")
    genesis.add_argument("--merge", action="store_true", help="only merge OUT/parts into tables")
    genesis.add_argument("--part", action="store_true", help="run one scene (--only) and noise")
    genesis.add_argument("--noise", choices=("none", *KINDS), help="with --part: the noise kind")
    genesis.add_argument("--alpha", type=float, help="with --part: the noise level (0 for none)")
    parser.add_argument("overrides", nargs="*", help="own-synth: key=value recipe overrides")
    args = parser.parse_args(argv)
    try:
        args.levels = tuple(float(a) for a in args.levels.split(",") if a.strip())
    except ValueError:
        parser.error(f"--levels {args.levels!r}: give comma-separated numbers")
    if not args.levels or any(a <= 0 for a in args.levels):
        parser.error(f"--levels {','.join(f'{a:g}' for a in args.levels)}: every level must be > 0")
    check_mode(parser, args)
    return args


def check_mode(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """Refuse flags of the other mode, so a run never silently ignores one."""
    args.genesis = args.scenes is not None or args.merge
    if args.genesis:
        if args.overrides:
            parser.error(
                f"{args.overrides[0]}: with --scenes give recipe overrides as --set key=value"
            )
        if args.threads is not None:
            parser.error("--threads: own-synth mode only (each Genesis run is a process)")
        if args.out is None:
            parser.error("--out is required with --scenes or --merge")
        return
    given = [
        f"--{f.replace('_', '-')}"
        for f in GENESIS_FLAGS
        if getattr(args, f) not in (None, False, [])
    ]
    if given:
        parser.error(f"{given[0]}: only with --scenes (the Genesis mode)")
    args.recipe = args.recipe or Path("recipes/paper.yaml")
    args.out = args.out or Path("runs/noise_suite")
    args.threads = 1 if args.threads is None else args.threads


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    args = parse_args(argv)
    # the pipeline's progress (stages, global candidates) is logged at INFO: show it
    configure_logging(level_from_flags())
    if args.genesis:
        import genesis_noise

        return genesis_noise.run(args, argv)
    result = run_suite(
        recipe=args.recipe,
        out=args.out,
        extra=args.overrides,
        scale=scale_options(args),
        threads=args.threads,
        levels=args.levels,
    )
    print(markdown(result["rows"]))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
