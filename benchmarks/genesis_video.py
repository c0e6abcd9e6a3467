"""From video on Genesis scenes: the paper's table 1, and optionally its table 3 ablation.

On every scene of a suite folder that ``mosiv data suite DIR --source genesis --ranges wide``
made, runs each method from the recorded videos and masks, end to end, and scores it:

- ``ours``: ``recipes/video_paper.yaml`` (object-aware dynamic Gaussians, lifting, object-wise
  Chamfer + silhouette identification);
- ``library``: OmniPhysGS-RGB, the discrete-library baseline from video: ours' Stages I-II
  (copied from ours' run of the scene, which therefore runs too; its wall time counts them as
  they ran there) with the identify section of ``recipes/baselines/library.yaml`` (itself a
  ground-truth recipe): each object takes the best of every family's prototypes;
- ``library-oracle``: the same given the true material family (``identify.library_scope=family``);
- ``coupnerf``: CoupNeRF* (``recipes/baselines/coupnerf.yaml``, plugin mosiv-nerf).

Per scene and method: observed and future PSNR, SSIM, Chamfer (CD, mm^2), EMD (mm), wall time
and peak memory (GPU when CUDA ran, else the process's resident memory); for Gaussian runs also
Stage I per object (Chamfer of the Gaussian centres as a multiple of the scene's Chamfer floor,
mask IoU), as metrics.json records them. ``--ablation`` adds the supervision ablation of
``benchmarks/video_suite.py`` (object- against scene-wise losses, Chamfer only, silhouette
only) on the inter-material scenes with several Stage I seeds, so each difference is shown
beside the run-to-run spread.

    python benchmarks/genesis_video.py --scenes runs/genesis --out runs/genesis_video
    python benchmarks/genesis_video.py --scenes runs/genesis --out runs/genesis_video \\
        --only E-S --method ours --part       # one (scene, method) per process on a device
    python benchmarks/genesis_video.py --scenes runs/genesis --out runs/genesis_video \\
        --merge --write-results docs/RESULTS.md
    python benchmarks/genesis_video.py --scenes runs/genesis --out runs/genesis_video \\
        --methods ours --ablation --seeds 2 --jobs 8 --gpus-per-task 0.125
    python benchmarks/genesis_video.py --scenes runs/genesis --out runs/genesis_video \\
        --job-file video.jobs     # on a GPU machine without Ray: the runs as queue jobs
    python3 benchmarks/device_queue.py start video.jobs --slots 5

``--set key=value`` overrides every method's recipe, ``--set METHOD:key=value`` one method's
(the library baselines and the ablation's variants run ours' Stages I-II and take ours' too).
Every run is a process of its own (this script with ``--part``; in turn here, or ``--jobs N``
at once as Ray tasks), so its peak memory is its own; its row goes to
``OUT/parts/SCENE/RUN.json``, and the table is always merged from those, so parts made on
several machines merge into one. A rerun resumes each run's finished stages.
Writes ``OUT/table.json`` and ``OUT/table.md``; ``--write-results FILE`` replaces the section
"From video on Genesis scenes" of FILE. ``--development E-S,F-F`` names the scenes that recipe
settings were chosen on: they stay in the table, marked, and the targets are judged on the
others (the test scenes).
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import sys
import time
import traceback
from contextlib import nullcontext
from dataclasses import dataclass
from pathlib import Path

import genesis_identify as gi
import genesis_video_table as gt
from identify_suite import _timed, code_version
from video_suite import (
    SHARED_POLL_S,
    STAGES_FAILED,
    VARIANTS,
    copy_shared_stages,
    making_shared_stages,
    reused_shared_stages,
    variant_losses,
)

from mosiv_framework.logs import configure_logging, level_from_flags
from mosiv_framework.scale import Task, run_command, run_tasks
from mosiv_framework.scale.flags import add_scale_flags, scale_options

ROOT = Path(__file__).resolve().parents[1]
#: marks OUT as this benchmark's folder (a rerun resumes there; a foreign folder is refused)
MARKER = "genesis_video.json"
MARKER_FORMAT = "mosiv-genesis-video/1"


@dataclass(frozen=True)
class Method:
    """One row of table 1 (named in genesis_video_table.LABELS): its recipe, the recipe whose
    identify section replaces the recipe's own (None: keep it) and the overrides that make it
    this method."""

    recipe: str
    identify_from: str | None = None
    sets: tuple[str, ...] = ()
    #: the method whose Stages I-II this one runs: its ``--set METHOD:`` values apply here too
    base: str | None = None

    def describe(self) -> str:
        """The recipe as the results name it."""
        if self.identify_from is None:
            return self.recipe
        return f"{self.recipe} with the identify section of {self.identify_from}"


METHODS = {
    "ours": Method("recipes/video_paper.yaml"),
    "library": Method("recipes/video_paper.yaml", "recipes/baselines/library.yaml", base="ours"),
    "library-oracle": Method(
        "recipes/video_paper.yaml",
        "recipes/baselines/library.yaml",
        ("identify.library_scope=family",),
        base="ours",
    ),
    "coupnerf": Method("recipes/baselines/coupnerf.yaml"),
}
#: ablation variants other than ours (video_suite's object-wise Chamfer + silhouette is ours)
ABLATION = {folder: (granularity, terms) for folder, _, granularity, terms in VARIANTS[1:]}
#: what every method needs on the Genesis suite's scenes, before the user's --set: the wide
#: ranges reach E = 1e6 Pa (2e6 Pa in the density gauge); at grid 64 and 24 fps 100 substeps
#: cap E near 1.9e5 Pa, 400 lift the cap above 2e6 Pa (as recipes/genesis_oracle.yaml)
GENESIS_SETS = ("simulator.substeps=400",)
#: the paper's ablation scenes: one per inter-material pair
ABLATION_SCENES = ("E-P", "E-F", "E-S", "P-F", "P-S", "F-S")


@dataclass(frozen=True)
class Job:
    """One run: a method (or ablation variant) on a scene with a Stage I seed (0: the recipe's
    own)."""

    scene: str
    method: str
    seed: int = 0

    @property
    def run(self) -> str:
        """The run's folder name under OUT/runs/SCENE (and its part's name)."""
        return self.method if self.seed == 0 else f"{self.method}-seed{self.seed}"

    @property
    def name(self) -> str:
        return f"{self.scene}/{self.run}"

    @property
    def shares_from(self) -> Job | None:
        """The run whose Stage I-II this one copies: an ablation variant and a method that runs
        ours' Stages I-II (the library baselines) take ours' of its seed (same scene,
        reconstructor and lifter, so the same stage keys). Sharing them makes the baselines
        differ from ours in identification alone, and saves their Stage I."""
        method = METHODS.get(self.method)
        if self.method in ABLATION or (method is not None and method.base == "ours"):
            return Job(self.scene, "ours", self.seed)
        return None


def parse_sets(sets: list[str], known: list[str]) -> dict[str | None, list[str]]:
    """``--set`` values by the method they are for (None: every method)."""
    out: dict[str | None, list[str]] = {}
    for item in sets:
        key, eq, _ = item.partition("=")
        if not eq or not key:
            raise SystemExit(f"--set {item!r}: give key=value or METHOD:key=value")
        method, colon, _ = key.partition(":")
        if colon and method not in known:
            raise SystemExit(f"--set {item!r}: unknown method {method!r}; valid: {known}")
        out.setdefault(method if colon else None, []).append(
            item.split(":", 1)[1] if colon else item
        )
    return out


def job_overrides(job: Job, sets: dict) -> list[str]:
    """The recipe overrides of ``job`` (without scene.path and output.dir): the method's own,
    then GENESIS_SETS, every method's --set, the --set of the method whose Stages I-II it runs
    (ours' for the library baselines and the ablation's variants), its own --set, and the
    Stage I seed."""
    name = "ours" if job.method in ABLATION else job.method
    method = METHODS[name]
    out = list(method.sets)
    if method.identify_from:
        out = identify_overrides(ROOT / method.identify_from) + out
    out += [*GENESIS_SETS, *sets.get(None, [])]
    bases = ["ours"] if job.method in ABLATION else [method.base] if method.base else []
    for key in [*bases, job.method]:
        out += sets.get(key, [])
    if job.seed:
        out.append(f"reconstructor.seed={job.seed}")
    return out


def identify_overrides(recipe: Path) -> list[str]:
    """The identify section of ``recipe`` as overrides (the baseline's identification settings
    put on another recipe's Stages I-II)."""
    from omegaconf import OmegaConf

    section = OmegaConf.to_container(OmegaConf.load(recipe).identify, resolve=True)
    return [f"identify.{k}={v}" for k, v in section.items()]


def load_job_recipe(job: Job, *, scene: Path, run_dir: Path, overrides: list[str]):
    """The validated recipe of ``job``: the method's recipe with ``overrides``; an ablation
    variant's losses built from the recipe's chamfer and silhouette sections."""
    from omegaconf import OmegaConf

    from mosiv_framework.errors import ConfigError
    from mosiv_framework.recipes.load import read_recipe_file, validate_recipe
    from mosiv_framework.registry import get_registry

    recipe = ROOT / METHODS["ours" if job.method in ABLATION else job.method].recipe
    raw = read_recipe_file(recipe, [f"scene.path={scene}", f"output.dir={run_dir}", *overrides])
    if job.method in ABLATION:
        granularity, terms = ABLATION[job.method]
        raw["losses"] = variant_losses(raw.get("losses") or {}, granularity, terms)
    resolved, problems = validate_recipe(raw, get_registry())
    if problems:
        raise ConfigError("; ".join(problems))
    return OmegaConf.create(resolved)


# --------------------------------------------------------------------------------------------
# one run (the --part process)


def scene_data(scene: Path) -> dict:
    """Where the scene came from and its size: generator, ranges and seed (gt/params.json),
    frames, observed frames, cameras and resolution, the object families (scene.json)."""
    truth = json.loads((scene / "gt" / "params.json").read_text())
    info = json.loads((scene / "scene.json").read_text())
    cameras = json.loads((scene / "cameras.json").read_text()).get("cameras", [])
    return {
        "generator": truth.get("generator"),
        "ranges": truth.get("ranges"),
        "seed": (truth.get("generator_params") or {}).get("seed"),
        "frames": info.get("n_frames"),
        "observed_frames": info.get("observed_frames"),
        "cameras": len(cameras),
        "resolution": cameras[0].get("width") if cameras else None,
        "materials": [o.get("material") for o in info.get("objects", [])],
    }


def run_job(job: Job, *, scenes: Path, out: Path, sets: dict) -> dict:
    """``run_pipeline`` of ``job`` into OUT/runs/SCENE/RUN; its row (an ``error`` row when it
    fails, so one run cannot lose the others)."""
    import torch

    from mosiv_framework.pipeline import run_pipeline

    scene = scenes / job.scene
    run_dir = out / "runs" / job.scene / job.run
    overrides = job_overrides(job, sets)
    row = {"scene": job.scene, "method": job.method, "seed": job.seed, "overrides": overrides}
    if job.method in ABLATION:
        granularity, terms = ABLATION[job.method]
        row["recipe"] = f"ours with {granularity}-wise {' + '.join(terms)} losses"
    else:
        row["recipe"] = METHODS[job.method].describe()
    row.update(data=scene_data(scene), code=code_version())
    shared = out / "runs" / job.scene / job.shares_from.run if job.shares_from else None
    if shared is None:
        (run_dir / STAGES_FAILED).unlink(missing_ok=True)  # a rerun starts afresh
    try:
        cfg = load_job_recipe(job, scene=scene, run_dir=run_dir, overrides=overrides)
        if shared is not None:
            copy_shared_stages(shared, run_dir, poll_s=SHARED_POLL_S)
        if torch.cuda.is_available():
            torch.cuda.reset_peak_memory_stats()
        marker = run_dir / "stages" / "identify.json"
        before = marker.read_text() if marker.is_file() else None
        started = time.perf_counter()
        with making_shared_stages(run_dir) if shared is None else nullcontext():
            metrics = run_pipeline(cfg, run_dir=run_dir)
        elapsed = _timed(run_dir, before, time.perf_counter() - started)
    except Exception as exc:  # one failed run must not lose the others' rows
        traceback.print_exc()
        if shared is None and not (run_dir / "stages" / "lift.json").is_file():
            run_dir.mkdir(parents=True, exist_ok=True)  # the variants waiting on it stop
            (run_dir / STAGES_FAILED).write_text(f"{type(exc).__name__}: {exc}\n")
        # the message goes into a results file: folders by their names, not their paths
        why = f"{type(exc).__name__}: {exc}".replace(str(out), "OUT").replace(str(scenes), "SCENES")
        return {**row, "error": why}
    device = gi._device_name(cfg)
    row.update(gt.scores_of(metrics), time_s=elapsed, device=device)
    row["memory"] = "RSS" if device == "CPU" else "GPU"
    # copied Stage I-II the pipeline used (it makes its own where its settings differ)
    row["shared_stages"] = shared is not None and reused_shared_stages(shared, run_dir)
    if row["shared_stages"]:  # end to end: its own stages plus the Stage I-II it copied
        row["own_time_s"] = elapsed
        row["time_s"] = elapsed + shared_stage_seconds(row.get("stage_times_s"))
    return row


def shared_stage_seconds(stage_times: dict | None) -> float:
    """Seconds the copied Stage I-II took where they ran (their markers keep the time)."""
    stage_times = stage_times or {}
    return sum(stage_times.get(stage) or 0.0 for stage in ("reconstruct", "lift"))


def part_path(out: Path, job: Job) -> Path:
    return out / "parts" / job.scene / f"{job.run}.json"


def write_part(out: Path, job: Job, row: dict) -> None:
    """The row into its part file, whole or not at all (a merge may read it any time)."""
    path = part_path(out, job)
    path.parent.mkdir(parents=True, exist_ok=True)
    partial = path.with_suffix(".json.partial")
    partial.write_text(json.dumps(row, indent=2) + "\n")
    os.replace(partial, path)


# --------------------------------------------------------------------------------------------
# the suite: jobs, their processes, the merge


def plan_jobs(names, methods, *, ablation_scenes=(), seeds: int = 1) -> list[Job]:
    """Table 1's runs (every method on every scene), then the ablation's: on each ablation
    scene and Stage I seed, ours and every variant. Runs that others copy Stage I-II from come
    first, so with fewer workers than runs none waits on a run that has no worker."""
    first = []
    for name in names:  # a method that shares ours' Stage I-II needs ours' run, before it
        for method in methods:
            job = Job(name, method)
            if job.shares_from is not None:
                first.append(job.shares_from)
            first.append(job)
    first += [Job(n, "ours", s) for n in ablation_scenes for s in range(seeds)]
    rest = [Job(n, v, s) for n in ablation_scenes for s in range(seeds) for v in ABLATION]
    jobs, seen = [], set()
    for job in first + rest:
        if job not in seen:
            seen.add(job)
            jobs.append(job)
    return jobs


def part_command(args, job: Job, *, launcher: tuple[str, str] | None = None) -> list[str]:
    """The --part process of ``job``: this interpreter and script, or ``launcher`` (python,
    script) as another machine names them; folders absolute, so any working folder does."""
    python, script = launcher or (sys.executable, __file__)
    command = [python, script, "--scenes", str(args.scenes.resolve())]
    command += ["--out", str(args.out.resolve()), "--only", job.scene, "--method", job.method]
    command += ["--seed", str(job.seed), "--part"]
    return command + [x for s in args.set for x in ("--set", s)]


def write_job_file(args, jobs: list[Job]) -> None:
    """The planned runs as ``benchmarks/device_queue.py`` lines, ``NAME COMMAND``, on the
    machine that runs them. Folders are absolute (each job runs in its own snapshot of the
    checkout and every row must land in the one OUT); the script is named by its path in the
    checkout. A run that copies Stage I-II comes after the run it copies, so the queue starts
    that one first."""
    if args.job_file.exists():
        raise SystemExit(f"--job-file {args.job_file}: exists; give a new file")
    launcher = ("python3", "benchmarks/genesis_video.py")
    lines = [
        f"{job.scene}-{job.run} {shlex.join(part_command(args, job, launcher=launcher))}"
        for job in jobs
    ]
    args.job_file.write_text("\n".join(lines) + "\n")
    print(
        f"[genesis-video] {len(lines)} runs in {args.job_file}: python3 "
        f"benchmarks/device_queue.py start {args.job_file} --slots 5"
    )


def run_jobs(args, jobs: list[Job], scale: dict) -> None:
    """Each job as a process of its own running this script with ``--part``: one after another
    here, or as Ray tasks (``--jobs``, ``--ray-address``)."""
    tasks = []
    for job in jobs:
        part_path(args.out, job).unlink(missing_ok=True)  # no stale row of a crash
        log = part_path(args.out, job).with_suffix(".log")
        log.parent.mkdir(parents=True, exist_ok=True)
        log.unlink(missing_ok=True)  # a Ray task appends to it
        tasks.append(Task(job.name, run_command, (part_command(args, job),), log))
    for name, outcome in run_tasks(tasks, **scale).items():
        code = outcome.result if outcome.ok else repr(outcome.error)
        print(f"[genesis-video] {name}: {'done' if code == 0 else f'FAILED ({code})'}", flush=True)
    for job in jobs:  # a process that died before its row: an error row names its log
        if not part_path(args.out, job).is_file():
            row = {"scene": job.scene, "method": job.method, "seed": job.seed}
            row["error"] = f"the run wrote no row (see parts/{job.scene}/{job.run}.log)"
            write_part(args.out, job, row)


def read_parts(out: Path) -> list[dict]:
    """Every row under OUT/parts, by scene, method and seed."""
    rows = [json.loads(p.read_text()) for p in sorted((out / "parts").glob("*/*.json"))]
    return sorted(rows, key=lambda r: (r["scene"], r["method"], r.get("seed", 0)))


def merge(out: Path, development: list[str] | tuple = ()) -> dict:
    """table.json and table.md from every part under ``out``; ``development``: the scenes that
    settings were chosen on (the targets are judged on the others)."""
    rows = read_parts(out)
    if not rows:
        raise SystemExit(f"--merge: no rows under {out / 'parts'}; run the suite first")
    unknown = sorted(set(development) - {r["scene"] for r in rows})
    if unknown:
        raise SystemExit(f"--development: no runs of {', '.join(unknown)} under {out / 'parts'}")
    table = gt.make_table(rows, development)
    (out / "table.json").write_text(json.dumps(table, indent=2) + "\n")
    (out / "table.md").write_text(gt.markdown(table))
    return table


def claim_output(out: Path) -> None:
    """Make ``out`` this benchmark's folder: new or empty (the marker is written first), or one
    it made before; anything else is refused untouched."""
    marker = out / MARKER
    if out.exists() and not out.is_dir():
        raise SystemExit(f"--out {out}: exists and is not a folder")
    if out.is_dir() and any(out.iterdir()) and not marker.is_file():
        raise SystemExit(
            f"--out {out}: not empty and not a folder of benchmarks/genesis_video.py (no "
            f"{MARKER}); give a new or empty folder, or one this benchmark wrote"
        )
    out.mkdir(parents=True, exist_ok=True)
    try:  # exclusive create: concurrent --part processes write it once
        fd = os.open(marker, os.O_WRONLY | os.O_CREAT | os.O_EXCL)
    except FileExistsError:
        return
    with os.fdopen(fd, "w") as f:
        f.write(json.dumps({"format": MARKER_FORMAT}) + "\n")


def parse_args(argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", type=Path, help="a `mosiv data suite --source genesis` folder")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--methods", default=",".join(METHODS), help=f"of {','.join(METHODS)}")
    parser.add_argument("--only", default=None, help="comma-separated scene names (E-P,...)")
    parser.add_argument("--method", default=None, help="with --part: the one method or variant")
    parser.add_argument("--seed", type=int, default=0, help="with --part: the Stage I seed")
    parser.add_argument("--set", action="append", default=[], help="[METHOD:]key=value")
    parser.add_argument("--ablation", action="store_true", help="also the supervision ablation")
    parser.add_argument(
        "--ablation-scenes",
        default=None,
        help=f"comma-separated (default: those of {','.join(ABLATION_SCENES)} in --scenes)",
    )
    parser.add_argument("--seeds", type=int, default=2, help="Stage I seeds of the ablation")
    parser.add_argument("--merge", action="store_true", help="only merge OUT/parts into tables")
    parser.add_argument("--write-results", type=Path, default=None, help="e.g. docs/RESULTS.md")
    parser.add_argument(
        "--development",
        default="",
        help="comma-separated scenes that settings were chosen on; the targets are judged on "
        "the other (test) scenes",
    )
    parser.add_argument(
        "--job-file",
        type=Path,
        default=None,
        help="write the planned runs as jobs of benchmarks/device_queue.py (one --part process "
        "per line, Stage I-II sharers after the run they copy), run none",
    )
    add_scale_flags(parser, "runs")
    parser.add_argument("--part", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if sum([args.part, args.merge, args.job_file is not None]) > 1:
        parser.error("--part runs one run, --merge tabulates, --job-file lists: give one")
    if not args.merge and args.scenes is None:
        parser.error("--scenes is required unless --merge")
    if args.seeds < 1:
        parser.error(f"--seeds {args.seeds}: must be at least 1")
    return args


def _split(text: str, valid, flag: str) -> list[str]:
    names = [n.strip() for n in text.split(",") if n.strip()]
    unknown = [n for n in names if n not in valid]
    if unknown or not names:
        raise SystemExit(f"{flag}: unknown {unknown or text!r}; valid: {', '.join(valid)}")
    return names


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    args = parse_args(argv)
    # the pipeline's progress (stages, global candidates) is logged at INFO: show it
    configure_logging(level_from_flags())
    runnable = [*METHODS, *ABLATION]
    sets = parse_sets(args.set, runnable)
    development = [d.strip() for d in args.development.split(",") if d.strip()]
    if args.merge:
        if not (args.out / MARKER).is_file():
            raise SystemExit(f"--merge: {args.out} is not a folder of this benchmark")
        table = merge(args.out, development)
    elif args.part:
        names = gi.find_scenes(args.scenes, args.only)
        if len(names) != 1 or args.method not in runnable:
            raise SystemExit(f"--part: give one scene (--only) and --method of {runnable}")
        claim_output(args.out)
        job = Job(names[0], args.method, args.seed)
        write_part(args.out, job, run_job(job, scenes=args.scenes, out=args.out, sets=sets))
        return 0
    else:
        methods = _split(args.methods, METHODS, "--methods")
        names = gi.find_scenes(args.scenes, args.only)
        ablation = []
        if args.ablation:
            wanted = ABLATION_SCENES
            if args.ablation_scenes is not None:
                wanted = _split(args.ablation_scenes, names, "--ablation-scenes")
            ablation = [n for n in names if n in wanted]
            if not ablation:
                raise SystemExit(f"--ablation: none of {', '.join(wanted)} in --scenes")
        jobs = plan_jobs(names, methods, ablation_scenes=ablation, seeds=args.seeds)
        if args.job_file is not None:
            write_job_file(args, jobs)
            return 0
        scale = scale_options(args)
        claim_output(args.out)
        run_jobs(args, jobs, scale)
        table = merge(args.out, development)
    print(gt.markdown(table))
    if args.write_results is not None:
        command = gi.command_line(argv).replace(
            "benchmarks/genesis_identify.py", "benchmarks/genesis_video.py", 1
        )
        gt.write_results(args.write_results, table, command=command, merged=args.merge)
        print(f"[genesis-video] wrote the section '{gt.SECTION}' of {args.write_results}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
