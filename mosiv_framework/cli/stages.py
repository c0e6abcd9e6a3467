"""Pipeline commands: ``mosiv run``, ``eval``, ``simulate``, ``diagnose``.

Each command says plainly when the stage it needs is not available in this installation,
rather than failing somewhere deep inside.
"""

from __future__ import annotations

from pathlib import Path

from mosiv_framework.errors import StageNotAvailable


def add_parsers(sub) -> None:
    run = sub.add_parser("run", help="run a recipe end to end (resumes a finished stage)")
    run.add_argument("recipe")
    run.add_argument("overrides", nargs="*", help="key=value overrides, e.g. scene.path=my_scene")
    run.set_defaults(handler=run_recipe)

    ev = sub.add_parser("eval", help="evaluate a finished run folder again (metrics, plots)")
    ev.add_argument("run_dir")
    ev.set_defaults(handler=not_built("eval", "the evaluation stage (issue #8)"))

    sim = sub.add_parser("simulate", help="novel interactions from a finished run")
    sim.add_argument("run_dir")
    sim.add_argument("--swap", help="swap the parameters of two objects, e.g. 1,2")
    sim.set_defaults(handler=not_built("simulate", "novel-interaction rollouts (issue #8)"))

    diag = sub.add_parser("diagnose", help="locate and explain what the fitted model misses")
    diag.add_argument("run_dir")
    diag.set_defaults(handler=not_built("diagnose", "missing-physics diagnosis (issue #9)"))


def not_built(command: str, what: str):
    def handler(args) -> int:
        raise StageNotAvailable(
            f"`mosiv {command}` needs {what}, which this version of MOSIV does not provide yet."
        )

    return handler


def run_recipe(args) -> int:
    from mosiv_framework.pipeline import run_pipeline
    from mosiv_framework.recipes import load_recipe

    recipe = load_recipe(args.recipe, args.overrides)
    run_pipeline(recipe, run_dir=Path(recipe.output.dir))
    return 0
