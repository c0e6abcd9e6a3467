"""The ``mosiv`` command line: one sub-command per job, each in its own module.

Heavy imports (torch, image I/O, backends) happen inside the command that needs them, so
``mosiv --help`` and ``mosiv plugins`` stay fast.

Global options, before the sub-command: ``-v``/``--verbose`` (DEBUG log records, with the
logger's name), ``-q``/``--quiet`` (warnings and errors only; ``-qq``: errors only),
``--version``. Log records go to stderr as ``[mosiv] message``; what a command was asked for
(tables, JSON, paths it wrote) goes to stdout.
"""

from __future__ import annotations

import argparse
import logging
import sys

from mosiv_framework.errors import MosivError


class _VersionAction(argparse.Action):
    """``--version``: looked up only when asked for, then exits like argparse's own."""

    def __init__(self, option_strings, dest, **kwargs):
        super().__init__(option_strings, dest, nargs=0, default=argparse.SUPPRESS, **kwargs)

    def __call__(self, parser, namespace, values, option_string=None):
        print(version_text())
        parser.exit()


def version_text() -> str:
    """``mosiv-framework X`` and one line per installed plugin distribution with its version."""
    from importlib import metadata

    from mosiv_framework.registry.manager import ENTRY_POINT_GROUP

    try:
        core = metadata.version("mosiv-framework")
    except metadata.PackageNotFoundError:
        core = "unknown (not installed)"
    # plugins are named by their entry points' distributions; none is imported for this
    dists = {
        ep.dist.name: ep.dist.version
        for ep in metadata.entry_points(group=ENTRY_POINT_GROUP)
        if ep.dist is not None and ep.dist.name != "mosiv-framework"
    }
    lines = [f"mosiv-framework {core}"]
    lines += [f"  {name} {dists[name]}" for name in sorted(dists)]
    return "\n".join(lines)


def build_parser() -> argparse.ArgumentParser:
    from mosiv_framework.cli import bench, data, diagnose, parity, plugins, recipe, stages

    parser = argparse.ArgumentParser(
        prog="mosiv",
        description="MOSIV: multi-object system identification from multi-view video.",
    )
    parser.add_argument(
        "--version",
        action=_VersionAction,
        help="print the versions of mosiv-framework and the installed plugins, and exit",
    )
    loudness = parser.add_mutually_exclusive_group()
    loudness.add_argument(
        "-v", "--verbose", action="count", default=0, help="show debug messages (log level DEBUG)"
    )
    loudness.add_argument(
        "-q",
        "--quiet",
        action="count",
        default=0,
        help="show only warnings and errors (-qq: errors only)",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    plugins.add_parser(sub)
    recipe.add_parser(sub)
    data.add_parser(sub)
    bench.add_parser(sub)
    parity.add_parser(sub)
    stages.add_parsers(sub)
    diagnose.add_parsers(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    from mosiv_framework.logs import configure_logging, level_from_flags

    parser = build_parser()
    args = parser.parse_args(argv)
    configure_logging(level_from_flags(args.verbose, args.quiet))
    logging.getLogger(__name__).debug("command line: %s", sys.argv if argv is None else argv)
    try:
        return int(args.handler(args) or 0)
    except MosivError as exc:
        print(f"mosiv {args.command}: error:\n{exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
