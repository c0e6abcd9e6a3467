"""Write a diagnosis suite's entries as jobs of benchmarks/device_queue.py, one per entry.

A full-budget diagnosis of a Genesis scene takes minutes of host-bound GPU work, so a suite
runs best as one ``mosiv diagnose-suite OUT --only ENTRY`` process per entry, several sharing
each GPU under MPS (docs/BENCHMARKS.md, Diagnosis time)::

    python benchmarks/diagnose_jobs.py OUT --source genesis --split test --budget full > JOBS
    python3 benchmarks/device_queue.py start JOBS --mps --slots 6 --threads 2

Entries already scored in OUT (their ``score.json``) are left out, so the same command after
a lease lists what is still to run. OUT is written as an absolute path: each job runs in its
own snapshot of the checkout.
"""

from __future__ import annotations

import argparse
import shlex
import sys
from pathlib import Path

from mosiv_framework.diagnose.suite import suite_selection


def job_lines(
    out: Path,
    *,
    source: str,
    split: str | None,
    budget: str,
    only: list[str] | None = None,
    overrides: list[str] | None = None,
) -> list[str]:
    """``NAME COMMAND`` per entry of the suite still to score, in suite order.

    Args:
        out: the suite folder (made absolute).
        source, split: which suite (``suite.suite_selection``).
        budget: the diagnosis budget, small or full.
        only: entry names to keep (None: all); an unknown name raises ValueError naming the
            valid ones.
        overrides: ``--set KEY=VALUE`` overrides passed to every entry.

    Returns:
        The job lines of ``benchmarks/device_queue.py``.
    """
    out = Path(out).resolve()
    entries = suite_selection(False, source, split)
    names = [e.name for e in entries]
    unknown = sorted(set(only or []) - set(names))
    if unknown:
        raise ValueError(
            f"--only {', '.join(unknown)}: not in the suite; valid: {', '.join(names)}"
        )
    lines = []
    for entry in entries:
        if only and entry.name not in only:
            continue
        if (out / entry.name / "score.json").exists():
            continue  # scored already
        words = ["mosiv", "diagnose-suite", str(out), "--source", source]
        words += ["--split", split] if split else []
        words += ["--only", entry.name, "--budget", budget]
        for item in overrides or []:
            words += ["--set", item]
        lines.append(f"{entry.name} {shlex.join(words)}")
    return lines


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", type=Path, help="the suite folder (scenes made there already)")
    parser.add_argument("--source", default="synth", help="synth or genesis")
    parser.add_argument("--split", default=None, help="dev or test (the genesis suite)")
    parser.add_argument("--budget", default="full", choices=["small", "full"])
    parser.add_argument("--only", default=None, help="comma-separated entry names")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    args = parser.parse_args(argv)
    only = [n.strip() for n in args.only.split(",") if n.strip()] if args.only else None
    try:
        lines = job_lines(
            args.out,
            source=args.source,
            split=args.split,
            budget=args.budget,
            only=only,
            overrides=args.set,
        )
    except ValueError as err:
        parser.error(str(err))
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
