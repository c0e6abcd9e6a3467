"""The lifting acceptance checks on TRAINED ``gauss-dynamic`` Gaussians, for the paper's 10 shapes.

Usage:
    python benchmarks/lift_shapes.py --device cuda --out runs/lift_shapes
    python benchmarks/lift_shapes.py --device cpu --tiny --out runs/lift_shapes_tiny
    python benchmarks/lift_shapes.py --device cuda --seed-offsets 0,100,200   # three draws each
    python benchmarks/lift_shapes.py --device cuda --also-cells 0.003   # each fit lifted twice

Five generated two-object scenes (fixed seeds) cover the ten shapes of the paper. Per scene:
1. the scene is generated (a short clip: the lift uses frame 0 only), all scenes in one child
   process on ``--device`` so this process's peak memory is the fit's and the lift's; a folder
   under ``--scenes-dir`` that already holds a scene is reused;
2. ``gauss-dynamic`` is fitted to it (``--gauss-options`` overrides the preset's options);
3. its reconstruction is lifted by the ``gaussians`` lifter;
4. the lift is scored (``mosiv_lift.quality.score_lift``): per object the volume error and the
   voxel IoU against the ground-truth frame-0 particles on their lattice (``scoring_cell``: the
   lattice, or a multiple for a coarser lift), the smallest distance between particles of
   different objects in lift cells, and the rest-state PSNR of the
   bound trained Gaussians against the recorded frame 0 (full image, and objects only: pixels
   inside the recorded or rendered silhouettes).
Writes ``lift_shapes.json`` and ``lift_shapes.md`` (one table row per shape, pass/fail against
the acceptance thresholds) into ``--out``; progress goes to stdout.

Presets: ``full`` (default; 128 px, 11 cameras, 6 mm lattice, lifted on a 3 mm cell and scored
on the 6 mm lattice, 26 virtual views of 96 px, sized for ~1 min per scene on one H200) and
``--tiny`` (64 px, 6 cameras, 8 mm, a short fit: a CPU check of the pipeline in minutes, not of
the thresholds).
"""

from __future__ import annotations

import argparse
import json
import platform
import resource
import subprocess
import sys
import time
from pathlib import Path

import torch

#: five scenes of two objects covering the paper's ten shapes, with their fixed seeds
SCENES = [
    ("egg", "pawn", 11),
    ("apple", "bread", 12),
    ("cream", "barrel", 13),
    ("potato", "cushion", 14),
    ("banana", "mushroom", 15),
]
#: material families cycle over the scenes (they play no part at frame 0)
MATERIALS = [
    "elastic,plasticine",
    "plasticine,sand",
    "sand,elastic",
    "elastic,sand",
    "plasticine,elastic",
]

#: the lifting acceptance thresholds
TARGETS = {"volume_error": 0.10, "iou": 0.8, "min_gap_cells": 0.5, "psnr_db": 28.0}

PRESETS = {
    "full": {
        "scene": {"resolution": 128, "n_cameras": 11, "particle_spacing": 0.006},
        "fit": {
            "hull_resolution": 128,
            "max_init_gaussians": 8000,
            "iterations": 1500,
            "views_per_step": 4,
            "motion_init_iterations": 100,
            "densify_from": 200,
            "densify_every": 100,
            "densify_until": 1100,
            "densify_grad": 5e-5,
            "tile_size": 16,
        },
        # lifted at half the lattice: on one 6 mm grid a perfect lift of a body 4-5 cells thick
        # scores as low as 0.75 from the two grids' phases (docs/BENCHMARKS.md "Lifting")
        "lift": {"cell_size": 0.003, "virtual_views": 26, "virtual_resolution": 96},
    },
    "tiny": {
        "scene": {"resolution": 64, "n_cameras": 6, "particle_spacing": 0.008},
        "fit": {
            "hull_resolution": 96,
            "max_init_gaussians": 2000,
            "iterations": 300,
            "views_per_step": 2,
            "motion_init_iterations": 50,
            "densify_from": 100,
            "densify_every": 50,
            "densify_until": 250,
            "densify_grad": 5e-5,
            "tile_size": 8,
        },
        # short fits leave semi-transparent Gaussians without gaps: 9 of 10 views must agree
        "lift": {
            "cell_size": 0.008,
            "virtual_views": 10,
            "virtual_resolution": 48,
            "virtual_agreement": 0.9,
        },
    },
}
#: frames of every clip: frame 0 is lifted; the objects touch at the last frame
N_FRAMES = 3


