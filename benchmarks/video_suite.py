"""From-video benchmark: the whole pipeline on the identification suite's scenes, and the
paper's supervision ablation (table 3).

For each material pair of ``identify_suite.PAIRS`` (the same scenes: same recipe source, same
seeds), Stage I fits object-aware dynamic Gaussians to the videos and masks, Stage II lifts them
to particles, and identification runs with six loss variants that share those two stages:
object-wise or scene-wise supervision, each with Chamfer + silhouette (the paper's method when
object-wise), Chamfer alone, silhouette alone. Every run is scored against the recorded videos
(observed and future PSNR, SSIM, full images rendered through the lifted Gaussians) and the
ground-truth points (Chamfer ``cd_mm2``, EMD ``emd_mm``). Writes ``table.json``, ``table.md``
and ``ablation.png`` into ``--out``; a rerun into the same folder reuses finished stages.

    python benchmarks/video_suite.py --recipe recipes/video_quickstart.yaml \
        --out runs/video_suite --jobs 2 scene.source.n_frames=14 scene.source.observed_frames=9

The from-video targets: mean observed PSNR >= 30 dB and mean future PSNR >= 27 dB over
the scenes (paper: 30.5 and 28.3), object-wise losses better than scene-wise ones.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import socket
import statistics
import time
import traceback
from contextlib import contextmanager, nullcontext
from pathlib import Path

from identify_suite import LETTERS, PAIRS, _fmt, _timed, errors_of, select_pairs

from mosiv_framework.logs import configure_logging, level_from_flags
from mosiv_framework.scale import Task, run_tasks
from mosiv_framework.scale.flags import add_scale_flags, scale_options

#: (folder, label, granularity, loss terms): the object-wise Chamfer + silhouette is ours
VARIANTS = (
    ("object-cd-sil", "object-wise CD + silhouette (ours)", "object", ("cd", "sil")),
    ("object-cd", "object-wise CD", "object", ("cd",)),
    ("object-sil", "object-wise silhouette", "object", ("sil",)),
    ("scene-cd-sil", "scene-wise CD + silhouette", "scene", ("cd", "sil")),
    ("scene-cd", "scene-wise CD", "scene", ("cd",)),
    ("scene-sil", "scene-wise silhouette", "scene", ("sil",)),
)
OURS = VARIANTS[0][0]
#: loss component per (granularity, term)
LOSS_NAMES = {
    ("object", "cd"): "chamfer",
    ("object", "sil"): "silhouette",
    ("scene", "cd"): "scene-chamfer",
    ("scene", "sil"): "scene-silhouette",
}
TARGET_OBSERVED_PSNR = 30.0
TARGET_FUTURE_PSNR = 27.0
QUANTITIES = (("psnr", "PSNR dB", max), ("psnr_objects", "object PSNR dB", max))
QUANTITIES += (("ssim", "SSIM", max), ("cd_mm2", "CD mm^2", min))
QUANTITIES += (("emd_mm", "EMD mm", min),)
#: files of Stage I and II that a variant copies from the scene's first run to skip them
SHARED_STAGES = ("reconstruction.pt", "particles.pt", "stages/reconstruct.json", "stages/lift.json")
#: written into the first variant's folder when its run fails, so the variants waiting for its
#: Stage I-II stop waiting
STAGES_FAILED = "stages_failed.txt"
#: seconds between a waiting variant's looks for its scene's Stage I-II (which take minutes)
SHARED_POLL_S = 10.0
#: written beside a run's folder (the run folder takes no foreign file) while the run makes
#: Stage I-II that others copy: its host and process id
STAGES_OWNER_SUFFIX = ".stages_owner.json"
#: hours a run waits for the Stage I-II it copies before it gives up (a run never started)
SHARED_WAIT_H = 4.0


def variant_losses(recipe_losses: dict, granularity: str, terms: tuple[str, ...]) -> dict:
    """The ``losses`` section of a variant, built from the recipe's object-wise ``chamfer`` and
    ``silhouette`` sections (their weights and options carry over to the scene-wise terms)."""
    missing = [n for n in ("chamfer", "silhouette") if n not in recipe_losses]
    if missing:
        raise SystemExit(
            f"the recipe's losses need both chamfer and silhouette sections (the variants are "
            f"built from them); missing: {missing}"
        )
    out = {}
    for term in terms:
        section = dict(recipe_losses["chamfer" if term == "cd" else "silhouette"])
        out[LOSS_NAMES[(granularity, term)]] = section
    return out


def _run_one(job: dict) -> dict:
    """One variant on one scene, in a worker process; returns its scores or its error."""
    import torch
    from omegaconf import OmegaConf

    from mosiv_framework.pipeline import run_pipeline
    from mosiv_framework.recipes.load import read_recipe_file, validate_recipe
    from mosiv_framework.registry import get_registry

    torch.set_num_threads(job["threads"])
    run_dir = Path(job["run_dir"])
    shared = Path(job["shared_from"]) if job["shared_from"] else None
    if shared is None:
        (run_dir / STAGES_FAILED).unlink(missing_ok=True)  # a rerun starts afresh
    try:
        raw = read_recipe_file(job["recipe"], job["overrides"])
        raw["losses"] = variant_losses(raw.get("losses") or {}, job["granularity"], job["terms"])
        raw.setdefault("output", {})["dir"] = str(run_dir)
        resolved, problems = validate_recipe(raw, get_registry())
        if problems:
            raise SystemExit("; ".join(problems))
        if shared is not None:
            copy_shared_stages(shared, run_dir, poll_s=SHARED_POLL_S)
        marker = run_dir / "stages" / "identify.json"
        before = marker.read_text() if marker.is_file() else None
        started = time.perf_counter()
        with making_shared_stages(run_dir) if shared is None else nullcontext():
            metrics = run_pipeline(OmegaConf.create(resolved), run_dir=run_dir)
        elapsed = _timed(run_dir, before, time.perf_counter() - started)
    except Exception as exc:  # one failed run must not lose the others' rows
        traceback.print_exc()
        if shared is None and not (run_dir / "stages" / "lift.json").is_file():
            run_dir.mkdir(parents=True, exist_ok=True)
            (run_dir / STAGES_FAILED).write_text(f"{type(exc).__name__}: {exc}\n")
        return {"error": f"{type(exc).__name__}: {exc}"}
    scores = {}
    for block in ("observed", "future"):
        values = metrics.get(block) or {}
        scores[block] = {key: values.get(key) for key, *_ in QUANTITIES}
    return {
        **scores,
        "errors": errors_of(metrics),
        "time_s": elapsed,
        "peak_memory_gb": metrics.get("peak_memory_gb"),
    }


@contextmanager
def making_shared_stages(run_dir: Path):
    """While the block runs, ``run_dir`` names this process as the one making its Stage I-II,
    so that a run waiting to copy them can tell a run that died from one still going."""
    owner = owner_path(run_dir)
    owner.parent.mkdir(parents=True, exist_ok=True)
    owner.write_text(json.dumps({"host": socket.gethostname(), "pid": os.getpid()}) + "\n")
    try:
        yield
    finally:
        owner.unlink(missing_ok=True)


def owner_path(run_dir: Path) -> Path:
    """Where the run making ``run_dir``'s Stage I-II names itself while it runs."""
    return run_dir.with_name(run_dir.name + STAGES_OWNER_SUFFIX)


