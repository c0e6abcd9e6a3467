"""Time and peak memory of the ``gaussians`` lifter at about 100k particles, and the rest-state
PSNR of the bound Gaussians against frame 0 of the recording.

Usage: python benchmarks/lift_bench.py [--scene DIR] [--cell 0.004] [--particles-per-cell 8]
           [--gauss-options '{"iterations": 2000}']

1. A synth scene with two large shapes (bread, barrel) is generated into ``--scene`` in a child
   process (skipped when the folder already holds a scene), so this process's peak memory is
   the lift's, not the generator's.
2. The oracle's ground-truth points are lifted (Gaussians seeded from the points); with the
   default cell of 4 mm and 8 particles per cell that is ~100k particles.
3. If a ``gauss-dynamic`` reconstructor is registered, it is fitted and its reconstruction is
   lifted too, with the rest-state PSNR of its bound Gaussians (the >= 28 dB check).
Prints one JSON document: per run the lift time (s), particles, peak resident memory (GiB),
volume error and IoU per object against gt/points.npz, and the PSNR (full image, objects only).
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time
from pathlib import Path

import torch

SPACING = 0.006  # m, ground-truth particle lattice of the generated scene
SCENE = {
    "n_objects": 2,
    "shapes": "bread,barrel",
    "materials": "elastic,plasticine",
    "resolution": 128,
    "n_cameras": 6,
    "n_frames": 4,
    "observed_frames": 3,
    "particle_spacing": SPACING,
    "collision_frame": 3,
    "simulator": "warp-mpm",
    "simulator_options": {"grid": 32, "substeps": 40, "device": "cpu"},
    "seed": 2,
    "progress": False,
}


def _peak_rss_gb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20  # KiB on Linux


def generate(scene_dir: Path) -> None:
    from mosiv_framework.registry import get_registry

    get_registry().create("scene_source", "synth", SCENE).generate(scene_dir)


def lift_and_score(reconstruction, scene, options: dict) -> dict:
    from mosiv_lift.quality import score_lift

    from mosiv_framework.registry import get_registry

    registry = get_registry()
    lifter = registry.create("lifter", "gaussians", options)
    start = time.perf_counter()
    particles = lifter.lift(reconstruction, scene)
    seconds = time.perf_counter() - start
    peak = _peak_rss_gb()
    if torch.cuda.is_available():
        peak = max(peak, torch.cuda.max_memory_allocated() / 2**30)
    renderer = registry.create("renderer", "gauss-torch", {"tile_size": 8})
    score = score_lift(particles, scene, renderer, gt_spacing=SPACING, cell=options["cell_size"])
    return {
        "lift_time_s": seconds,
        "peak_rss_gb": peak,
        **score,
        "report": particles.appearance.report,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", type=Path, default=Path("runs/lift_bench/scene"))
    ap.add_argument("--cell", type=float, default=0.004, help="lift cell size (m)")
    ap.add_argument("--particles-per-cell", type=int, default=8)
    ap.add_argument("--gauss-options", default="{}", help="JSON options of gauss-dynamic")
    ap.add_argument(
        "--no-gauss", action="store_true", help="skip the gauss-dynamic fit (slow on CPU)"
    )
    ap.add_argument("--generate-only", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.generate_only:
        generate(args.scene)
        return
    if not (args.scene / "scene.json").is_file():
        subprocess.run(
            [sys.executable, __file__, "--generate-only", "--scene", str(args.scene)], check=True
        )

    from mosiv_framework.registry import get_registry
    from mosiv_framework.scene import read_scene

    registry = get_registry()
    scene = read_scene(args.scene)
    options = {"cell_size": args.cell, "particles_per_cell": args.particles_per_cell}
    baseline = _peak_rss_gb()
    oracle = registry.create("reconstructor", "oracle", {"max_points": 0}).fit(scene)
    result = {
        "scene": str(args.scene),
        "options": options,
        "threads": torch.get_num_threads(),
        "rss_before_lift_gb": baseline,
        "oracle": lift_and_score(oracle, scene, options),
    }
    if args.no_gauss:
        result["gauss_dynamic"] = "skipped (--no-gauss)"
    elif "gauss-dynamic" in registry.names("reconstructor"):
        start = time.perf_counter()
        recon = registry.create(
            "reconstructor", "gauss-dynamic", json.loads(args.gauss_options)
        ).fit(scene)
        result["gauss_dynamic_fit_s"] = time.perf_counter() - start
        result["gauss_dynamic"] = lift_and_score(recon, scene, options)
    else:
        result["gauss_dynamic"] = "not registered"
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
