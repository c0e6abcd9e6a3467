"""Contact mode (or another setting) on Genesis scenes: the same identification, two settings.

Genesis solves every body on one grid, so bodies that touch stick. warp-mpm's default contact
(``multi_field``) gives each object its own field with Coulomb friction between them; its
``single_field`` mode is classic sticky MPM, Genesis's own kind of contact. This script reads the
per-scene rows of two ``benchmarks/genesis_identify.py`` runs that differ only in
``simulator.contact`` and tabulates, scene by scene and object by object, the gauge-free errors
of the stiffness and of each family's own parameter, and the observed and future Chamfer.

    python benchmarks/genesis_identify.py --scenes runs/genesis --out runs/gid-multi ...
    python benchmarks/genesis_identify.py --scenes runs/genesis --out runs/gid-single \\
        --set simulator.contact=single_field ...
    python benchmarks/genesis_contact_compare.py runs/gid-multi runs/gid-single \\
        --write-results docs/RESULTS.md

A run folder holds its rows as ``parts/SCENE.json`` or (as kept under benchmarks/data)
``scene_SCENE.json``; only scenes present in both are compared. ``--section`` and
``--difference`` compare runs that differ in another setting, e.g. the stress law:

    python benchmarks/genesis_contact_compare.py benchmarks/data/genesis_identify runs/gid-laws \
        --labels "own laws,laws chosen" --difference "identify.law_choice (fixed, auto)" \
        --section "Choosing the stress on Genesis scenes" --write-results docs/RESULTS.md
"""

from __future__ import annotations

import argparse
import json
import shlex
import statistics
import sys
from pathlib import Path

from genesis_identify import KEEP_MARKER, _fill, replace_section  # noqa: F401
from genesis_identify_table import run_dates

SECTION = "Contact mode on Genesis scenes"
#: besides E, the parameter that tells each family apart (None: E only)
FAMILY_PARAM = {
    "elastic": None,
    "plasticine": "yield_stress",
    "elastic_corotated": None,
    "plasticine_corotated": "yield_stress",
    "sand": "friction_angle",
    "newtonian": "bulk_modulus",
}


def read_rows(folder: Path) -> dict[str, dict]:
    """Rows by scene name from ``parts/SCENE.json`` or ``scene_SCENE.json`` files."""
    rows = {}
    for path in sorted(folder.glob("parts/*.json")) + sorted(folder.glob("scene_*.json")):
        row = json.loads(path.read_text())
        if not isinstance(row, dict) or "objects" not in row or "scene" not in row:
            raise SystemExit(f"{path}: not a genesis_identify scene row (no 'scene'/'objects')")
        rows[row["scene"]] = row
    if not rows:
        raise SystemExit(f"{folder}: no parts/SCENE.json or scene_SCENE.json rows")
    return rows


def _error(obj: dict, name: str | None) -> float | None:
    entry = obj["params"].get(name) if name else None
    return entry.get("error") if isinstance(entry, dict) else None


def compare(first: dict[str, dict], second: dict[str, dict]) -> list[dict]:
    """One record per (scene, object) of the scenes in both runs."""
    records = []
    for scene in sorted(set(first) & set(second)):
        a, b = first[scene], second[scene]
        for key, obj in a["objects"].items():
            other = b["objects"][key]
            family = obj["family"]
            param = FAMILY_PARAM.get(family)
            records.append(
                {
                    "scene": scene,
                    "object": f"{key} {family}",
                    "E": (_error(obj, "E"), _error(other, "E")),
                    "param": param,
                    "family_param": (_error(obj, param), _error(other, param)),
                    "observed_cd": (a["observed_cd_mm2"], b["observed_cd_mm2"]),
                    "future_cd": (a["future_cd_mm2"], b["future_cd_mm2"]),
                }
            )
    return records


def _pair(values: tuple, unit: str = "") -> str:
    if values[0] is None or values[1] is None:
        return "-"
    return f"{values[0]:.3g} / {values[1]:.3g}{unit}"


def _median(records: list[dict], key: str, side: int, *, per_scene: bool = False) -> float:
    seen, values = set(), []
    for r in records:
        if per_scene and r["scene"] in seen:
            continue
        seen.add(r["scene"])
        if r[key][side] is not None:
            values.append(r[key][side])
    return statistics.median(values) if values else float("nan")


