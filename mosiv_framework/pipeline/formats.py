"""Format versions of the files a run writes, and the check its readers apply.

Every JSON file of a run folder carries a top-level ``"format"`` naming its layout and version
(``mosiv-metrics/1``, ...); ``recipe.yaml`` starts with the comment line ``# mosiv-recipe/1``.
A reader accepts a file without the field (the layout written before the field existed, which
is version 1) and rejects a format it does not know, naming the file, the field, the value and
the formats it supports, rather than misreading a newer layout. ``identify/history.json`` and
``identify/library.json`` hold lists: their versioned layout is an object with the format and
the list under ``entries``.

``run.json`` marks a folder as a run folder (see ``mosiv_framework.pipeline.rundir``).
``identified.json`` may hold ``warnings``: what the recipe's settings cap (e.g. a stiffness
ceiling below a law's bound) and a contact choice that was a close call, as the run logged
them.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from mosiv_framework.errors import EXIT_OUTPUT, MosivError

FIELD = "format"

METRICS = "mosiv-metrics/1"
IDENTIFIED = "mosiv-identified/1"
HISTORY = "mosiv-history/1"
LIBRARY = "mosiv-library/1"
STAGE = "mosiv-stage/1"
PARAMS = "mosiv-params/1"
RECIPE = "mosiv-recipe/1"
RUN = "mosiv-run/1"

#: run-folder file -> the formats its readers understand (the first is the one written)
FILE_FORMATS: dict[str, tuple[str, ...]] = {
    "metrics.json": (METRICS,),
    "identified.json": (IDENTIFIED,),
    "identify/history.json": (HISTORY,),
    "identify/library.json": (LIBRARY,),
    "params.json": (PARAMS,),
    "run.json": (RUN,),
}
STAGE_FORMATS: tuple[str, ...] = (STAGE,)  # stages/<stage>.json, the completion markers


class FormatError(MosivError):
    """A run file declares a format this version of MOSIV cannot read."""

    exit_code = EXIT_OUTPUT  # a file of the run folder cannot be read (docs/CLI.md)


def formats_of(name: str) -> tuple[str, ...] | None:
    """The formats supported for the run-folder file ``name`` (None: not a versioned file)."""
    if name.startswith("stages/") and name.endswith(".json"):
        return STAGE_FORMATS
    return FILE_FORMATS.get(name)


def stamped(fmt: str, data: dict) -> dict:
    """``data`` with ``"format": fmt`` first."""
    return {FIELD: fmt, **{k: v for k, v in data.items() if k != FIELD}}


def stamped_entries(fmt: str, entries: list) -> dict:
    """A list file's versioned layout: the format and the list under ``entries``."""
    return {FIELD: fmt, "entries": list(entries)}


def check_format(data: Any, supported: tuple[str, ...], *, path: str | Path) -> Any:
    """Return ``data`` if its ``format`` is one of ``supported`` or absent; else raise
    FormatError naming the file, field, value and the supported formats."""
    if isinstance(data, dict) and FIELD in data and data[FIELD] not in supported:
        raise FormatError(
            f"{path}: field {FIELD!r} is {data[FIELD]!r}, which this version of MOSIV cannot "
            f"read; it supports {', '.join(map(repr, supported))} (or no {FIELD!r} field, the "
            f"first layout)"
        )
    return data


def entries(data: Any, supported: tuple[str, ...], *, path: str | Path) -> list:
    """The list a list file holds, in either layout (a bare list, or the versioned object)."""
    if isinstance(data, list):
        return data
    check_format(data, supported, path=path)
    if not isinstance(data, dict) or not isinstance(data.get("entries"), list):
        raise FormatError(f"{path}: expected a list or an object with a list under 'entries'")
    return data["entries"]


def read_history(path: str | Path) -> list[dict]:
    """The per-iteration records of an ``identify/history.json``."""
    return entries(json.loads(Path(path).read_text()), (HISTORY,), path=path)


def recipe_header() -> bytes:
    """The first line of a run's recipe.yaml: a YAML comment, so loading ignores it."""
    return f"# {RECIPE}\n".encode()