def scene_options(index: int, preset: str, device: str, seed_offset: int = 0) -> dict:
    a, b, seed = SCENES[index]
    return {
        "n_objects": 2,
        "shapes": f"{a},{b}",
        "materials": MATERIALS[index],
        "n_frames": N_FRAMES,
        "observed_frames": N_FRAMES,
        "collision_frame": N_FRAMES - 1,
        "simulator": "warp-mpm",
        "simulator_options": {"grid": 32, "substeps": 40, "device": device},
        "seed": seed + seed_offset,
        "progress": False,
        **PRESETS[preset]["scene"],
    }


def scene_folder(scenes_dir: Path, index: int, preset: str, seed_offset: int = 0) -> Path:
    a, b, seed = SCENES[index]
    return scenes_dir / f"{preset}_{a}_{b}_s{seed + seed_offset}"


def generate_all(scenes_dir: Path, preset: str, device: str, jobs: list[tuple[int, int]]) -> None:
    """Generate the missing scenes, one per (scene index, seed offset) (a child of ``main``)."""
    from mosiv_framework.registry import get_registry

    for i, offset in jobs:
        folder = scene_folder(scenes_dir, i, preset, offset)
        if (folder / "scene.json").is_file():
            continue
        start = time.perf_counter()
        options = scene_options(i, preset, device, offset)
        get_registry().create("scene_source", "synth", options).generate(folder)
        print(f"generated {folder.name} in {time.perf_counter() - start:.1f} s", flush=True)


