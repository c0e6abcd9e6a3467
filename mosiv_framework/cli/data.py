"""``mosiv data synth|check``: make scenes with a registered SceneSource, validate scene folders."""

from __future__ import annotations

from pathlib import Path


def add_parser(sub) -> None:
    p = sub.add_parser("data", help="generate or check scenes in the mosiv-scene/1 format")
    dsub = p.add_subparsers(dest="data_command", metavar="ACTION", required=True)
    check = dsub.add_parser("check", help="validate a scene folder and list every problem")
    check.add_argument("scene_dir")
    check.set_defaults(handler=run_check)
    synth = dsub.add_parser("synth", help="generate a scene with a registered scene source")
    synth.add_argument("out_dir", help="folder to write the scene into")
    synth.add_argument("--source", default="synth", help="registered scene source (default: synth)")
    synth.add_argument(
        "--conceal",
        action="append",
        default=[],
        metavar="KIND[:param=value,...]",
        help="add physics the scene does not declare (repeatable): linear_drag, quadratic_drag, "
        "wind, gravity, ground_friction; e.g. --conceal wind:acceleration=1.5,0,0",
    )
    synth.add_argument(
        "options", nargs="*", help="source options as key=value (see `mosiv plugins`)"
    )
    synth.set_defaults(handler=run_synth)


def run_check(args) -> int:
    from mosiv_framework.scene.check import run_check as check

    return check(Path(args.scene_dir))


def run_synth(args) -> int:
    from omegaconf import OmegaConf

    from mosiv_framework.errors import ConfigError
    from mosiv_framework.registry import get_registry

    bad = [o for o in args.options if "=" not in o]
    if bad:
        raise ConfigError([f"option {o!r} is not of the form key=value" for o in bad])
    options = OmegaConf.to_container(OmegaConf.from_dotlist(args.options))
    if args.conceal:
        if "conceal" in options:
            raise ConfigError(
                "give concealed effects either as --conceal or as conceal=..., not both"
            )
        options["conceal"] = list(args.conceal)
    source = get_registry().create("scene_source", args.source, options)
    path = source.generate(Path(args.out_dir))
    print(f"wrote scene {path}")
    return 0
