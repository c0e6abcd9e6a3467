"""Re-decide saved diagnoses under another acceptance rule, from their diagnosis.json alone.

``mosiv diagnose-suite OUT --replay`` needs the suite's scene folders (it reads each scene's
gt/effects.json for the coefficient error); the evidence kept in the repository
(benchmarks/data/dsuite_s13, session 13's device runs) has only each entry's diagnosis.json, so
this prints the suite table without coefficient errors:

    python benchmarks/replay_evidence.py benchmarks/data/dsuite_s13 --bic-margin 2 --min-drop 0
    python benchmarks/replay_evidence.py benchmarks/data/dsuite_s13      # the current rule
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from mosiv_framework.diagnose.decide import DecideOptions
from mosiv_framework.diagnose.replay import replay_diagnosis
from mosiv_framework.diagnose.suite import score_entry, suite_entries, summarise, table


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("folder", help="a folder of ENTRY/diagnosis.json")
    parser.add_argument("--z", type=float)
    parser.add_argument("--min-drop", type=float)
    parser.add_argument("--bic-margin", type=float)
    parser.add_argument("--bootstrap", type=int, default=1000)
    args = parser.parse_args(argv)
    given = {"z": args.z, "min_drop": args.min_drop, "bic_margin": args.bic_margin}
    options = DecideOptions(
        bootstrap=args.bootstrap, **{k: v for k, v in given.items() if v is not None}
    )
    scores = []
    for entry in suite_entries(small=False):
        path = Path(args.folder) / entry.name / "diagnosis.json"
        if path.exists():
            diagnosis = replay_diagnosis(json.loads(path.read_text()), options)
            scores.append(score_entry(entry, diagnosis, effects=[]))
    print(f"replayed under {options}")
    print(table(summarise(scores)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