def peak_rss_gb() -> float:
    """Peak resident memory of this process so far (GiB; ru_maxrss is KiB on Linux)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20


def fit_gauss(scene, options: dict, device: str):
    """(reconstruction, seconds, peak GPU memory GiB or None) of one gauss-dynamic fit."""
    from mosiv_framework.registry import get_registry

    cuda = device.startswith("cuda")
    if cuda:
        torch.cuda.reset_peak_memory_stats()
    start = time.perf_counter()
    recon = get_registry().create("reconstructor", "gauss-dynamic", options).fit(scene)
    if cuda:
        torch.cuda.synchronize()
    seconds = time.perf_counter() - start
    return recon, seconds, torch.cuda.max_memory_allocated() / 2**30 if cuda else None


def lift_scene(recon, scene, lift_options: dict, *, gt_spacing: float) -> dict:
    """Lift ``recon`` with the ``gaussians`` lifter and score it; times and memory included."""
    from mosiv_lift.quality import score_lift

    from mosiv_framework.registry import get_registry

    registry = get_registry()
    start = time.perf_counter()
    particles = registry.create("lifter", "gaussians", lift_options).lift(recon, scene)
    seconds = time.perf_counter() - start
    renderer = registry.create("renderer", "gauss-torch", {"tile_size": 8})
    score = score_lift(
        particles, scene, renderer, gt_spacing=gt_spacing, cell=lift_options["cell_size"]
    )
    return {
        "lift_s": seconds,
        "peak_rss_gb": peak_rss_gb(),
        **score,
        "report": particles.appearance.report,
    }


def verdicts(score: dict, k: str) -> dict[str, bool]:
    """Pass/fail of each acceptance check for object ``k`` of a scored lift."""
    obj = score["objects"][k]
    return {
        "volume": abs(obj["volume_error"]) <= TARGETS["volume_error"],
        "iou": obj["iou"] >= TARGETS["iou"],
        "gap": score["min_gap_cells"] >= TARGETS["min_gap_cells"],
        "psnr": score["psnr"]["full"] >= TARGETS["psnr_db"],
    }


def markdown(results: list[dict], header: str) -> str:
    lines = [
        header,
        "",
        "| shape | seed | volume error | IoU | min gap / cell | PSNR full (dB) | PSNR objects (dB) "
        "| fit (s) | lift (s) | peak GPU (GiB) | peak RSS (GiB) | pass |",
        "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | --- |",
    ]
    passes: dict[str, list[bool]] = {}
    for r in results:
        s = r["lift"]
        for k, obj in s["objects"].items():
            v = verdicts(s, k)
            failed = [name for name, ok in v.items() if not ok]
            gpu = "-" if r["fit_peak_gpu_gb"] is None else f"{r['fit_peak_gpu_gb']:.2f}"
            shape = r["shapes"][int(k) - 1]
            passes.setdefault(shape, []).append(not failed)
            lines.append(
                f"| {shape} | {r.get('seed', '-')} | {100 * obj['volume_error']:+.1f}% "
                f"| {obj['iou']:.3f} | {s['min_gap_cells']:.2f} | {s['psnr']['full']:.1f} "
                f"| {s['psnr']['objects']:.1f} | {r['fit_s']:.0f} | {s['lift_s']:.1f} | {gpu} "
                f"| {s['peak_rss_gb']:.2f} | {'pass' if not failed else 'FAIL: ' + ', '.join(failed)} |"
            )
    if any(len(v) > 1 for v in passes.values()):
        lines += ["", "| shape | draws passing every check |", "| --- | ---: |"]
        lines += [f"| {shape} | {sum(v)} of {len(v)} |" for shape, v in passes.items()]
    t = TARGETS
    lines += [
        "",
        f"Thresholds: |volume error| <= {100 * t['volume_error']:.0f}%, IoU >= {t['iou']}, "
        f"min gap >= {t['min_gap_cells']} cell, full-image PSNR >= {t['psnr_db']} dB. "
        "Gap and PSNR are per scene (both shapes of a scene show the same value); fit and lift "
        "times per scene; peak RSS is the process's peak so far.",
    ]
    return "\n".join(lines) + "\n"


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    p.add_argument("--out", type=Path, default=Path("runs/lift_shapes"))
    p.add_argument("--scenes-dir", type=Path, help="scene folders (default: OUT/scenes)")
    p.add_argument("--tiny", action="store_true", help="small CPU preset (pipeline check)")
    p.add_argument("--gauss-options", default="{}", help="JSON overriding gauss-dynamic options")
    p.add_argument("--lift-options", default="{}", help="JSON overriding gaussians lifter options")
    p.add_argument(
        "--scenes", default="0,1,2,3,4", help="comma-separated scene indices 0..4 (default: all)"
    )
    p.add_argument(
        "--seed-offsets",
        default="0",
        help="comma-separated offsets added to each scene's seed (default 0): every offset is "
        "a fresh random draw of the scene (sizes, rotations, cameras), so '0,100,200' measures "
        "each shape in three orientations",
    )
    p.add_argument(
        "--also-cells",
        default="",
        help="comma-separated extra cell sizes (m), e.g. 0.003: each fit is also lifted and "
        "scored at these, written to lift_shapes_cell<mm>mm.md and under 'also_cells' in the "
        "JSON (one fit, several lifts)",
    )
    p.add_argument(
        "--save-reconstructions",
        action="store_true",
        help="save each fitted reconstruction under OUT/<scene name>/ (gauss-dynamic format)",
    )
    p.add_argument(
        "--generate-device",
        help="device of the scene generator's simulator (default: --device); scenes made on "
        "one machine can be fitted on another through --scenes-dir",
    )
    p.add_argument(
        "--generate-only", action="store_true", help="generate the missing scenes and stop"
    )
    return p.parse_args(argv)


def main(argv=None) -> dict:
    args = parse_args(argv)
    preset = "tiny" if args.tiny else "full"
    scenes_dir = args.scenes_dir or args.out / "scenes"
    indices = [int(i) for i in args.scenes.split(",")]
    if any(not 0 <= i < len(SCENES) for i in indices):
        raise SystemExit(f"--scenes={args.scenes!r}: indices must lie in 0..{len(SCENES) - 1}")
    offsets = [int(o) for o in args.seed_offsets.split(",")]
    jobs = [(i, offset) for offset in offsets for i in indices]
    generate_device = args.generate_device or args.device
    if args.generate_only:
        generate_all(scenes_dir, preset, generate_device, jobs)
        return {}
    generate_missing(args, scenes_dir, preset, generate_device, jobs)

    fit_options = {
        **PRESETS[preset]["fit"],
        "device": args.device,
        "progress": False,
        "save_dir": "",
        **json.loads(args.gauss_options),
    }
    lift_options = {**PRESETS[preset]["lift"], **json.loads(args.lift_options)}
    extra_cells = [float(c) for c in args.also_cells.split(",") if c.strip()]
    results = []
    for n, (i, offset) in enumerate(jobs):
        print(f"[{n + 1}/{len(jobs)}] ", end="", flush=True)
        folder = scene_folder(scenes_dir, i, preset, offset)
        results.append(
            measure_scene(args, folder, i, offset, preset, fit_options, lift_options, extra_cells)
        )
    summary = {
        "preset": preset,
        "device": args.device,
        "targets": TARGETS,
        "fit_options": fit_options,
        "lift_options": lift_options,
        "scene_options": PRESETS[preset]["scene"],
        "n_frames": N_FRAMES,
        "scenes": results,
    }
    write_summary(args, summary, extra_cells)
    return summary


def generate_missing(args, scenes_dir: Path, preset: str, generate_device: str, jobs) -> None:
    """Generate the scenes of ``jobs`` not yet in ``scenes_dir``: one child per missing seed
    offset keeps the generator's memory out of this process."""
    missing = [
        (i, o)
        for i, o in jobs
        if not (scene_folder(scenes_dir, i, preset, o) / "scene.json").is_file()
    ]
    for offset in sorted({o for _, o in missing}):
        child = [sys.executable, __file__, "--generate-only", "--device", generate_device]
        child += ["--scenes-dir", str(scenes_dir), "--out", str(args.out)]
        child += ["--scenes", ",".join(str(i) for i, o in missing if o == offset)]
        child += ["--seed-offsets", str(offset)]
        subprocess.run(child + (["--tiny"] if args.tiny else []), check=True)


