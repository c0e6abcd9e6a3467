"""Pipeline commands: ``mosiv run``, ``eval``, ``simulate`` (``diagnose`` lives in diagnose.py).

Each command says plainly when the stage it needs is not available in this installation,
rather than failing somewhere deep inside. Paths are checked before anything runs: a folder to
read must exist (nothing is created in its place), a folder to write must be writable.
"""

from __future__ import annotations

import os
from pathlib import Path

from mosiv_framework.errors import ConfigError, OutputError, SceneFormatError


def add_parsers(sub) -> None:
    run = sub.add_parser("run", help="run a recipe end to end (resumes a finished stage)")
    run.add_argument("recipe")
    run.add_argument("overrides", nargs="*", help="key=value overrides, e.g. scene.path=my_scene")
    run.add_argument(
        "--force",
        action="store_true",
        help="with output.resume=false, remove the previous run's files from output.dir and "
        "start afresh (only files a run writes; anything else there is kept)",
    )
    run.set_defaults(handler=run_recipe)

    ev = sub.add_parser("eval", help="evaluate a finished run folder again (metrics, plots)")
    ev.add_argument("run_dir")
    ev.set_defaults(handler=run_eval)

    iv = sub.add_parser(
        "intervals",
        help="compute a finished run's parameter intervals again (another --method, or newer "
        "interval code) without identifying again",
    )
    iv.add_argument("run_dir")
    iv.add_argument(
        "--method",
        choices=("laplace", "sandwich"),
        help="default: the run's identify.interval_method",
    )
    iv.add_argument("--device", help="simulator device, e.g. cpu or cuda (default: the run's)")
    iv.add_argument("--scene", help="the run's scene folder, where it has moved since the run")
    iv.set_defaults(handler=run_intervals)

    sim = sub.add_parser(
        "simulate",
        help="novel interactions from a finished run: swapped materials, edited parameters, "
        "new initial velocities (rollout.npz, params.json, video.gif)",
    )
    sim.add_argument("run_dir")
    sim.add_argument("--swap", help="swap the materials of two objects, e.g. 1,2")
    sim.add_argument(
        "--set",
        dest="sets",
        action="append",
        default=[],
        metavar="objK.NAME=VALUE",
        help="set a parameter (SI units), e.g. obj1.E=1e5, ground_friction=0.5 or "
        "term.wind.acceleration=0,1.5,0 (adds the term if the run did not model it); repeatable",
    )
    sim.add_argument(
        "--velocity",
        dest="velocities",
        action="append",
        default=[],
        metavar="objK=VX,VY,VZ",
        help="new initial velocity of an object in m/s, e.g. obj1=0,0,1; repeatable",
    )
    sim.add_argument("--frames", type=int, help="frames to simulate (default: the scene's)")
    sim.add_argument("--out", help="output folder (default: RUN_DIR/simulate/<edits>)")
    sim.add_argument("--size", type=int, default=256, help="video size in pixels")
    sim.set_defaults(handler=run_simulate)


def require_folder(path: str | Path, what: str, valid: str) -> Path:
    """``path`` if it is an existing folder; else ConfigError naming it as ``what`` and saying
    what is ``valid``. Nothing is created: a command reading a folder never makes one."""
    folder = Path(path)
    if folder.is_dir():
        return folder
    state = "is a file, not a folder" if folder.exists() else "does not exist"
    if folder.is_symlink() and not folder.exists():
        state = "is a broken symbolic link"
    raise ConfigError(f"{what} {str(path)!r} {state}; give {valid}")


def require_run_folder(path: str | Path) -> Path:
    """``path`` if it is an existing folder; else ConfigError naming it (nothing is created)."""
    return require_folder(path, "run folder", "a folder written by `mosiv run` (its output.dir)")


