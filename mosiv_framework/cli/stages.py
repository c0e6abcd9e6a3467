"""Pipeline commands: ``mosiv run``, ``eval``, ``simulate`` (``diagnose`` lives in diagnose.py).

Each command says plainly when the stage it needs is not available in this installation,
rather than failing somewhere deep inside.
"""

from __future__ import annotations

from pathlib import Path


def add_parsers(sub) -> None:
    run = sub.add_parser("run", help="run a recipe end to end (resumes a finished stage)")
    run.add_argument("recipe")
    run.add_argument("overrides", nargs="*", help="key=value overrides, e.g. scene.path=my_scene")
    run.set_defaults(handler=run_recipe)

    ev = sub.add_parser("eval", help="evaluate a finished run folder again (metrics, plots)")
    ev.add_argument("run_dir")
    ev.set_defaults(handler=run_eval)

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


def run_recipe(args) -> int:
    from mosiv_framework.pipeline import run_pipeline
    from mosiv_framework.recipes import load_recipe

    recipe = load_recipe(args.recipe, args.overrides)
    run_pipeline(recipe, run_dir=Path(recipe.output.dir))
    return 0


def run_eval(args) -> int:
    from mosiv_framework.pipeline import evaluate_run, simulator_refiner
    from mosiv_framework.pipeline.novel import load_finished_run

    run = load_finished_run(args.run_dir)
    metrics = evaluate_run(
        recipe=run.recipe,
        scene=run.scene,
        particles=run.particles,
        reconstruction=run.reconstruction,
        identified=run.identified,
        simulator=run.simulator(),
        run_dir=run.run_dir,
        refine=simulator_refiner(run.recipe.simulator),
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

    run = load_finished_run(args.run_dir)
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
    written = simulate_novel(run, params, frames=args.frames, out_dir=out, size=args.size)
    for what, path in written.items():
        print(f"{what}: {path}")
    return 0