def measure_scene(args, folder, i, offset, preset, fit_options, lift_options, extra_cells) -> dict:
    """Fit gauss-dynamic to one scene, lift it (also at each of ``extra_cells``), score it;
    returns the scene's result record."""
    from mosiv_framework.scene import read_scene

    scene = read_scene(folder)
    shapes = list(SCENES[i][:2])
    seed = SCENES[i][2] + offset
    spacing = PRESETS[preset]["scene"]["particle_spacing"]
    print(f"{'+'.join(shapes)} seed {seed}: fitting gauss-dynamic", flush=True)
    recon, fit_s, fit_gpu = fit_gauss(scene, fit_options, args.device)
    training = recon.extras["training"]
    if args.save_reconstructions:
        from mosiv_gauss.reconstructor import save_reconstruction

        save_reconstruction(recon, args.out / folder.name)
    print(
        f"  fit {fit_s:.0f} s, {recon.extras['n_gaussians']} Gaussians, training PSNR "
        f"{training['psnr_mean']:.1f} dB; lifting",
        flush=True,
    )
    score = lift_scene(recon, scene, lift_options, gt_spacing=spacing)
    also = {
        str(cell): lift_scene(recon, scene, {**lift_options, "cell_size": cell}, gt_spacing=spacing)
        for cell in extra_cells
    }
    print_lift(score, also)
    return {
        "scene": str(folder),
        "shapes": shapes,
        "seed": seed,
        "fit_s": fit_s,
        "fit_peak_gpu_gb": fit_gpu,
        "n_gaussians": recon.extras["n_gaussians"],
        "training_psnr_db": training["psnr_mean"],
        "lift": score,
        "also_cells": also,
    }


def _objects_line(score: dict) -> str:
    return ", ".join(
        f"{o['name']}: vol {100 * o['volume_error']:+.1f}% IoU {o['iou']:.3f}"
        for o in score["objects"].values()
    )


def print_lift(score: dict, also: dict) -> None:
    """One line of the lift's scores, and one per extra cell size."""
    print(
        f"  lift {score['lift_s']:.1f} s, {score['particles']} particles; {_objects_line(score)}; "
        f"gap {score['min_gap_cells']:.2f} cells; PSNR {score['psnr']['full']:.1f} dB "
        f"(objects {score['psnr']['objects']:.1f} dB)",
        flush=True,
    )
    for cell, extra in also.items():
        print(
            f"  lift at {cell} m: {extra['particles']} particles; {_objects_line(extra)}",
            flush=True,
        )


def write_summary(args, summary: dict, extra_cells: list[float]) -> None:
    """lift_shapes.json and the markdown tables (one per lift cell size) into ``args.out``."""
    results, lift_options = summary["scenes"], summary["lift_options"]
    header = (
        f"lift_shapes ({summary['preset']} preset, device {args.device}"
        + (f", {torch.cuda.get_device_name()}" if args.device.startswith("cuda") else "")
        + f", host {platform.node()}, {torch.get_num_threads()} CPU threads)"
    )
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "lift_shapes.json").write_text(
        json.dumps(summary, indent=2, default=str) + "\n", encoding="utf-8"
    )
    table = markdown(results, header + f", cell {1000 * lift_options['cell_size']:g} mm")
    (args.out / "lift_shapes.md").write_text(table, encoding="utf-8")
    print(table)
    for cell in extra_cells:
        relifted = [{**r, "lift": r["also_cells"][str(cell)]} for r in results]
        table = markdown(relifted, header + f", the same fits lifted at cell {1000 * cell:g} mm")
        (args.out / f"lift_shapes_cell{1000 * cell:g}mm.md").write_text(table, encoding="utf-8")
        print(table)


if __name__ == "__main__":
    main(sys.argv[1:])