def _owner_ended(shared: Path) -> str | None:
    """Why the run making ``shared``'s Stage I-II will not finish them: its process, on this
    host, has ended; None while it runs, before it starts, or on another host (unknowable)."""
    try:
        owner = json.loads(owner_path(shared).read_text())
    except (FileNotFoundError, ValueError):
        return None
    if owner.get("host") != socket.gethostname():
        return None
    try:
        os.kill(int(owner["pid"]), 0)
    except ProcessLookupError:
        return f"its process {owner['pid']} ended without them (killed, or out of memory)"
    except PermissionError:
        return None
    return None


def wait_for_shared_stages(
    shared: Path, *, poll_s: float, max_wait_s: float = SHARED_WAIT_H * 3600
) -> None:
    """Block until the scene's first variant has finished Stage I-II in ``shared`` (its lift
    marker exists); raise if that run failed first, if its process ended without them, or
    after ``max_wait_s`` (a run that was never started). Later variants wait here instead of
    for every scene's first variant, so a scene's supervisions run side by side."""
    deadline = time.monotonic() + max_wait_s
    while not (shared / "stages" / "lift.json").is_file():
        failed = shared / STAGES_FAILED
        if failed.is_file():
            raise RuntimeError(f"Stage I-II of this scene failed in {shared}: {failed.read_text()}")
        ended = _owner_ended(shared)
        if ended is not None:
            raise RuntimeError(f"Stage I-II of this scene never came in {shared}: {ended}")
        if time.monotonic() > deadline:
            raise RuntimeError(
                f"waited {max_wait_s / 3600:g} h for Stage I-II in {shared}: start the run "
                "that makes them (ours of this scene) before the runs that copy them"
            )
        time.sleep(poll_s)


