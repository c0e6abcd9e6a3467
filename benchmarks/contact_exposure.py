"""How much of each suite scene's observed window a scene-wise Chamfer could get wrong.

The paper explains its supervision ablation (table 3) by contact: a Chamfer over the union of
the bodies may match a point of one body to the other where they touch, which per-object
Chamfers cannot. That can only happen to points lying within about a particle spacing or two of
the other body. For each material pair of ``identify_suite.PAIRS`` (the same scenes: same seeds,
the recipe's simulator settings, here on the CPU), this plans and simulates the scene on the CPU, without
rendering, and reports per observed frame the share of particles within ``--radius`` of the
other body, and the frames in which the bodies touch (closest particles within one spacing).

    python benchmarks/contact_exposure.py --pairs E-P,P-F --json runs/contact.json
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from identify_suite import LETTERS, select_pairs
from omegaconf import OmegaConf
from scipy.spatial import cKDTree

#: the from-video suite's recipe, whose scene source the scenes are made with
PAPER_RECIPE = Path(__file__).resolve().parents[1] / "recipes" / "video_paper.yaml"


def exposure(positions: np.ndarray, sizes: list[int], *, radius: float, touch: float) -> dict:
    """Per frame of ``positions`` [T, N, 3] (m; objects in order, ``sizes`` particles each, two
    objects): the share of all particles within ``radius`` (m) of the other object, and whether
    the objects touch (some pair of their particles closer than ``touch``)."""
    if len(sizes) != 2:
        raise ValueError(f"contact exposure is defined for two objects, got {len(sizes)}")
    split = np.cumsum(sizes)[:-1]
    near, touching = [], []
    for frame in positions:
        a, b = np.split(frame, split)
        d_ab, _ = cKDTree(b).query(a, k=1)
        d_ba, _ = cKDTree(a).query(b, k=1)
        near.append(float((np.sum(d_ab < radius) + np.sum(d_ba < radius)) / (len(a) + len(b))))
        touching.append(bool(min(d_ab.min(), d_ba.min()) < touch))
    return {"near_share": near, "touching": touching}


def scene_exposure(
    pair: str, seed: int, *, source: dict, observed: int, radius_cells: float
) -> dict:
    """The exposure of ``pair``'s scene drawn from ``seed`` with the recipe's scene ``source``
    settings (its simulator run on the CPU)."""
    from mosiv_synth.generate import plan_scene, simulate
    from mosiv_synth.options import SynthOptions

    a, b = (LETTERS[x] for x in pair.split("-"))
    options = SynthOptions(
        materials=f"{a},{b}",
        seed=seed,
        particle_spacing=source["particle_spacing"],
        simulator=source["simulator"],
        simulator_options={**source["simulator_options"], "device": "cpu"},
        progress=False,
    )
    plan = plan_scene(options)
    positions = simulate(plan, options)[:observed]
    spacing = options.particle_spacing
    result = exposure(
        positions,
        [len(p) for p in plan.particles],
        radius=radius_cells * spacing,
        touch=spacing,
    )
    near = result["near_share"]
    return {
        "pair": pair,
        "seed": seed,
        "observed_frames": len(near),
        "touching_frames": int(sum(result["touching"])),
        "mean_near_share": float(np.mean(near)),
        "max_near_share": float(np.max(near)),
        **result,
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", default=None, help="comma-separated (default: all ten)")
    parser.add_argument("--observed", type=int, default=15, help="observed frames (paper: 15)")
    parser.add_argument(
        "--radius-cells", type=float, default=2.0, help="'near' radius in particle spacings"
    )
    parser.add_argument("--recipe", type=Path, default=PAPER_RECIPE, help="scene source settings")
    parser.add_argument("--json", type=Path, default=None, help="also write the rows here")
    args = parser.parse_args(argv)
    source = OmegaConf.to_container(OmegaConf.load(args.recipe).scene.source, resolve=True)
    rows = []
    print("| pair | touching frames | mean share near the other body | largest share |")
    print("|---|---:|---:|---:|")
    for index, pair in select_pairs(pairs=args.pairs, scenes=None):
        row = scene_exposure(
            pair, index, source=source, observed=args.observed, radius_cells=args.radius_cells
        )
        rows.append(row)
        print(
            f"| {pair} | {row['touching_frames']} of {row['observed_frames']} | "
            f"{100 * row['mean_near_share']:.1f} % | {100 * row['max_near_share']:.1f} % |",
            flush=True,
        )
        if args.json is not None:
            args.json.parent.mkdir(parents=True, exist_ok=True)
            args.json.write_text(json.dumps({"radius_cells": args.radius_cells, "rows": rows}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