def check_writable_folder(path: str | Path, what: str) -> None:
    """OutputError unless ``path`` is, or can be made, a writable folder; ``what`` names it
    in the message (e.g. ``output.dir``). Nothing is created."""
    target = Path(path)
    existing = target
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    if not existing.is_dir():
        where = "" if existing == target else f" ({str(existing)!r} on its path)"
        raise OutputError(
            f"{what}={str(target)!r}: is a file{where}, not a folder; give a folder path to write to"
        )
    if not os.access(existing, os.W_OK | os.X_OK):
        raise OutputError(
            f"{what}={str(target)!r}: {str(existing)!r} is not writable by this user; choose "
            f"another folder or change its permissions"
        )


def check_scene_path(path: str | Path) -> None:
    """SceneFormatError if ``scene.path`` names a file (a folder to read or generate into)."""
    if Path(path).exists() and not Path(path).is_dir():
        raise SceneFormatError(
            f"scene.path={str(path)!r}: is a file, not a scene folder; give the folder that "
            f"holds scene.json, cameras.json, rgb/ and masks/ (or a new folder for scene.source "
            f"to generate the scene into)"
        )


def run_intervals(args) -> int:
    from mosiv_framework.pipeline.reinterval import recompute_intervals

    run_dir = require_run_folder(args.run_dir)
    if args.scene is not None:
        require_folder(args.scene, "--scene", "the scene folder the run was made from")
    record = recompute_intervals(
        run_dir, method=args.method, device=args.device, scene_path=args.scene
    )
    print(f"{record['method']} 95 % intervals of {run_dir} (frames 1..{record['horizon']}):")
    for owner, entries in sorted(record["intervals"].items()):
        entries = {"": entries} if "kind" in entries else entries
        for name, got in sorted(entries.items()):
            low, high = got["low"], got["high"]
            span = f"{'-' if low is None else f'{low:.4g}'} .. {'-' if high is None else f'{high:.4g}'}"
            print(f"  {owner}{'.' + name if name else ''}: {got['kind']} {span}")
    print("written into identify/history.json, identified.json and metrics.json")
    return 0


def run_recipe(args) -> int:
    from mosiv_framework.cli.main import resume_from
    from mosiv_framework.pipeline import run_pipeline
    from mosiv_framework.recipes import load_recipe

    recipe = load_recipe(args.recipe, args.overrides)
    check_scene_path(recipe.scene.path)
    check_writable_folder(recipe.output.dir, "output.dir")
    resume_from(args, recipe.output.dir)
    run_pipeline(recipe, run_dir=Path(recipe.output.dir), force=args.force)
    return 0


def run_eval(args) -> int:
    from mosiv_framework.pipeline import evaluate_run, simulator_refiner
    from mosiv_framework.pipeline.novel import load_finished_run

    run = load_finished_run(require_run_folder(args.run_dir))
    metrics = evaluate_run(
        recipe=run.recipe,
        scene=run.scene,
        particles=run.particles,
        reconstruction=run.reconstruction,
        identified=run.identified,
        simulator=run.simulator(),
        run_dir=run.run_dir,
        refine=simulator_refiner(run.simulator_section),
    )
    future = metrics["future"]
    print(
        f"{run.run_dir.root}: observed cd {metrics['observed']['cd_mm2']:.3g} mm^2"
        + (f", future cd {future['cd_mm2']:.3g} mm^2" if future else "")
        + f"; wrote {run.run_dir.path('metrics.json')}"
    )
    return 0


def run_simulate(args) -> int:
    from mosiv_framework.pipeline.novel import edit_params, load_finished_run, simulate_novel

    run = load_finished_run(require_run_folder(args.run_dir))
    params = edit_params(run.identified, swap=args.swap, sets=args.sets, velocities=args.velocities)
    label = (
        "-".join(
            ([f"swap{args.swap.replace(',', '-')}"] if args.swap else [])
            + [s.replace("=", "_") for s in args.sets]
            + [v.replace("=", "_v").replace(",", "_") for v in args.velocities]
        )
        or "identified"
    )
    out = Path(args.out) if args.out else run.run_dir.path(f"simulate/{label}")
    check_writable_folder(out, "--out")
    written = simulate_novel(run, params, frames=args.frames, out_dir=out, size=args.size)
    for what, path in written.items():
        print(f"{what}: {path}")
    return 0
