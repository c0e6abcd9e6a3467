"""Format versions of the JSON files the diagnosis writes, and the check that reads them.

Each file carries its format as a top-level ``"format"`` field. A reader accepts the formats it
lists and, where it can, files written before the field existed (the unversioned layout, told
apart by the field's absence); a file of any other format, e.g. one written by a newer MOSIV,
is refused with an error that names the file, the field and the supported values, rather than
being misread.
"""

from __future__ import annotations

from pathlib import Path

from mosiv_framework.errors import MosivError

#: diagnosis.json (``report.write_report``; read by ``replay``)
DIAGNOSIS_FORMAT = "mosiv-diagnosis/1"
#: the summary of a scored diagnosis suite, suite.json (``suite.run_suite``)
SUITE_FORMAT = "mosiv-diagnose-suite/1"
#: one suite entry's score, score.json (``suite.run_entry``, which resumes from it)
SCORE_FORMAT = "mosiv-diagnose-score/1"

FIELD = "format"


class FormatError(MosivError, ValueError):
    """A file's ``format`` field names a format this version of MOSIV cannot read (a user's
    error, reported by the CLI without a traceback)."""


def file_format(data: dict, source: str | Path, supported: tuple[str, ...]) -> str | None:
    """The format of ``data`` (a parsed JSON file from ``source``): one of ``supported``, or
    None for a file without the field (the unversioned layout).

    Raises:
        FormatError: the field holds anything else; the message names ``source``, the field,
            its value and the supported values.
    """
    value = data.get(FIELD)
    if value is None:
        return None
    if value not in supported:
        raise FormatError(
            f"{source}: field {FIELD!r} is {value!r}, which this version of MOSIV cannot read; "
            f"supported: {', '.join(repr(s) for s in supported)} (or no {FIELD!r} field, the "
            "unversioned layout)"
        )
    return value