def copy_shared_stages(shared: Path, run_dir: Path, *, poll_s: float) -> None:
    """Wait for ``shared``'s Stage I-II, then copy them into ``run_dir``: always the current
    files, so a rerun after the shared run's stages changed does not keep an older copy."""
    wait_for_shared_stages(shared, poll_s=poll_s)
    for name in SHARED_STAGES:
        (run_dir / name).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(shared / name, run_dir / name)


def reused_shared_stages(shared: Path, run_dir: Path) -> bool:
    """Whether ``run_dir``'s pipeline used the copied Stage I-II (its markers are still the
    shared run's) rather than making its own (its settings for them differ)."""
    markers = ("stages/reconstruct.json", "stages/lift.json")
    return all(
        (run_dir / m).is_file() and (run_dir / m).read_text() == (shared / m).read_text()
        for m in markers
    )


def _jobs_for(selected, *, recipe, out, seed, extra, threads, variants):
    first, rest = [], []
    for index, pair in selected:
        a, b = (LETTERS[x] for x in pair.split("-"))
        scene_dir = out / f"scene-{index:02d}-{a}-{b}"
        overrides = [
            f"scene.path={scene_dir / 'scene'}",
            f"scene.source.materials={a},{b}",
            f"scene.source.seed={seed + index}",
            *extra,
        ]
        for n, (folder, _, granularity, terms) in enumerate(variants):
            job = {
                "scene": scene_dir.name,
                "pair": pair,
                "variant": folder,
                "granularity": granularity,
                "terms": terms,
                "recipe": str(recipe),
                "overrides": overrides,
                "run_dir": str(scene_dir / folder),
                "shared_from": None if n == 0 else str(scene_dir / variants[0][0]),
                "threads": threads,
            }
            (first if n == 0 else rest).append(job)
    return first, rest


def run_suite(*, recipe, selected, out: Path, seed: int, extra, threads: int, variants, scale):
    """Every variant of every scene; rows merged with earlier ones in ``out/table.json``.

    The first variant of each scene runs Stage I-II; the scene's other variants wait for those
    stages (not for the first variant's identification) and then run beside it. All first
    variants are queued before any other, so with fewer ``jobs`` than runs no waiting run holds
    a worker that a Stage I-II it waits for would need. ``scale``: the keyword arguments of
    ``run_tasks`` from the ``--jobs``/``--ray-address``/``--gpus-per-task`` flags."""
    table = out / "table.json"
    rows = {r["scene"]: r for r in json.loads(table.read_text())["rows"]} if table.is_file() else {}
    first, rest = _jobs_for(
        selected, recipe=recipe, out=out, seed=seed, extra=extra, threads=threads, variants=variants
    )
    by_name = {f"{job['scene']}/{job['variant']}": job for job in first + rest}

    def record(outcome) -> None:
        job = by_name[outcome.name]
        result = outcome.result if outcome.ok else {"error": repr(outcome.error)}
        row = rows.setdefault(job["scene"], {"scene": job["scene"], "pair": job["pair"]})
        row[job["variant"]] = result
        print(f"[video-suite] {job['scene']} {job['variant']}: {_brief(result)}", flush=True)
        table.write_text(json.dumps({"rows": [rows[k] for k in sorted(rows)]}, indent=2))

    run_tasks([Task(n, _run_one, (j,)) for n, j in by_name.items()], on_done=record, **scale)
    ordered = [rows[k] for k in sorted(rows)]
    summary = summarise(ordered)
    result = {"recipe": str(recipe), "overrides": extra, "rows": ordered, "summary": summary}
    table.write_text(json.dumps(result, indent=2) + "\n")
    (out / "table.md").write_text(markdown(ordered, summary))
    plot_ablation(summary, out / "ablation.png")
    return result


