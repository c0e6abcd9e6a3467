"""``mosiv diagnose RUN_DIR`` and ``mosiv diagnose-suite OUT``: finding missing physics.

``diagnose`` reads a finished run folder and writes diagnosis.json / diagnosis.md into it;
``diagnose-suite`` generates scenes with concealed effects, runs and diagnoses each, and prints
the score table (docs/DIAGNOSIS.md).
"""

from __future__ import annotations

import argparse

from mosiv_framework.errors import ConfigError


def add_parsers(sub) -> None:
    diag = sub.add_parser("diagnose", help="locate and explain what the fitted model misses")
    diag.add_argument("run_dir", help="a folder written by `mosiv run`")
    diag.add_argument(
        "--budget",
        choices=("small", "full"),
        default="small",
        help="refit iterations, starts and candidates (small: minutes on CPU)",
    )
    diag.add_argument("--device", help="run the simulator on this device (cpu, cuda) instead")
    diag.set_defaults(handler=diagnose)
    _add_suite_parser(sub)


def _add_suite_parser(sub) -> None:
    suite = sub.add_parser(
        "diagnose-suite", help="score the diagnosis on scenes with concealed effects"
    )
    suite.add_argument("out", help="folder for the suite's scenes, runs and table")
    suite.add_argument("--small", action="store_true", help="three tiny scenes (CPU, minutes)")
    suite.add_argument(
        "--source",
        default="synth",
        help="whose suite: synth (default) or genesis (Genesis-recorded scenes with "
        "out-of-library fields; needs --split)",
    )
    suite.add_argument(
        "--split",
        help="dev or test split of the genesis suite: choose thresholds on dev (--replay), "
        "score once on test",
    )
    suite.add_argument("--recipe", help="recipe the scenes run with (default: the suite's own)")
    suite.add_argument("--budget", choices=("small", "full"), help="diagnosis budget")
    suite.add_argument("--only", help="comma-separated entry names to run (default: all)")
    stop_early = suite.add_mutually_exclusive_group()
    stop_early.add_argument(
        "--prepare-only",
        action="store_true",
        help="generate and run the entries (synthesis, identification, evaluation) but do not "
        "diagnose them; a later run with the same OUT path diagnoses them from those stages",
    )
    stop_early.add_argument(
        "--scenes-only",
        action="store_true",
        help="generate the entries' scenes and nothing else (where the scene source's engine "
        "is installed, e.g. genesis-world); the folder, copied to a GPU machine, is run and "
        "diagnosed there",
    )
    suite.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override every entry's recipe (repeatable), e.g. diagnose.refit_velocity_lr=1e-4",
    )
    from mosiv_framework.scale.flags import add_scale_flags

    add_scale_flags(suite, "entries")
    suite.add_argument(
        "--replay",
        action="store_true",
        help="run nothing: re-decide the finished entries in OUT from their saved error tables "
        "under the rule given by --z, --min-drop, --bic-margin, --block, --require-nonzero, "
        "--min-effect, --grid-bic, --heldout-statistic and --consistency-tolerance, and print "
        "the table",
    )
    _add_decision_rule_flags(suite)
    suite.add_argument(
        "--plot",
        metavar="PNG",
        help="with --replay: also draw the replayed suite into this file (a run always writes "
        "OUT/suite.png)",
    )
    suite.set_defaults(handler=diagnose_suite)


