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

``--noise centroid:2 points:5 --seeds 3`` reads each scene again with reconstruction noise
added to its points, as a reconstruction from video would carry it (``perturbed``): ``points``
moves every point by its own Gaussian offset of that many mm per coordinate and frame,
``centroid`` moves all of a body's points together by one such offset per frame. The
centroid's velocities are frame differences, so a body's common jitter enters the impulses
whole; independent offsets of its points mostly cancel in the centroid, but they move the
lowest point (which dates the landing), the point spacing and the clearance to the other
bodies. Each scene and seed draws its own noise (seeded by the suite folder's and the scene's
names and the seed), the same pattern at every level of a kind, so levels differ in size only.
"""

from __future__ import annotations

import argparse
import datetime
import json
import math
import statistics
import sys
import zlib
from pathlib import Path

import torch
from genesis_identify import find_scenes, replace_section, shown_command
from genesis_model_error import GENESIS_GROUND_FRICTION
from identify_suite import code_version

from mosiv_framework.pipeline.landing import landing_friction
from mosiv_framework.registry import get_registry
from mosiv_framework.scene import read_scene

FORMAT = "mosiv-genesis-landing-friction/1"
SECTION = "Ground friction from the landings on Genesis scenes"
#: the section goes before this one
SECTION_BEFORE = "Stiffness profile on Genesis scenes"


#: the kinds of reconstruction noise ``perturbed`` adds
NOISE_KINDS = ("points", "centroid")


def perturbed(
    points: dict[int, torch.Tensor], kind: str, sigma_mm: float, seed: int
) -> dict[int, torch.Tensor]:
    """A copy of ``points`` (object id -> [F, N, 3] m) with Gaussian noise of ``sigma_mm`` mm
    per coordinate, drawn by the oracle reconstructor (the noise of the sensitivity studies,
    every point kept): ``points``, an offset of its own for every point and frame
    (``noise_iid``); ``centroid``, one offset per body and frame shared by all of its points
    (``noise_shared``)."""
    if kind not in NOISE_KINDS:
        raise ValueError(f"noise kind {kind!r}: use one of {', '.join(NOISE_KINDS)}")
    option = "noise_iid" if kind == "points" else "noise_shared"
    options = {option: sigma_mm * 1e-3, "max_points": 0, "seed": seed}
    oracle = get_registry().create("reconstructor", "oracle", options)
    return oracle.fit(_TrackedPoints(points)).points


class _TrackedPoints:
    """Points standing in for a scene where the oracle reads them (its ``gt_points``)."""

    def __init__(self, points: dict[int, torch.Tensor]):
        self.points = points

    def gt_points(self) -> dict[int, torch.Tensor]:
        return self.points


def parse_noise(text: str) -> tuple[str, float]:
    """'centroid:2' -> ('centroid', 2.0), with an error naming what is valid."""
    kind, _, mm = text.partition(":")
    try:
        sigma = float(mm)
    except ValueError:
        sigma = -1.0
    if kind not in NOISE_KINDS or not math.isfinite(sigma) or sigma < 0:
        raise argparse.ArgumentTypeError(
            f"--noise {text!r}: write KIND:MM with KIND one of {', '.join(NOISE_KINDS)} and MM a "
            "standard deviation in mm >= 0, e.g. centroid:2"
        )
    return kind, sigma


def positive_count(text: str) -> int:
    """``--seeds``: a whole number of at least 1."""
    try:
        count = int(text)
    except ValueError:
        count = 0
    if count < 1:
        raise argparse.ArgumentTypeError(f"--seeds {text!r}: give a whole number >= 1")
    return count


def scene_seed(folder: Path, seed: int) -> int:
    """The noise seed of one scene's ``seed``-th noisy copy: its own for every scene of every
    suite folder, the same on every run."""
    return (zlib.crc32(f"{folder.parent.name}/{folder.name}".encode()) << 16) + seed


def measure(
    folder: Path,
    clearances: tuple[float, ...] = (),
    noise: tuple[tuple[str, float], ...] = (),
    seeds: int = 3,
) -> dict:
    """One scene's landings over its observed frames, the estimate and the truth; with
    ``clearances`` (in point spacings) also the estimate at each of them, and with ``noise``
    ((kind, mm) pairs) the estimate from ``seeds`` noisy copies of the points at each."""
    scene = read_scene(folder)
    points = {int(k): torch.as_tensor(v) for k, v in scene.gt_points().items()}
    frames = scene.observed_frames
    value, found = landing_friction(points, scene.world, frames)
    other = {
        f"{c:g}": landing_friction(points, scene.world, frames, clear_spacings=c)[0]
        for c in clearances
    }
    noisy = [
        {"kind": kind, "mm": mm, "seed": seed, "estimate": landing_friction(
            perturbed(points, kind, mm, scene_seed(folder, seed)), scene.world, frames)[0]}
        for kind, mm in noise
        for seed in range(seeds)
    ]  # fmt: skip
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
        "noisy": noisy,
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
                lines.append(f"| {suite} | {c} | {_ratio_cell(at)} |")
    return "\n".join(lines + _noise_lines(rows)) + "\n"


def _noise_lines(rows: list[dict]) -> list[str]:
    """Per suite and noise level: how many (scene, seed) readings found a landing, and their
    estimate / truth; the first line is the clean reading of the same scenes."""
    levels = list(dict.fromkeys((n["kind"], n["mm"]) for r in rows for n in r.get("noisy") or []))
    if not levels:
        return []
    lines = [
        "",
        "| suite | noise (mm, per coordinate) | readings with a landing | estimate / truth |",
    ]
    lines.append("|---|---|---|---|")
    for suite in dict.fromkeys(r.get("suite", "-") for r in rows):
        mine = [r for r in rows if r.get("suite", "-") == suite]
        lines.append(f"| {suite} | none (one reading a scene) | {_ratio_cell(mine)} |")
        for kind, mm in levels:
            at = [
                {"estimate": n["estimate"], "truth": r["truth"]}
                for r in mine
                for n in r.get("noisy") or []
                if (n["kind"], n["mm"]) == (kind, mm)
            ]
            lines.append(f"| {suite} | {kind} {mm:g} | {_ratio_cell(at)} |")
    seeds = max(len({n["seed"] for n in r.get("noisy") or []}) for r in rows)
    lines += [
        "",
        f"Noise: Gaussian, per coordinate, {seeds} noisy copies of each scene's points per level;"
        " points: an offset of its own for every point and frame; centroid: one offset per body"
        " and frame, shared by its points. A reading without a landing starts at the default 0.3.",
    ]
    return lines


def _ratio_cell(rows: list[dict]) -> str:
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
    ap.add_argument(
        "--noise", nargs="*", type=parse_noise, default=[], metavar="KIND:MM",
        help="also read each scene with this noise on its points (points:MM or centroid:MM)",
    )  # fmt: skip
    ap.add_argument(
        "--seeds", type=positive_count, default=3, help="noisy copies per --noise level"
    )
    ap.add_argument("--data", default="the scenes of --scenes", help="what the scenes are")
    ap.add_argument("--write-results", type=Path, default=None, help="markdown file to update")
    return ap.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    args = parse_args(argv)
    rows = [
        measure(suite / name, tuple(args.clearances), tuple(dict.fromkeys(args.noise)), args.seeds)
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