def _brief(result: dict) -> str:
    if "error" in result:
        return f"failed: {result['error']}"
    o, f = result["observed"], result["future"]
    return (
        f"PSNR {_fmt(o['psnr'])} / {_fmt(f['psnr'])} dB, CD {_fmt(o['cd_mm2'])} / "
        f"{_fmt(f['cd_mm2'])} mm^2 (observed / future), {result['time_s']:.0f} s"
    )


def _ok(result) -> bool:
    return isinstance(result, dict) and "error" not in result


def _mean(values):
    values = [v for v in values if v is not None]
    return statistics.fmean(values) if values else None


def paired_p_value(pairs: list[tuple[float, float]]) -> float | None:
    """Two-sided Wilcoxon signed-rank p-value of the per-scene differences (object-wise minus
    scene-wise), the scenes as paired units; None below 6 scenes with a difference, where even
    a clean sweep cannot reach p < 0.05. Counting wins alone would treat a 0.01 dB lead like a
    3 dB one; a run's own spread (docs/RESULTS.md, "Run-to-run spread") is why a test is
    needed at all."""
    differences = [a - b for a, b in pairs if a != b]
    if len(differences) < 6:
        return None
    from scipy.stats import wilcoxon

    return float(wilcoxon(differences).pvalue)


def summarise(rows: list[dict]) -> dict:
    """Means over the scenes: ours against the PSNR targets; every variant on the scenes where
    all of them ran (the ablation table); scene by scene, object-wise against scene-wise."""
    ours = [r[OURS] for r in rows if _ok(r.get(OURS))]
    out: dict = {"scenes": len(rows), "ours_ok": len(ours)}
    for block in ("observed", "future"):
        out[f"ours_{block}"] = {k: _mean(o[block].get(k) for o in ours) for k, *_ in QUANTITIES}
    obs, fut = out["ours_observed"]["psnr"], out["ours_future"]["psnr"]
    out["observed_psnr_met"] = None if obs is None else obs >= TARGET_OBSERVED_PSNR
    out["future_psnr_met"] = None if fut is None else fut >= TARGET_FUTURE_PSNR
    names = [v[0] for v in VARIANTS if any(v[0] in r for r in rows)]
    complete = [r for r in rows if all(_ok(r.get(n)) for n in names)]
    out["ablation_scenes"] = [r["pair"] for r in complete]
    out["ablation"] = {
        n: {
            block: {k: _mean(r[n][block].get(k) for r in complete) for k, *_ in QUANTITIES}
            for block in ("observed", "future")
        }
        for n in names
    }
    # object-wise against scene-wise with the same terms: scenes where object-wise is better
    wins = {}
    for folder, _, granularity, terms in VARIANTS:
        rival = next(v[0] for v in VARIANTS if v[2] == "scene" and v[3] == terms)
        if granularity != "object" or folder not in names or rival not in names:
            continue
        for block in ("observed", "future"):
            for key, _, better in QUANTITIES:
                pairs = [
                    (r[folder][block].get(key), r[rival][block].get(key))
                    for r in complete
                    if r[folder][block].get(key) is not None
                    and r[rival][block].get(key) is not None
                ]
                won = sum(better(a, b) == a and a != b for a, b in pairs)
                wins[f"{folder}|{block}|{key}"] = [won, len(pairs), paired_p_value(pairs)]
    out["object_beats_scene"] = wins
    out["median_time_s"] = statistics.median([o["time_s"] for o in ours]) if ours else None
    out["max_peak_memory_gb"] = max((o["peak_memory_gb"] or 0.0 for o in ours), default=None)
    return out


