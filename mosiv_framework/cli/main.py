"""The ``mosiv`` command line: one sub-command per job, each in its own module.

Heavy imports (torch, image I/O, backends) happen inside the command that needs them, so
``mosiv --help`` and ``mosiv plugins`` stay fast.

Global options, before the sub-command: ``-v``/``--verbose`` (DEBUG log records, with the
logger's name), ``-q``/``--quiet`` (warnings and errors only; ``-qq``: errors only),
``--version``. Log records go to stderr as ``[mosiv] message``; what a command was asked for
(tables, JSON, paths it wrote) goes to stdout.

Errors end the command with one message on stderr, ``mosiv COMMAND: error: ...``, and the exit
status of their kind (``mosiv_framework.errors.EXIT_CODES``, docs/CLI.md); a traceback is shown
only with ``-v``. Ctrl-C ends with one line naming the folder a rerun resumes from.
"""

from __future__ import annotations

import argparse
import errno
import logging
import shlex
import sys
import traceback
from pathlib import Path

from mosiv_framework.errors import (
    EXIT_INTERNAL,
    EXIT_INTERRUPTED,
    EXIT_OUTPUT,
    MosivError,
)

#: what an OSError's number means for the path it names, and what to do about it
_OS_ADVICE: dict[int, str] = {
    errno.EACCES: "permission denied; choose another folder or make this one writable",
    errno.EPERM: "operation not permitted; choose another folder or fix its permissions",
    errno.EROFS: "the file system is read-only; choose a folder on a writable disk",
    errno.ENOTDIR: "a part of this path is a file, not a folder",
    errno.EISDIR: "this is a folder where a file is expected",
    errno.EEXIST: "this exists already as a file where a folder is expected",
    errno.ELOOP: "this is a symbolic link loop",
    errno.ENOENT: "no such file or folder",
    errno.ENOSPC: "no space left on the disk",
    errno.ENAMETOOLONG: "the name is too long for the file system",
}


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
    from mosiv_framework.cli import bench, data, diagnose, parity, plugins, recipe, stages, view

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
    from mosiv_framework.cli import importing

    importing.add_parser(sub)  # `data import`, under the data command
    bench.add_parser(sub)
    parity.add_parser(sub)
    stages.add_parsers(sub)
    diagnose.add_parsers(sub)
    view.add_parser(sub)
    from mosiv_framework.cli import export

    export.add_parser(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run the command line ``argv`` (default: ``sys.argv[1:]``); returns the exit status."""
    from mosiv_framework.logs import configure_logging, level_from_flags

    try:
        parser = build_parser()
        args = parser.parse_args(argv)
    except KeyboardInterrupt:
        print("mosiv: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    configure_logging(level_from_flags(args.verbose, args.quiet))
    logging.getLogger(__name__).debug("command line: %s", sys.argv if argv is None else argv)
    try:
        return int(args.handler(args) or 0)
    except KeyboardInterrupt:
        print(interrupted_message(args), file=sys.stderr)
        return EXIT_INTERRUPTED
    except MosivError as exc:
        return _fail(args, error_message(exc), exc.exit_code)
    except OSError as exc:
        if exc.filename is None:  # not about a path the user gave: a bug or the system
            return _internal(args, argv, exc)
        return _fail(args, os_error_message(exc), EXIT_OUTPUT)
    except Exception as exc:  # noqa: BLE001 -- the last line of defence: no bare traceback
        if _raised_by_ctrl_c(exc):
            print(interrupted_message(args), file=sys.stderr)
            return EXIT_INTERRUPTED
        return _internal(args, argv, exc)


def _raised_by_ctrl_c(exc: BaseException) -> bool:
    """Whether a KeyboardInterrupt lies in the chain of ``exc``: Python 3.11 wraps an exception
    raised while a class body is being set up (a lazy import a Ctrl-C lands in, e.g. torch's at
    the first optimiser step) in a RuntimeError, which must still read as an interruption."""
    seen: set[int] = set()
    while exc is not None and id(exc) not in seen:
        if isinstance(exc, KeyboardInterrupt):
            return True
        seen.add(id(exc))
        exc = exc.__cause__ or exc.__context__
    return False


def resume_from(
    args, folder: str | Path, what: str = "the last finished stage", kind: str = "run folder"
) -> None:
    """Record on ``args`` the folder a rerun of the command resumes from, named on Ctrl-C as
    ``kind`` (what the folder is) with ``what`` a rerun takes up again."""
    args.resume_folder = Path(folder)
    args.resume_what = what
    args.resume_kind = kind


def interrupted_message(args) -> str:
    """The one line printed on Ctrl-C: where a rerun of the same command resumes."""
    folder = getattr(args, "resume_folder", None)
    if folder is None:
        return f"mosiv {args.command}: interrupted; rerun the same command to start it again"
    return (
        f"mosiv {args.command}: interrupted; rerun the same command to resume from "
        f"{args.resume_what} ({args.resume_kind}: {folder})"
    )


def error_message(exc: MosivError) -> str:
    """The message of a MosivError: one line, or one line per problem under a count."""
    problems = getattr(exc, "problems", None) or [str(exc)]
    if len(problems) == 1:
        return problems[0]
    return f"{len(problems)} problems:\n" + "\n".join(f"- {p}" for p in problems)


def os_error_message(exc: OSError) -> str:
    """``PATH: what went wrong; what to do`` for an OSError about a path."""
    paths = " -> ".join(repr(str(f)) for f in (exc.filename, exc.filename2) if f is not None)
    advice = _OS_ADVICE.get(exc.errno, exc.strerror or type(exc).__name__)
    return f"{paths}: {advice}"


def _fail(args, message: str, code: int) -> int:
    if args.verbose:
        traceback.print_exc()
    print(f"mosiv {args.command}: error: {message}", file=sys.stderr)
    return code


def _internal(args, argv: list[str] | None, exc: BaseException) -> int:
    if args.verbose:
        traceback.print_exc()
        hint = "the traceback above shows where; please report it"
    else:
        words = sys.argv[1:] if argv is None else list(argv)
        # -q before the command would clash with the -v put in front
        head = words.index(args.command) if args.command in words else 0
        words = [w for w in words[:head] if w.lstrip("-q") and w != "--quiet"] + words[head:]
        hint = f"rerun as `mosiv -v {shlex.join(words)}` to see the traceback"
    print(
        f"mosiv {args.command}: internal error: {type(exc).__name__}: {exc}; {hint}",
        file=sys.stderr,
    )
    return EXIT_INTERNAL


if __name__ == "__main__":
    sys.exit(main())