def _add_decision_rule_flags(suite) -> None:
    """The acceptance rule's settings that --replay decides the finished entries again under
    (each defaults to the recipe's, shown in brackets)."""
    suite.add_argument("--z", type=float, help="held-out drop over its bootstrap spread (2)")
    suite.add_argument(
        "--min-drop", type=float, help="smallest held-out drop worth naming, a fraction (0.2)"
    )
    suite.add_argument("--bic-margin", type=float, help="delta BIC a candidate must beat (0)")
    suite.add_argument("--block", type=int, help="frames per time block (2)")
    suite.add_argument(
        "--require-nonzero",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="accept only a term whose 95 %% coefficient interval excludes zero (on)",
    )
    suite.add_argument(
        "--min-effect",
        type=float,
        help="resolution floors a term's own effect on the fit frames must reach "
        "(0: off, the default)",
    )
    suite.add_argument(
        "--grid-bic",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="the grid-stability check also requires the information criterion at the second "
        "grid (on); decided again from the second grid's saved tables where recorded",
    )
    suite.add_argument(
        "--heldout-statistic",
        choices=["log", "sum"],
        help="how the held-out drop summarises the (object, time block) units: log, one minus "
        "the geometric mean of their error ratios (the default), or sum, one minus the ratio "
        "of the summed errors",
    )
    suite.add_argument(
        "--consistency-tolerance",
        type=float,
        help="standard deviation, relative to the pooled coefficient, that the agreement test "
        "across objects adds to each object's estimate (0.05)",
    )


def diagnose(args) -> int:
    from mosiv_framework.cli.main import resume_from
    from mosiv_framework.cli.stages import require_run_folder
    from mosiv_framework.diagnose import diagnose_run

    resume_from(args, require_run_folder(args.run_dir), "the last saved diagnosis step")
    overrides = {"device": args.device} if args.device else None
    # progress is logged; the command's result, the verdict and where the report is, is printed
    summary = diagnose_run(args.run_dir, budget=args.budget, simulator_overrides=overrides)
    accepted = summary.get("accepted")
    print(f"verdict: {summary['verdict']}" + (f" ({accepted['name']})" if accepted else ""))
    print(f"report: {args.run_dir}/diagnosis.md")
    return 0 if summary["verdict"] else 1


def diagnose_suite(args) -> int:
    from mosiv_framework.diagnose.suite import run_suite, table

    if args.replay:
        return _replay(args)
    if args.plot:
        raise ConfigError("--plot draws a replayed suite: give it with --replay")
    from mosiv_framework.cli.main import resume_from
    from mosiv_framework.cli.stages import check_writable_folder
    from mosiv_framework.scale.flags import scale_options

    check_writable_folder(args.out, "OUT")
    resume_from(args, args.out, "its finished entries and stages", "suite folder")

    summary = run_suite(
        args.out,
        small=args.small,
        recipe=args.recipe,
        budget=args.budget,
        only=[name for name in args.only.split(",") if name] if args.only else None,
        **scale_options(args),
        overrides=args.overrides,
        prepare_only=args.prepare_only,
        source=args.source,
        split=args.split,
        scenes_only=args.scenes_only,
    )
    if args.scenes_only:
        print(f"scenes generated: {', '.join(summary['generated']) or 'none'}")
    elif args.prepare_only:
        print(f"prepared for diagnosis: {', '.join(summary['prepared']) or 'none'}")
        if summary.get("retried"):
            print(f"run again after their worker died: {', '.join(summary['retried'])}")
    else:
        print(table(summary))
    return 0


def _replay(args) -> int:
    from mosiv_framework.diagnose.decide import DecideOptions
    from mosiv_framework.diagnose.replay import replay_suite
    from mosiv_framework.diagnose.suite import table

    given = {
        "z": args.z,
        "min_drop": args.min_drop,
        "bic_margin": args.bic_margin,
        "block": args.block,
        "require_nonzero": args.require_nonzero,
        "min_effect": args.min_effect,
        "grid_bic": args.grid_bic,
        "heldout_statistic": args.heldout_statistic,
        "consistency_tolerance": args.consistency_tolerance,
    }
    options = DecideOptions(**{k: v for k, v in given.items() if v is not None})
    from mosiv_framework.cli.stages import require_folder

    require_folder(args.out, "suite folder", "the OUT of a finished `mosiv diagnose-suite`")
    summary = replay_suite(
        args.out, options, small=args.small, source=args.source, split=args.split
    )
    print(f"replayed under {summary['rule']}")
    print(table(summary))
    if args.plot:
        from mosiv_framework.diagnose.suite_plot import plot_suite

        print(f"figure: {plot_suite(summary, args.plot)}")
    return 0