def markdown(rows: list[dict], summary: dict) -> str:
    """Per-scene table of ours, the ablation table (means), object vs scene wins, targets."""
    head = ["observed PSNR / object PSNR / SSIM", "future PSNR / object PSNR / SSIM"]
    head += ["observed CD / EMD", "future CD / EMD"]
    head += ["E % (elastic)", "yield %", "friction angle deg", "v0 %", "time s", "peak GB"]
    lines = ["| scene | " + " | ".join(head) + " |", "|---" * (len(head) + 1) + "|"]
    for r in rows:
        o = r.get(OURS)
        if not _ok(o):
            why = (o or {}).get("error", "not run")
            lines.append(f"| {r['pair']} | failed: {why} |" + " |" * (len(head) - 1))
            continue
        ob, fu, e = o["observed"], o["future"], o["errors"]
        cells = [
            f"{_fmt(ob['psnr'])} / {_fmt(ob.get('psnr_objects'))} / {_fmt(ob['ssim'])}",
            f"{_fmt(fu['psnr'])} / {_fmt(fu.get('psnr_objects'))} / {_fmt(fu['ssim'])}",
            f"{_fmt(ob['cd_mm2'])} / {_fmt(ob['emd_mm'])}",
            f"{_fmt(fu['cd_mm2'])} / {_fmt(fu['emd_mm'])}",
            _fmt(e["E_pct"]),
            _fmt(e["yield_pct"]),
            _fmt(e["friction_angle_deg"]),
            _fmt(e["v0_pct"]),
            f"{o['time_s']:.0f}",
            _fmt(o["peak_memory_gb"]),
        ]
        lines.append(f"| {r['pair']} | " + " | ".join(cells) + " |")
    s = summary
    lines.append(
        f"\nMeans over {s['ours_ok']} scenes (ours): observed PSNR "
        f"{_fmt(s['ours_observed']['psnr'])} dB (target >= {TARGET_OBSERVED_PSNR:g}: "
        f"{_met(s['observed_psnr_met'])}), future PSNR {_fmt(s['ours_future']['psnr'])} dB "
        f"(target >= {TARGET_FUTURE_PSNR:g}: {_met(s['future_psnr_met'])}); object-region PSNR "
        f"{_fmt(s['ours_observed']['psnr_objects'])} / {_fmt(s['ours_future']['psnr_objects'])} "
        f"dB; observed / future CD {_fmt(s['ours_observed']['cd_mm2'])} / "
        f"{_fmt(s['ours_future']['cd_mm2'])} mm^2."
    )
    lines += [
        "",
        f"Supervision ablation (paper table 3), means over {len(s['ablation_scenes'])} scenes "
        f"({', '.join(s['ablation_scenes'])}):",
        "",
        "| losses | "
        + " | ".join(f"observed {t}" for _, t, _ in QUANTITIES)
        + " | "
        + " | ".join(f"future {t}" for _, t, _ in QUANTITIES)
        + " |",
        "|---" * (1 + 2 * len(QUANTITIES)) + "|",
    ]
    labels = {v[0]: v[1] for v in VARIANTS}
    for name, blocks in s["ablation"].items():
        cells = [_fmt(blocks[b][k]) for b in ("observed", "future") for k, *_ in QUANTITIES]
        lines.append(f"| {labels[name]} | " + " | ".join(cells) + " |")
    if s["object_beats_scene"]:
        title = "Scenes where object-wise beats scene-wise (same terms), with the two-sided"
        title += " Wilcoxon signed-rank p-value of the per-scene differences:"
        lines += ["", title, ""]
        for key, (won, n, *test) in s["object_beats_scene"].items():
            folder, block, quantity = key.split("|")
            p = test[0] if test else None
            p_text = "too few scenes for a test" if p is None else f"p = {p:.2g}"
            lines.append(f"- {labels[folder]}, {block} {quantity}: {won} of {n} ({p_text})")
    return "\n".join(lines) + "\n"


