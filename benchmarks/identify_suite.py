"""Identification benchmark: the oracle pipeline against the discrete-library baseline.

On generated scenes, one per material pair of the paper (E-P, E-F, E-S, P-F, P-S, F-S, E-E, P-P,
F-F, S-S; E elastic, P plasticine, F newtonian fluid, S sand), run the same recipe twice
(``identify.method=gradient`` and ``identify.method=library``) and tabulate the parameter errors
of the gradient fit (elastic E %, yield stress %, sand friction angle in degrees, initial
velocity %), the observed and future Chamfer of both methods and the future ratio
library / ours, against the own-synth targets (E within 15 %, yield within 25 %, friction angle
within 5 deg, v0 within 5 %, ratio at least 5; the table and summary are built in
``identify_suite_table.py``). Writes ``table.json`` and ``table.md`` into the output folder; a
rerun into the same folder reuses finished stages and keeps the rows of pairs it does not run.
Each row records the code version it was computed with (``code_version``; on a copy of the tree
without git history, e.g. the device machine, pass it as ``MOSIV_CODE_VERSION=<commit>``), and
table.md lists the versions, since a table built up over several runs can mix them.

    python benchmarks/identify_suite.py --recipe recipes/paper.yaml --out runs/suite
    python benchmarks/identify_suite.py --recipe recipes/quickstart.yaml --pairs E-P,E-S \
        --out runs/suite-cpu    # a small run on CPU
    python benchmarks/identify_suite.py --recipe recipes/paper.yaml --out runs/suite \
        --jobs 10 --gpus-per-task 0.1
    python benchmarks/identify_suite.py --recipe recipes/paper.yaml --out runs/suite-wide \
        --ranges wide --start centre --global-candidates 16 --jobs 10 --gpus-per-task 0.1 \
        --write-results docs/RESULTS.md

The last is the same suite on scenes drawn from the generator's wide ranges
(``scene.source.ranges``), identified from the start that recipes/genesis_oracle.yaml uses: the
centre of each law's bounds (``identify.start``) and a global stage of 16 candidates
(``identify.global_candidates``); positional ``key=value`` overrides set them as well. The
recipe's own start (the law defaults) lies near the centre of the paper ranges, which is what
the paper-range numbers were measured with. Scenes of ranges other than the paper's go to
folders of their own (``scene-00-elastic-plasticine-wide``), a scene that was drawn from other
ranges than asked is refused, and identification simulates with the substeps the generator made
each scene with where it raised them for a stiff draw (the model stays exact). ``table.json``
records these settings and the targets; a rerun into a folder whose table was run with other
settings is refused. ``--write-results`` writes the section of the settings
("Identification on own-synth scenes, wide ranges, centre start") into that markdown file,
after the hand-written paper-range section, which it never replaces.

With ``--jobs N`` (or ``--ray-address``) each pair runs in its own process, a Ray task,
N at a time, sharing a GPU in ``--gpus-per-task`` fractions, and the parent merges their
rows. On a GPU this pays: one paper-size identification leaves the device mostly idle between
its small kernels, and ten pairs sharing an H200 finished (ours and the library) in 30 minutes
(docs/BENCHMARKS.md, "Suites on a device machine"). Each pair's output goes to
``OUT/parts/PAIR.log``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
import traceback
from dataclasses import replace
from pathlib import Path

import torch
from identify_suite_table import (
    EXTRA,
    TARGETS,
    _fmt,  # noqa: F401  (the benchmarks that share the suite's number format import it here)
    describe_settings,
    markdown,
    summarise,
    targets_json,
    write_results,
)
from omegaconf import OmegaConf

from mosiv_framework.logs import configure_logging, level_from_flags
from mosiv_framework.pipeline import ensure_scene, run_pipeline
from mosiv_framework.pipeline.contact import simulator_section
from mosiv_framework.pipeline.evaluate import score
from mosiv_framework.pipeline.params import ParameterVector
from mosiv_framework.recipes import load_recipe
from mosiv_framework.recipes.schema import IDENTIFY_STARTS
from mosiv_framework.registry import get_registry
from mosiv_framework.scale import Task, run_command, run_tasks
from mosiv_framework.scale.flags import add_scale_flags, scale_options
from mosiv_framework.scene import read_scene

#: the paper's letters for the four material families of its benchmark
LETTERS = {"E": "elastic", "P": "plasticine", "F": "newtonian", "S": "sand"}
#: the paper's ten material pairs, in its order; a pair's index also seeds its scene, so the
#: scene of a pair is the same whichever pairs one run selects
PAIRS = ("E-P", "E-F", "E-S", "P-F", "P-S", "F-S", "E-E", "P-P", "F-F", "S-S")

#: the settings of a table whose table.json predates them: the only ones the suite then ran
LEGACY_SETTINGS = {"ranges": "paper", "start": "defaults", "global_candidates": 0}
#: the flags that set what a table depends on, and the recipe key each overrides
SETTING_FLAGS = {
    "ranges": "scene.source.ranges",
    "start": "identify.start",
    "global_candidates": "identify.global_candidates",
}


def select_pairs(*, pairs: str | None, scenes: int | None) -> list[tuple[int, str]]:
    """(index in PAIRS, pair) to run: the named pairs, else the first ``scenes`` of PAIRS."""
    if pairs:
        names = [p.strip().upper() for p in pairs.split(",") if p.strip()]
        unknown = [n for n in names if n not in PAIRS]
        if unknown:
            raise SystemExit(f"--pairs: unknown pair(s) {unknown}; valid: {', '.join(PAIRS)}")
        return [(PAIRS.index(n), n) for n in names]
    n = len(PAIRS) if scenes is None else scenes
    if not 1 <= n <= len(PAIRS):
        raise SystemExit(f"--scenes {n}: give 1 to {len(PAIRS)} (one scene per material pair)")
    return list(enumerate(PAIRS[:n]))


def setting_overrides(args: argparse.Namespace) -> list[str]:
    """The recipe overrides of ``--ranges``, ``--start`` and ``--global-candidates`` (those
    given)."""
    values = {name: getattr(args, name) for name in SETTING_FLAGS}
    return [f"{SETTING_FLAGS[n]}={v}" for n, v in values.items() if v is not None]


def suite_settings(recipe: Path, extra: list[str], *, seed: int = 0) -> dict:
    """What the rows of one table share, from the recipe as overridden: the ranges the scenes
    are drawn from (``scene.source.ranges``), where identification starts (``identify.start``),
    the candidates of its global stage (``identify.global_candidates``) and, where set, its
    coordinate sweep (``identify.global_polish``) and the first pair's scene seed (``--seed``;
    both left out at 0, so tables written before they existed keep their settings)."""
    cfg = load_recipe(recipe, extra)
    source = cfg.scene.get("source") or {}
    settings = {
        "ranges": str(source.get("ranges", "paper")),
        "start": str(cfg.identify.start),
        "global_candidates": int(cfg.identify.global_candidates),
    }
    polish = int(getattr(cfg.identify, "global_polish", 0) or 0)
    if polish:
        settings["global_polish"] = polish
    if seed:
        settings["seed"] = seed
    return settings


def errors_of(metrics: dict) -> dict[str, list[float]]:
    """Per kind of parameter, the errors over the scene's objects (percent or degrees).

    Stress-like parameters use ``rel_error_gauge_free``: motion fixes stresses only relative to
    density, and the first object's density is held at its given value (the gauge), so the
    error is taken after rescaling by that object's true / assumed density.
    """
    out: dict[str, list[float]] = {key: [] for key, *_ in TARGETS}
    out.update({key: [] for key, _ in EXTRA})
    families = {k: obj["family"] for k, obj in (metrics.get("params") or {})["objects"].items()}
    for k, obj in (metrics.get("param_error") or {}).items():
        for name, err in obj.items():
            rel = err.get("rel_error_gauge_free", err.get("rel_error"))
            if name == "E":
                out["E_pct" if families[k] == "elastic" else "E_other_pct"].append(100 * rel)
            elif name == "yield_stress":
                out["yield_pct"].append(100 * rel)
            elif name == "viscosity":
                out["viscosity_pct"].append(100 * rel)
            elif name == "friction_angle":
                out["friction_angle_deg"].append(err["abs_error_deg"])
            elif name == "initial_velocity":
                out["v0_pct"].append(100 * err["rel_error"])
    return out


def scene_folder(index: int, pair: str, ranges: str = "paper") -> str:
    """The folder of a pair's scene and runs: ``scene-II-A-B``, with ``-RANGES`` appended for
    ranges other than the paper's, so a scene drawn from other ranges never reuses (through
    ``scene.generate: if-missing``) a paper-range scene of an earlier run, nor its stages."""
    a, b = (LETTERS[x] for x in pair.split("-"))
    return f"scene-{index:02d}-{a}-{b}" + ("" if ranges == "paper" else f"-{ranges}")


def run_scene(
    *,
    recipe: Path,
    index: int,
    pair: str,
    out: Path,
    seed: int,
    extra: list[str],
    ranges: str = "paper",
):
    """Both methods on the scene of ``pair`` (drawn from ``ranges``); one table row."""
    a, b = (LETTERS[x] for x in pair.split("-"))
    scene_dir = out / scene_folder(index, pair, ranges)
    common = [
        f"scene.path={scene_dir / 'scene'}",
        f"scene.source.materials={a},{b}",
        f"scene.source.seed={seed + index}",
        *extra,
    ]
    row: dict = {"scene": scene_dir.name, "pair": pair, "materials": [a, b], "code": code_version()}
    row["ranges"] = ranges
    try:
        common += scene_substeps(recipe, common, ranges=ranges)
    except Exception as exc:  # the scene failed to generate: a failed row, the others go on
        traceback.print_exc()
        failed = {"error": f"{type(exc).__name__}: {exc}"}
        return {**row, "gradient": failed, "library": dict(failed)}
    for method in ("gradient", "library"):
        cfg = load_recipe(
            recipe, [*common, f"identify.method={method}", f"output.dir={scene_dir / method}"]
        )
        run_dir = Path(cfg.output.dir)
        marker = run_dir / "stages" / "identify.json"
        before = marker.read_text() if marker.is_file() else None
        started = time.perf_counter()
        try:
            metrics = run_pipeline(cfg, run_dir=run_dir)
            probe = future_with_true_ground(run_dir, n_samples=cfg.evaluate.emd_samples)
        except Exception as exc:  # one failed scene must not lose the others' rows
            traceback.print_exc()
            row[method] = {"error": f"{type(exc).__name__}: {exc}"}
            continue
        row["substeps"], row["device"] = cfg.simulator.substeps, _device_name(cfg)
        row[method] = {
            "observed_cd_mm2": metrics["observed"]["cd_mm2"],
            "future_cd_mm2": (metrics["future"] or {}).get("cd_mm2"),
            "future_cd_true_ground_mm2": probe,
            "errors": errors_of(metrics),
            "time_s": _timed(run_dir, before, time.perf_counter() - started),
            "peak_memory_gb": metrics["peak_memory_gb"],
        }
    ours = row["gradient"].get("future_cd_mm2")
    base = row["library"].get("future_cd_mm2")
    row["future_cd_ratio_library_over_ours"] = base / ours if ours and base is not None else None
    ours = row["gradient"].get("future_cd_true_ground_mm2")
    base = row["library"].get("future_cd_true_ground_mm2")
    row["true_ground_ratio_library_over_ours"] = base / ours if ours and base is not None else None
    return row


def scene_substeps(recipe: Path, overrides: list[str], *, ranges: str) -> list[str]:
    """Generate the scene of ``overrides`` where it is missing; the override that makes
    identification simulate with the substeps the scene was made with, where the generator
    raised them above the recipe's (mosiv-synth does for stiff draws of the wide ranges), so
    the model stays the one that made the data ([] otherwise: paper-range runs keep their
    recipe and stages). SystemExit when the scene there was drawn from other ranges."""
    cfg = load_recipe(recipe, overrides)
    gt = ensure_scene(cfg.scene).gt_params()
    drawn = gt.get("ranges", "paper")  # scenes made before the generator had ranges: paper
    if drawn != ranges:
        raise SystemExit(
            f"{cfg.scene.path}: gt/params.json says its parameters were drawn from the "
            f"{drawn!r} ranges, this run asks for {ranges!r}; remove that scene or give "
            "another --out"
        )
    made = (gt.get("generator_params") or {}).get("simulator_options", {}).get("substeps")
    if isinstance(made, int) and made > int(cfg.simulator.get("substeps") or 0):
        return [f"simulator.substeps={made}"]
    return []


def _device_name(cfg) -> str:
    from genesis_identify import _device_name as name  # genesis_identify imports this module

    return name(cfg)


def _timed(run_dir: Path, marker_before: str | None, elapsed: float) -> float:
    """Wall time (s) of the run that identified ``run_dir``: ``elapsed`` when this call ran
    identification (recorded in ``suite_time.json``), the recorded time when the pipeline
    reused an earlier identification (then this call only re-evaluated)."""
    record = run_dir / "suite_time.json"
    marker = run_dir / "stages" / "identify.json"
    reused = marker_before is not None and marker.read_text() == marker_before
    if reused and record.is_file():
        return float(json.loads(record.read_text())["time_s"])
    record.write_text(json.dumps({"time_s": elapsed}) + "\n")
    return elapsed


def future_with_true_ground(run_dir: Path, *, n_samples: int) -> float | None:
    """Future ``cd_mm2`` of the run's identified parameters with the table friction set to
    the scene's true value (gt/params.json), everything else as identified.

    A diagnostic, not a result: the table friction only acts once a body touches the table,
    so when that happens after the observed frames the recording cannot tell it and the
    fit keeps its start value; this rollout shows how much of the future error that one
    unobservable number causes (None when the scene has no true table friction).
    """
    recipe = OmegaConf.load(run_dir / "recipe.yaml")
    scene = read_scene(recipe.scene.path)
    true_ground = scene.gt_params().get("generator_params", {}).get("ground_friction")
    identified = json.loads((run_dir / "identified.json").read_text())
    if true_ground is None or scene.observed_frames >= scene.n_frames:
        return None
    identified["ground_friction"] = float(true_ground)
    # the contact the run identified with (identify.contact: auto may have chosen it)
    options = OmegaConf.to_container(simulator_section(recipe.simulator, identified), resolve=True)
    simulator = get_registry().create("simulator", options.pop("name"), options)
    params = ParameterVector.from_json(identified)
    particles = torch.load(run_dir / "particles.pt", weights_only=False)
    # the identified families may differ from the lifted ones (library baseline, scope "all")
    particles = replace(particles, materials={k: p.family for k, p in params.objects.items()})
    with torch.no_grad():
        traj = simulator.rollout(particles, params, world=scene.world, frames=scene.n_frames - 1)
    blocks = score(
        traj,
        scene.gt_points(),
        observed_frames=scene.observed_frames,
        n_samples=n_samples,
        seed=recipe.evaluate.seed,
    )
    return blocks["future"]["cd_mm2"]


def code_version() -> str:
    """The code a row was computed with: ``$MOSIV_CODE_VERSION`` if set (a copy of the tree
    without its git history, as on the device machine), else the checkout's short commit hash
    (``+dirty`` with uncommitted changes), else "unknown". Rows accumulate across runs, so a
    table can mix versions; the markdown lists them."""
    if os.environ.get("MOSIV_CODE_VERSION"):
        return os.environ["MOSIV_CODE_VERSION"]
    here = Path(__file__).resolve().parent
    try:
        head = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], cwd=here, capture_output=True, text=True
        )
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no"],
            cwd=here,
            capture_output=True,
            text=True,
        )
    except OSError:
        return "unknown"
    if head.returncode != 0:
        return "unknown"
    return head.stdout.strip() + ("+dirty" if dirty.stdout.strip() else "")


def run_suite(
    *,
    recipe: Path,
    selected: list[tuple[int, str]],
    out: Path,
    seed: int,
    extra: list[str],
    settings: dict,
    part: bool = False,
) -> dict:
    """Run the selected pairs, merge their rows with earlier rows in ``out/table.json``
    (SystemExit when those were run with other ``settings``).

    With ``part`` (one pair of a parallel run) the rows go to ``out/parts/PAIR.json`` instead,
    for the parent to merge (``merge_parts``), so parallel pairs never write one file."""
    ranges = settings["ranges"]
    if part:
        rows = [
            run_scene(
                recipe=recipe, index=i, pair=pair, out=out, seed=seed, extra=extra, ranges=ranges
            )
            for i, pair in selected
        ]
        target = out / "parts" / f"{selected[0][1]}.json"
        target.parent.mkdir(parents=True, exist_ok=True)
        target.write_text(json.dumps({"rows": rows}, indent=2) + "\n")
        return {"rows": rows, "summary": summarise(rows), "settings": settings}
    earlier, done = _earlier_rows(out, settings), []
    for index, pair in selected:
        done.append(
            run_scene(
                recipe=recipe,
                index=index,
                pair=pair,
                out=out,
                seed=seed,
                extra=extra,
                ranges=ranges,
            )
        )
        rows = merge_parts(earlier, [done])  # saved after every pair: a crash keeps the rows
        table = {"settings": settings, "rows": rows}
        (out / "table.json").write_text(json.dumps(table, indent=2) + "\n")
    rows = merge_parts(earlier, [done])
    return write_table(out, recipe=recipe, extra=extra, rows=rows, settings=settings)


def _earlier_rows(out: Path, settings: dict) -> list[dict]:
    """The rows of ``out/table.json`` from an earlier run ([] if none); SystemExit when that
    run had other ``settings``, since one table's summary is over rows of one kind (a table
    written before the settings were recorded had ``LEGACY_SETTINGS``)."""
    table = out / "table.json"
    if not table.is_file():
        return []
    doc = json.loads(table.read_text())
    before = doc.get("settings", LEGACY_SETTINGS)
    if before != settings:
        raise SystemExit(
            f"{table}: its rows were run with {describe_settings(before)}; this run asks for "
            f"{describe_settings(settings)}; give another --out"
        )
    return doc["rows"]


def write_table(
    out: Path, *, recipe: Path, extra: list[str], rows: list[dict], settings: dict
) -> dict:
    """``out/table.json`` and ``out/table.md`` from ``rows`` (ordered by scene), with the
    ``settings`` they were run with and the targets they are held to."""
    ordered = sorted(rows, key=lambda r: r["scene"])
    summary = summarise(ordered)
    result = {
        "recipe": str(recipe),
        "overrides": extra,
        "settings": settings,
        "targets": targets_json(),
        "rows": ordered,
        "summary": summary,
    }
    (out / "table.json").write_text(json.dumps(result, indent=2) + "\n")
    (out / "table.md").write_text(markdown(ordered, summary, settings=settings))
    return result


def merge_parts(earlier: list[dict], parts: list[list[dict]]) -> list[dict]:
    """Rows of an earlier table updated by the rows of parallel parts (a part's row replaces
    the earlier row of its scene); earlier rows without a pair (an older format) are dropped."""
    rows = {r["scene"]: r for r in earlier if "pair" in r}
    for part in parts:
        rows.update({r["scene"]: r for r in part})
    return [rows[k] for k in sorted(rows)]


def run_parallel(
    *,
    recipe: Path,
    selected: list[tuple[int, str]],
    out: Path,
    seed: int,
    extra: list[str],
    settings: dict,
    scale: dict,
) -> dict:
    """Each selected pair as a Ray task (``run_tasks`` with ``scale``, the keyword arguments
    of the ``--jobs``/``--ray-address``/``--gpus-per-task`` flags) running this script with
    ``--part`` on the GPUs Ray gave it; their rows merged with the earlier ones into
    ``out/table.json`` (SystemExit before any task when those were run with other
    ``settings``)."""
    earlier = _earlier_rows(out, settings)
    (out / "parts").mkdir(parents=True, exist_ok=True)
    tasks = []
    for pair in (pair for _, pair in selected):
        (out / "parts" / f"{pair}.json").unlink(missing_ok=True)  # no stale rows of a crash
        (out / "parts" / f"{pair}.log").unlink(missing_ok=True)  # the task appends to it
        command = [sys.executable, __file__, "--recipe", str(recipe), "--pairs", pair]
        command += ["--out", str(out), "--seed", str(seed), "--part", *extra]
        tasks.append(Task(pair, run_command, (command,), out / "parts" / f"{pair}.log"))
    for name, outcome in run_tasks(tasks, **scale).items():
        code = outcome.result if outcome.ok else repr(outcome.error)
        print(f"[suite] {name}: {'done' if code == 0 else f'FAILED ({code})'}", flush=True)
    parts = [
        json.loads(f.read_text())["rows"]
        for f in (out / "parts" / f"{pair}.json" for _, pair in selected)
        if f.is_file()
    ]
    rows = merge_parts(earlier, parts)
    return write_table(out, recipe=recipe, extra=extra, rows=rows, settings=settings)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--recipe", type=Path, default=Path("recipes/paper.yaml"))
    parser.add_argument(
        "--scenes", type=int, default=None, help="the first N pairs of PAIRS (default: all 10)"
    )
    parser.add_argument("--pairs", default=None, help=f"comma-separated, of {','.join(PAIRS)}")
    parser.add_argument("--out", type=Path, default=Path("runs/identify_suite"))
    parser.add_argument("--seed", type=int, default=0, help="scene seed of the first pair")
    parser.add_argument(
        "--ranges",
        default=None,
        help="the generator's parameter ranges, paper or wide (scene.source.ranges, checked by "
        "the scene source; default: the recipe's)",
    )
    parser.add_argument(
        "--start",
        choices=IDENTIFY_STARTS,
        default=None,
        help="where identification starts (identify.start; default: the recipe's)",
    )
    parser.add_argument(
        "--global-candidates",
        type=int,
        default=None,
        help="candidates of the global stage (identify.global_candidates; default: the recipe's)",
    )
    parser.add_argument(
        "--write-results",
        type=Path,
        default=None,
        help="e.g. docs/RESULTS.md: write the section of these settings (never the paper-range "
        "section)",
    )
    add_scale_flags(parser, "pairs")
    parser.add_argument("--part", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("overrides", nargs="*", help="key=value recipe overrides for every run")
    args = parser.parse_args(argv)
    # the pipeline's progress (stages, global candidates) is logged at INFO: show it
    configure_logging(level_from_flags())
    scale = scale_options(args)
    selected = select_pairs(pairs=args.pairs, scenes=args.scenes)
    extra = [*setting_overrides(args), *args.overrides]
    settings = suite_settings(args.recipe, extra, seed=args.seed)
    args.out.mkdir(parents=True, exist_ok=True)
    common = dict(recipe=args.recipe, selected=selected, out=args.out, seed=args.seed)
    common.update(extra=extra, settings=settings)
    if scale["jobs"] != 1 and len(selected) > 1 and not args.part:
        result = run_parallel(**common, scale=scale)
    else:
        result = run_suite(**common, part=args.part)
    print(markdown(result["rows"], result["summary"], settings=settings))
    if args.write_results is not None and not args.part:
        title = write_results(args.write_results, result, argv=argv)
        print(f"[suite] wrote the section '{title}' of {args.write_results}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
