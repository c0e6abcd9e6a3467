"""Logging set-up of the ``mosiv`` command line and of the worker processes it starts.

Modules log through ``logging.getLogger(__name__)``; nothing is configured on import, so a
program that uses MOSIV as a library keeps its own logging set-up. The CLI calls
:func:`configure_logging` once: one handler on the root logger writes to stderr in the
``[mosiv] message`` form. Records of MOSIV's own loggers (``mosiv_framework.*``) and of its
plugins (any logger whose name starts with ``mosiv_``, e.g. ``mosiv_gauss.train``) pass from the
chosen level up; other libraries' records pass from WARNING up only, so ``-v`` does not drown
the output in third-party debug lines.

The chosen level is also put in ``$MOSIV_LOG_LEVEL``: worker processes (spawned, so they do not
inherit the parent's logging set-up) call :func:`configure_from_environment` and log alike.
"""

from __future__ import annotations

import logging
import os
import sys

#: environment variable carrying the level to worker processes (and a default for the CLI)
LEVEL_VARIABLE = "MOSIV_LOG_LEVEL"
#: logger-name prefixes whose records pass at the chosen level (the core and its plugins)
MOSIV_PREFIXES = ("mosiv_framework", "mosiv_")


def is_mosiv_logger(name: str) -> bool:
    return name == "mosiv_framework" or name.startswith(MOSIV_PREFIXES)


class _MosivFilter(logging.Filter):
    def __init__(self, level: int):
        super().__init__()
        self.level = level

    def filter(self, record: logging.LogRecord) -> bool:
        floor = self.level if is_mosiv_logger(record.name) else max(self.level, logging.WARNING)
        return record.levelno >= floor


class _Formatter(logging.Formatter):
    """``[mosiv] message``; warnings and errors say so; at DEBUG the logger's name is shown."""

    def __init__(self, show_names: bool):
        super().__init__()
        self.show_names = show_names

    def format(self, record: logging.LogRecord) -> str:
        text = record.getMessage()
        if record.levelno >= logging.WARNING:
            text = f"{record.levelname.lower()}: {text}"
        if self.show_names:
            text = f"{record.name}: {text}"
        if record.exc_info:
            text += "\n" + self.formatException(record.exc_info)
        return f"[mosiv] {text}"


class _StderrHandler(logging.StreamHandler):
    """Writes to whatever ``sys.stderr`` is at the time of the record (pytest swaps it)."""

    def __init__(self) -> None:
        super().__init__(sys.stderr)

    @property
    def stream(self):  # type: ignore[override]
        return sys.stderr

    @stream.setter
    def stream(self, value) -> None:  # StreamHandler.__init__ assigns it
        pass


def level_from_flags(verbose: int = 0, quiet: int = 0) -> int:
    """DEBUG with ``-v``, WARNING with ``-q``, ERROR with ``-qq``; else ``$MOSIV_LOG_LEVEL`` or
    INFO."""
    if verbose:
        return logging.DEBUG
    if quiet:
        return logging.WARNING if quiet == 1 else logging.ERROR
    return parse_level(os.environ.get(LEVEL_VARIABLE, "")) or logging.INFO


def parse_level(text: str) -> int | None:
    """A level from a name (``debug``, ``INFO``) or a number; None for empty or unknown text."""
    text = text.strip()
    if text.isdigit():
        return int(text)
    level = logging.getLevelName(text.upper()) if text else None
    return level if isinstance(level, int) else None


def configure_logging(level: int) -> None:
    """Send MOSIV's and its plugins' log records of ``level`` and up to stderr.

    Calling it again replaces the earlier set-up rather than adding a second handler.
    """
    root = logging.getLogger()
    for handler in [h for h in root.handlers if isinstance(h, _StderrHandler)]:
        root.removeHandler(handler)
    handler = _StderrHandler()
    handler.addFilter(_MosivFilter(level))
    handler.setFormatter(_Formatter(show_names=level <= logging.DEBUG))
    root.addHandler(handler)
    # the root's level gates records before any handler sees them; other libraries' records
    # are held back to WARNING by the filter instead
    root.setLevel(min(level, logging.WARNING))
    logging.getLogger("mosiv_framework").setLevel(level)
    os.environ[LEVEL_VARIABLE] = logging.getLevelName(level)


def configure_from_environment() -> None:
    """In a worker process: log like the parent, if the parent set ``$MOSIV_LOG_LEVEL``."""
    level = parse_level(os.environ.get(LEVEL_VARIABLE, ""))
    if level is not None:
        configure_logging(level)