def markdown(records: list[dict], labels: tuple[str, str]) -> str:
    head = f"({labels[0]} / {labels[1]})"
    lines = [
        f"| scene | object | E % {head} | family parameter {head} | observed CD mm^2 | "
        "future CD mm^2 |",
        "|---|---|---|---|---|---|",
    ]
    for r in records:
        unit = " deg" if r["param"] == "friction_angle" else " %"
        family = f"{r['param']}: {_pair(r['family_param'], unit)}" if r["param"] else "-"
        lines.append(
            f"| {r['scene']} | {r['object']} | {_pair(r['E'])} | {family} | "
            f"{_pair(r['observed_cd'])} | {_pair(r['future_cd'])} |"
        )
    lines += [
        "",
        f"| median over the compared scenes | {labels[0]} | {labels[1]} |",
        "|---|---|---|",
    ]
    for title, key, per_scene in (
        ("E error % (objects)", "E", False),
        ("observed CD mm^2 (scenes)", "observed_cd", True),
        ("future CD mm^2 (scenes)", "future_cd", True),
    ):
        a, b = (_median(records, key, s, per_scene=per_scene) for s in (0, 1))
        lines.append(f"| {title} | {a:.3g} | {b:.3g} |")
    return "\n".join(lines)


def tallies(records: list[dict], labels: tuple[str, str]) -> str:
    """How often the second mode beat the first, per quantity (lower is better)."""

    def wins(key: str, per_scene: bool) -> tuple[int, int]:
        seen, better, total = set(), 0, 0
        for r in records:
            if (per_scene and r["scene"] in seen) or None in r[key]:
                continue
            seen.add(r["scene"])
            better, total = better + (r[key][1] < r[key][0]), total + 1
        return better, total

    parts = []
    for what, key, per_scene in (
        ("observed CD", "observed_cd", True),
        ("future CD", "future_cd", True),
        ("E error", "E", False),
        ("family-parameter error", "family_param", False),
    ):
        better, total = wins(key, per_scene)
        unit = "scenes" if per_scene else "objects"
        parts.append(f"{what} on {better} of {total} {unit}")
    return f"{labels[1]} is lower than {labels[0]} in " + "; ".join(parts) + "."


def section_text(
    records,
    labels,
    *,
    command: str,
    runs: tuple[dict, dict],
    section: str = SECTION,
    difference: str = "the contact between objects",
    data: str = "the Genesis scenes of the section above (wide ranges)",
) -> str:
    scenes = sorted({r["scene"] for r in records})
    alone = sorted((set(runs[0]) | set(runs[1])) - set(scenes))
    every = [row for run in runs for row in run.values()]
    machines = sorted({row.get("device", "?") for row in every})
    codes = sorted({str(row.get("code", "?")).split("+")[0] for row in every})
    intro = (
        'Two runs of the identification of "Identification on Genesis scenes" '
        f"(`benchmarks/genesis_identify.py`) that differ only in {difference} "
        f"(same recipe, settings and scenes otherwise): {labels[0]} and {labels[1]}. Compared "
        f"scenes: {', '.join(scenes)} (those run both ways). Errors are gauge-free, as above."
    )
    return "\n".join(
        [
            f"## {section}",
            "",
            _fill(intro),
            "",
            f"- Command: `{command}`",
            f"- Machine: {', '.join(machines)}. Date {run_dates(every)}. Code {', '.join(codes)}.",
            f"- Data: {data}."
            + (f" Run one way only, not compared: {', '.join(alone)}." if alone else ""),
            "",
            markdown(records, labels),
            "",
            _fill(tallies(records, labels)),
        ]
    )


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("first", type=Path, help="rows of the first contact mode")
    parser.add_argument("second", type=Path, help="rows of the second contact mode")
    parser.add_argument("--labels", default="multi_field,single_field")
    parser.add_argument("--write-results", type=Path, default=None)
    parser.add_argument("--section", default=SECTION, help="the RESULTS section's title")
    parser.add_argument(
        "--difference",
        default="the contact between objects",
        help="what the two runs differ in, as the section's first sentence names it",
    )
    parser.add_argument(
        "--data",
        default="the Genesis scenes of the section above (wide ranges)",
        help="which scenes the rows come from, as the section's Data line names them",
    )
    args = parser.parse_args(argv)
    labels = tuple(args.labels.split(","))
    if len(labels) != 2:
        raise SystemExit(f"--labels {args.labels!r}: give two names separated by a comma")
    runs = read_rows(args.first), read_rows(args.second)
    records = compare(*runs)
    if not records:
        raise SystemExit("the two runs share no scene")
    print(markdown(records, labels))
    if args.write_results is not None:
        command = "python benchmarks/genesis_contact_compare.py " + shlex.join(argv)
        text = args.write_results.read_text()
        body = section_text(
            records,
            labels,
            command=command,
            runs=runs,
            section=args.section,
            difference=args.difference,
            data=args.data,
        )
        args.write_results.write_text(replace_section(text, body, title=args.section))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
