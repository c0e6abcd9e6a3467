"""The table's Coulomb coefficient read off the observed landings of Genesis scenes.

No simulation: for every scene of a suite folder (``mosiv data suite OUT --source genesis``),
the observed frames of gt/points.npz (what the oracle reconstructor gives identification)
are read by ``mosiv_framework.pipeline.landing`` (``identify.ground_friction_start:
landing``): each landing clear of the other bodies, its tangential-to-normal impulse ratio,
and the estimate (the largest ratio). Genesis's table has the coefficient 0.1 (its rigid
plane's ``coup_friction``; docs/PHYSICS.md, Ground friction), or the one gt/params.json records.

    python benchmarks/genesis_landing_friction.py --scenes runs/genesis --out runs/landing

Writes ``OUT/landing_friction.json`` (one row per scene, with the machine and code version)
and ``OUT/landing_friction.md``; ``--write-results FILE`` replaces the section "Ground friction
from the landings on Genesis scenes" there, ``--data`` saying what the scenes are.
"""

from __future__ import annotations

import argparse
import datetime
import json
import statistics
import sys
from pathlib import Path

import torch
from genesis_identify import find_scenes, replace_section, shown_command
from genesis_model_error import GENESIS_GROUND_FRICTION
from identify_suite import code_version

from mosiv_framework.pipeline.landing import landing_friction
from mosiv_framework.scene import read_scene

FORMAT = "mosiv-genesis-landing-friction/1"
SECTION = "Ground friction from the landings on Genesis scenes"
#: the section goes before this one
SECTION_BEFORE = "Stiffness profile on Genesis scenes"


def measure(folder: Path, clearances: tuple[float, ...] = ()) -> dict:
    """One scene's landings over its observed frames, the estimate and the truth; with
    ``clearances`` (in point spacings) also the estimate at each of them."""
    scene = read_scene(folder)
    points = {int(k): torch.as_tensor(v) for k, v in scene.gt_points().items()}
    value, found = landing_friction(points, scene.world, scene.observed_frames)
    other = {
        f"{c:g}": landing_friction(points, scene.world, scene.observed_frames, clear_spacings=c)[0]
        for c in clearances
    }
    generator = scene.gt_params().get("generator_params") or {}
    truth = generator.get("ground_friction", GENESIS_GROUND_FRICTION)
    return {
        "suite": folder.parent.name,
        "scene": folder.name,
        "materials": [o.material for o in scene.objects],
        "observed_frames": scene.observed_frames,
        "estimate": value,
        "truth": truth,
        "landings": [{"object": x.object_id, "frame": x.frame, "ratio": x.ratio} for x in found],
        "by_clearance": other,
        "device": "CPU",
        "code": code_version(),
    }


def markdown(rows: list[dict]) -> str:
    """The per-scene table and, per suite folder, a summary line."""
    lines = [
        "| suite | scene | materials | landings read (object: frame, ratio) | estimate | truth |",
        "|---|---|---|---|---|---|",
    ]
    for r in rows:
        read = "; ".join(f"{x['object']}: {x['frame']}, {x['ratio']:.3f}" for x in r["landings"])
        estimate = "-" if r["estimate"] is None else f"{r['estimate']:.3f}"
        materials = ", ".join(r["materials"])
        lines.append(
            f"| {r.get('suite', '-')} | {r['scene']} | {materials} | {read or '-'} | {estimate} "
            f"| {r['truth']:g} |"
        )
    lines.append("")
    for suite in dict.fromkeys(r.get("suite", "-") for r in rows):
        lines.append(f"{suite}: {_summary([r for r in rows if r.get('suite', '-') == suite])}")
    lines += ["", "Estimate: the largest ratio, a lower bound of the coefficient (docs/PHYSICS.md,"]
    lines[-1] += " Ground friction); a scene without a readable landing starts at the default 0.3."
    clearances = list(dict.fromkeys(c for r in rows for c in r.get("by_clearance") or {}))
    if clearances:
        lines += ["", "| suite | clearance (point spacings) | scenes read | estimate / truth |"]
        lines.append("|---|---|---|---|")
        for suite in dict.fromkeys(r.get("suite", "-") for r in rows):
            mine = [r for r in rows if r.get("suite", "-") == suite]
            for c in clearances:
                at = [{**r, "estimate": (r.get("by_clearance") or {}).get(c)} for r in mine]
                lines.append(f"| {suite} | {c} | {_clearance_cell(at)} |")
    return "\n".join(lines) + "\n"


def _clearance_cell(rows: list[dict]) -> str:
    """'3 of 4 | median 0.67, range 0.53-0.94' for the rows' estimates against their truth."""
    ratios = _ratios(rows)
    return f"{len(ratios)} of {len(rows)} | {_spread(ratios) if ratios else '-'}"


def _summary(rows: list[dict]) -> str:
    ratios = _ratios(rows)
    if not ratios:
        return f"no landing read on any of the {len(rows)} scenes."
    return f"read on {len(ratios)} of {len(rows)} scenes, estimate / truth {_spread(ratios)}."


def _ratios(rows: list[dict]) -> list[float]:
    """estimate / truth of each row that read a landing."""
    return [r["estimate"] / r["truth"] for r in rows if r["estimate"] is not None and r["truth"]]


def _spread(ratios: list[float]) -> str:
    return f"median {statistics.median(ratios):.2f}, range {min(ratios):.2f}-{max(ratios):.2f}"


def section_text(rows: list[dict], *, command: str, data: str) -> str:
    codes = sorted({r["code"] for r in rows})
    head = [
        f"## {SECTION}",
        "",
        "What `identify.ground_friction_start: landing` reads off the observed frames of each",
        "scene's tracked points (gt/points.npz, as the oracle reconstructor gives them), with no",
        "simulation: the landings clear of the other bodies, each one's ratio of tangential to",
        "normal impulse, and the estimate, against Genesis's table coefficient.",
        "",
        f"- Command: `{command}`",
        f"- Machine: development CPU. Date {datetime.date.today().isoformat()}. "
        f"Code {', '.join(codes)}.",
        f"- Data: {data}.",
        "",
    ]
    return "\n".join(head) + "\n" + markdown(rows)


def parse_args(argv: list[str] | None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", type=Path, nargs="+", required=True, help="suite folders")
    ap.add_argument("--out", type=Path, required=True, help="folder for landing_friction.json")
    ap.add_argument("--only", help="comma-separated scene names")
    ap.add_argument(
        "--clearances", nargs="*", type=float, default=[],
        help="also read each scene with these clearances (point spacings; the option's is 1.5)",
    )  # fmt: skip
    ap.add_argument("--data", default="the scenes of --scenes", help="what the scenes are")
    ap.add_argument("--write-results", type=Path, default=None, help="markdown file to update")
    return ap.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    args = parse_args(argv)
    rows = [
        measure(suite / name, tuple(args.clearances))
        for suite in args.scenes
        for name in find_scenes(suite, args.only)
    ]
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "landing_friction.json").write_text(
        json.dumps({"format": FORMAT, "rows": rows}, indent=1)
    )
    (args.out / "landing_friction.md").write_text(markdown(rows))
    print(markdown(rows))
    if args.write_results is not None:
        command = shown_command("benchmarks/genesis_landing_friction.py", argv, drop=("--data",))
        body = section_text(rows, command=command, data=args.data)
        text = args.write_results.read_text()
        args.write_results.write_text(
            replace_section(text, body, title=SECTION, before=SECTION_BEFORE)
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