def _met(flag) -> str:
    return "not measured" if flag is None else ("met" if flag else "not met")


def plot_ablation(summary: dict, path: Path) -> None:
    """Bars of the future PSNR and future Chamfer of every variant (the ablation means)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(summary["ablation"])
    if not names:
        return
    labels = {v[0]: v[1] for v in VARIANTS}
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for ax, (key, title) in zip(
        axes, (("psnr", "future PSNR (dB)"), ("cd_mm2", "future CD (mm^2)"))
    ):
        values = [summary["ablation"][n]["future"][key] or 0.0 for n in names]
        colors = ["tab:blue" if n.startswith("object") else "tab:orange" for n in names]
        ax.barh([labels[n] for n in names], values, color=colors)
        ax.set_xlabel(title)
        positive = [v for v in values if v > 0]
        # a log axis only where the variants span a decade; bars on a log axis have no zero,
        # so a narrow span would make a 10 % gap look like a hundredfold one
        if key == "cd_mm2" and positive and max(positive) > 10 * min(positive):
            ax.set_xscale("log")
        else:
            ax.set_xlim(0, 1.25 * max(values + [1e-9]))  # room for the value labels
        for y, v in enumerate(values):
            ax.annotate(f"{v:.3g}", (v, y), xytext=(3, 0), textcoords="offset points", va="center")
        ax.invert_yaxis()
    fig.suptitle(f"supervision ablation, means over {len(summary['ablation_scenes'])} scenes")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--recipe", type=Path, default=Path("recipes/video_quickstart.yaml"))
    parser.add_argument("--scenes", type=int, default=None, help="the first N pairs (default 10)")
    parser.add_argument("--pairs", default=None, help=f"comma-separated, of {','.join(PAIRS)}")
    parser.add_argument("--out", type=Path, default=Path("runs/video_suite"))
    parser.add_argument("--seed", type=int, default=0, help="scene seed of the first pair")
    add_scale_flags(parser, "runs")
    parser.add_argument("--threads", type=int, default=1, help="torch threads per run")
    parser.add_argument(
        "--variants",
        default=",".join(v[0] for v in VARIANTS),
        help="comma-separated loss variants; the first one runs Stage I and II for the others",
    )
    parser.add_argument(
        "--report",
        action="store_true",
        help="only rebuild table.md and ablation.png from table.json",
    )
    parser.add_argument("overrides", nargs="*", help="key=value recipe overrides for every run")
    args = parser.parse_args(argv)
    # the pipeline's progress (stages, global candidates) is logged at INFO: show it
    configure_logging(level_from_flags())
    known = {v[0]: v for v in VARIANTS}
    chosen = [n.strip() for n in args.variants.split(",") if n.strip()]
    unknown = [n for n in chosen if n not in known]
    if unknown or not chosen:
        raise SystemExit(f"--variants: unknown {unknown}; valid: {', '.join(known)}")
    if args.report:
        table = args.out / "table.json"
        if not table.is_file():
            raise SystemExit(f"--report: {table} does not exist; run the suite first")
        rows = json.loads(table.read_text())["rows"]
        summary = summarise(rows)
        (args.out / "table.md").write_text(markdown(rows, summary))
        plot_ablation(summary, args.out / "ablation.png")
        print(markdown(rows, summary))
        return 0
    selected = select_pairs(pairs=args.pairs, scenes=args.scenes)
    args.out.mkdir(parents=True, exist_ok=True)
    result = run_suite(
        recipe=args.recipe,
        selected=selected,
        out=args.out,
        seed=args.seed,
        extra=args.overrides,
        scale=scale_options(args),
        threads=args.threads,
        variants=[known[n] for n in chosen],
    )
    print(markdown(result["rows"], result["summary"]))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
