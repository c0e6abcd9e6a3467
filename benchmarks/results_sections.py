"""Writing a benchmark's section into a markdown results file (docs/RESULTS.md,
docs/BENCHMARKS.md): the section replaced in place, the reading written by hand below
``KEEP_MARKER`` kept, the prose wrapped as the files wrap it."""

from __future__ import annotations

import textwrap


def _fill(text: str, **indents) -> str:
    """``text`` wrapped at 100 columns, never inside a word or a hyphenated name (E-P-S)."""
    return textwrap.fill(text, 100, break_long_words=False, break_on_hyphens=False, **indents)


#: a line that starts the part of a section written by hand (the reading of its numbers): a
#: regenerated section keeps everything from this line to the section's end
KEEP_MARKER = "<!-- written by hand below: kept when the section above is regenerated -->"


def replace_section(text: str, body: str, *, title: str, before: str) -> str:
    """``text`` with its ``## title`` section (up to the next level-2 heading) replaced by
    ``body``; a missing section goes before ``## before``, else at the end. From a
    ``KEEP_MARKER`` line on, the old section is kept after the new body."""
    lines = text.splitlines(keepends=True)
    heads = [i for i, line in enumerate(lines) if line.startswith("## ")]
    body = body.rstrip("\n") + "\n\n"
    start = next((i for i in heads if lines[i].strip() == f"## {title}"), None)
    if start is None:
        at = next((i for i in heads if lines[i].strip() == f"## {before}"), None)
        if at is None:
            return text.rstrip("\n") + "\n\n" + body.rstrip("\n") + "\n"
        return "".join(lines[:at]) + body + "".join(lines[at:])
    end = next((i for i in heads if i > start), len(lines))
    kept = next((i for i in range(start, end) if lines[i].strip() == KEEP_MARKER), None)
    if kept is not None:  # the reading written by hand stays below the regenerated numbers
        body += "".join(lines[kept:end]).rstrip("\n") + "\n\n"
    if end == len(lines):
        body = body.rstrip("\n") + "\n"
    return "".join(lines[:start]) + body + "".join(lines[end:])
