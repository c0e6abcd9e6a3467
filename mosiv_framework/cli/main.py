"""The ``mosiv`` command line: one sub-command per job, each in its own module.

Heavy imports (torch, image I/O, backends) happen inside the command that needs them, so
``mosiv --help`` and ``mosiv plugins`` stay fast.
"""

from __future__ import annotations

import argparse
import sys

from mosiv_framework.errors import MosivError


def build_parser() -> argparse.ArgumentParser:
    from mosiv_framework.cli import bench, data, diagnose, parity, plugins, recipe, stages

    parser = argparse.ArgumentParser(
        prog="mosiv",
        description="MOSIV: multi-object system identification from multi-view video.",
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
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.handler(args) or 0)
    except MosivError as exc:
        print(f"mosiv {args.command}: error:\n{exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
