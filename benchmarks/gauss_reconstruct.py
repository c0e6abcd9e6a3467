"""Benchmark of the ``gauss-dynamic`` reconstructor (its acceptance scene).

Generates the two-object synth scene of the issue (11 cameras, 30 frames, 128x128) unless
``--scene`` names an existing one, reconstructs it, and writes one JSON object (also printed)
with training-view PSNR, per-object mask IoU per frame, per-object Chamfer distance (mm^2) of the
Gaussian centres to the ground-truth points per frame, the contact-frame error ratio (identity
kept through the collision), wall time and peak memory. Non-interactive; examples:

    python benchmarks/gauss_reconstruct.py --device cuda --out runs/gauss_bench.json
    python benchmarks/gauss_reconstruct.py --scene runs/quickstart/scene --device cpu \\
        --options '{"iterations": 300}' --out runs/gauss.json
"""

from __future__ import annotations

import argparse
import json
import platform
import resource
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from mosiv_framework.metrics import chamfer_floor_mm2
from mosiv_framework.registry import get_registry
from mosiv_framework.scene import read_scene

#: the acceptance thresholds (reported next to the measured values)
TARGETS = {"psnr_db": 30.0, "iou_min": 0.9, "chamfer_mm2_max": 4.0, "contact_ratio_max": 2.0}


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--scene", type=Path, help="existing mosiv-scene/1 folder (skips generation)")
    p.add_argument("--scene-dir", type=Path, help="where to generate the scene (default: temp)")
    p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    p.add_argument("--resolution", type=int, default=128)
    p.add_argument("--cameras", type=int, default=11)
    p.add_argument("--frames", type=int, default=30)
    p.add_argument("--particle-spacing", type=float, default=0.008)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--options", default="{}", help="JSON of gauss-dynamic options to override")
    p.add_argument("--out", type=Path, required=True, help="JSON file to write the results to")
    p.add_argument(
        "--save-reconstruction",
        type=Path,
        help="also save the fitted reconstruction in this folder (gaussians.npz, for re-scoring)",
    )
    return p.parse_args(argv)


def generate_scene(args: argparse.Namespace) -> Path:
    """The acceptance scene: 2 objects, ``--cameras`` views, ``--frames`` frames, simulated by
    warp-mpm on the benchmark device."""
    root = args.scene_dir or Path(tempfile.mkdtemp(prefix="gauss_bench_")) / "scene"
    options = {
        "n_objects": 2,
        "resolution": args.resolution,
        "n_cameras": args.cameras,
        "n_frames": args.frames,
        "observed_frames": args.frames // 2,
        "particle_spacing": args.particle_spacing,
        "simulator": "warp-mpm",
        "simulator_options": {"device": args.device},
        "seed": args.seed,
        "progress": False,
    }
    return get_registry().create("scene_source", "synth", options).generate(root)


def contact_frames(gt: dict[int, torch.Tensor], *, distance: float) -> list[int]:
    """Frames where some pair of objects' ground-truth points come within ``distance`` (m)."""
    from scipy.spatial import cKDTree

    ids = sorted(gt)
    n_frames = gt[ids[0]].shape[0]
    out = []
    for t in range(n_frames):
        touching = False
        for i, a in enumerate(ids):
            for b in ids[i + 1 :]:
                d, _ = cKDTree(gt[b][t].numpy()).query(gt[a][t].numpy(), k=1)
                touching |= bool(d.min() < distance)
        if touching:
            out.append(t)
    return out


def main(argv=None) -> dict:
    args = parse_args(argv)
    from mosiv_gauss.evaluate import chamfer_per_frame

    t0 = time.perf_counter()
    scene_path = args.scene or generate_scene(args)
    generate_s = time.perf_counter() - t0
    scene = read_scene(scene_path)
    options = {"device": args.device, "progress": False, **json.loads(args.options)}
    reconstructor = get_registry().create("reconstructor", "gauss-dynamic", options)
    if args.device.startswith("cuda"):
        torch.cuda.reset_peak_memory_stats()
    t1 = time.perf_counter()
    recon = reconstructor.fit(scene)
    if args.device.startswith("cuda"):
        torch.cuda.synchronize()
    fit_s = time.perf_counter() - t1

    if args.save_reconstruction:
        from mosiv_gauss.reconstructor import save_reconstruction

        save_reconstruction(recon, args.save_reconstruction)
    training = recon.extras["training"]
    gt = scene.gt_points()
    cd = chamfer_per_frame(recon.points, gt)
    spacing = float(scene.gt_params().get("generator_params", {}).get("particle_spacing", 0.01))
    contact = contact_frames(gt, distance=1.5 * spacing)
    per_object = {}
    for k, values in cd.items():
        values = np.asarray(values)
        iou = [v for v in training["iou"][str(k)] if v is not None]
        inside = values[contact] if contact else np.array([])
        outside = np.delete(values, contact) if contact else values
        ratio = float(inside.mean() / outside.mean()) if len(inside) and len(outside) else None
        per_object[str(k)] = {
            "iou_min": min(iou) if iou else None,
            "chamfer_mm2_max": float(values.max()),
            "chamfer_mm2_mean": float(values.mean()),
            "chamfer_mm2_per_frame": values.tolist(),
            "contact_ratio": ratio,
        }
    peak_gpu = torch.cuda.max_memory_allocated() if args.device.startswith("cuda") else None
    result = {
        "scene": str(scene_path),
        "device": args.device,
        "gpu": torch.cuda.get_device_name() if args.device.startswith("cuda") else None,
        "host": platform.node(),
        "n_cameras": len(scene.cameras),
        "n_frames": scene.n_frames,
        "resolution": [scene.cameras[0].width, scene.cameras[0].height],
        "options": recon.extras["options"],
        "n_gaussians": recon.extras["n_gaussians"],
        "skipped_steps": recon.extras["skipped_steps"],
        "psnr_db": training["psnr_mean"],
        "psnr_db_min": training["psnr_min"],
        "iou_min": training["iou_min"],
        "iou_per_frame": training["iou"],
        "area_ratio_per_frame": training["area_ratio"],
        "chamfer_mm2_max": max(o["chamfer_mm2_max"] for o in per_object.values()),
        "chamfer_floor_mm2": chamfer_floor_mm2(gt, spacing=spacing),
        "contact_frames": contact,
        "contact_ratio_max": max(
            (o["contact_ratio"] for o in per_object.values() if o["contact_ratio"] is not None),
            default=None,
        ),
        "per_object": per_object,
        "generate_seconds": generate_s,
        "fit_seconds": fit_s,
        "peak_gpu_memory_bytes": peak_gpu,
        "peak_rss_bytes": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024,
        "targets": TARGETS,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n", encoding="utf-8")
    print(json.dumps(result, indent=2))
    return result


if __name__ == "__main__":
    main(sys.argv[1:])
