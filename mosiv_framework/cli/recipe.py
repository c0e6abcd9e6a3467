"""``mosiv recipe show|validate RECIPE [key=value ...]``."""

from __future__ import annotations


def add_parser(sub) -> None:
    p = sub.add_parser("recipe", help="print or validate a recipe with overrides applied")
    rsub = p.add_subparsers(dest="recipe_command", metavar="ACTION", required=True)
    show = rsub.add_parser("show", help="print the fully resolved recipe")
    validate = rsub.add_parser("validate", help="report every problem in a recipe at once")
    for q in (show, validate):
        q.add_argument("recipe", help="recipe YAML file")
        q.add_argument("overrides", nargs="*", help="key=value overrides (dotted keys)")
    show.set_defaults(handler=run_show)
    validate.set_defaults(handler=run_validate)


def run_show(args) -> int:
    from omegaconf import OmegaConf

    from mosiv_framework.recipes import load_recipe

    print(OmegaConf.to_yaml(load_recipe(args.recipe, args.overrides)), end="")
    return 0


def run_validate(args) -> int:
    import sys

    from mosiv_framework.recipes import check_recipe

    # raises ConfigError listing every problem; warnings: valid settings worth knowing about
    _, warnings = check_recipe(args.recipe, args.overrides)
    for warning in warnings:
        print(f"{args.recipe}: warning: {warning}", file=sys.stderr)
    print(f"{args.recipe}: valid")
    return 0
