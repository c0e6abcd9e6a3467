"""Per-frame refinement (``gauss-dynamic`` option ``refine_iterations``) on a saved fit.

Loads a scene and a reconstruction saved by ``gauss_reconstruct.py --save-reconstruction``,
runs ``mosiv_gauss.refine.refine_frames`` on it with each ``--variants`` set of options, and
prints, before and after, per object: the worst and mean mask IoU over frames, the worst and
mean Chamfer (mm^2) of the Gaussian centres to the true particles, and the contact-frame ratio.
Cheaper than a refit: the trained model is reused, only the refinement runs. Example:

    python benchmarks/gauss_refine_check.py --scene runs/g6/scene --recon runs/g6/base_recon \\
        --options '{"hull_resolution": 96, "views_per_step": 2, "lambda_hull": 0.01}' \\
        --variants '{"refine_iterations": 300}' '{"refine_iterations": 300, "lambda_refine_smooth": 0.1}'
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

from mosiv_framework.scene import read_scene


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--scene", type=Path, required=True)
    p.add_argument("--recon", type=Path, required=True, help="saved reconstruction folder")
    p.add_argument("--device", default="cpu")
    p.add_argument("--options", default="{}", help="JSON of gauss-dynamic options (shared)")
    p.add_argument("--variants", nargs="+", default=['{"refine_iterations": 300}'])
    p.add_argument("--out", type=Path, help="JSON file for every variant's scores")
    return p.parse_args(argv)


def scores(gaussians, scene, data, mask_ids, background, contact) -> dict:
    """Per object: IoU worst/mean, Chamfer worst/mean (mm^2), contact ratio; and PSNR."""
    from mosiv_gauss.evaluate import chamfer_per_frame, training_metrics

    metrics = training_metrics(gaussians, data.cameras, data.rgb, mask_ids, background)
    ids = gaussians.object_ids.cpu()
    points = {int(k): gaussians.means[:, ids == k].cpu() for k in ids.unique().tolist()}
    cd = chamfer_per_frame(points, scene.gt_points())
    out = {"psnr_db": metrics["psnr_mean"], "objects": {}}
    for k, values in cd.items():
        values = np.asarray(values)
        iou = np.asarray([v for v in metrics["iou"][str(k)] if v is not None])
        outside = np.delete(values, contact) if contact else values
        ratio = float(values[contact].mean() / outside.mean()) if contact else None
        out["objects"][str(k)] = {
            "iou_min": float(iou.min()),
            "iou_mean": float(iou.mean()),
            "iou_per_frame": np.round(iou, 3).tolist(),
            "chamfer_mm2_max": float(values.max()),
            "chamfer_mm2_mean": float(values.mean()),
            "contact_ratio": ratio,
        }
    return out


def line(name: str, s: dict, seconds: float | None = None) -> str:
    parts = [f"{name:<44} PSNR {s['psnr_db']:.2f}"]
    for k, o in s["objects"].items():
        ratio = "-" if o["contact_ratio"] is None else f"{o['contact_ratio']:.2f}"
        parts.append(
            f"obj {k}: IoU {o['iou_min']:.3f}/{o['iou_mean']:.3f} "
            f"CD {o['chamfer_mm2_max']:.0f}/{o['chamfer_mm2_mean']:.0f} ratio {ratio}"
        )
    if seconds is not None:
        parts.append(f"{seconds:.0f} s")
    return " | ".join(parts)


def main(argv=None) -> list[dict]:
    args = parse_args(argv)
    sys.path.insert(0, str(Path(__file__).parent))
    from gauss_reconstruct import contact_frames
    from mosiv_gauss.dynamic_options import DynamicGaussOptions
    from mosiv_gauss.reconstructor import load_reconstruction, prepare_training
    from mosiv_gauss.refine import refine_frames

    from mosiv_framework.types import GaussianFrames

    scene = read_scene(args.scene)
    shared = {"device": args.device, "progress": False, **json.loads(args.options)}
    base_opts = DynamicGaussOptions(**shared)
    generator = torch.Generator().manual_seed(base_opts.seed)
    data, _, mask_ids = prepare_training(scene, base_opts, torch.device(args.device), generator)
    recon = load_reconstruction(args.recon)
    g = recon.gaussians
    gaussians = GaussianFrames(
        *(x.to(args.device) for x in (g.means, g.radii, g.colors, g.opacities, g.object_ids))
    )
    cams = list(recon.background)
    background = torch.stack([recon.background[c] for c in cams]).to(args.device)
    spacing = float(scene.gt_params().get("generator_params", {}).get("particle_spacing", 0.01))
    contact = contact_frames(scene.gt_points(), distance=1.5 * spacing)

    results = [
        {
            "variant": "fitted model",
            "scores": scores(gaussians, scene, data, mask_ids, background, contact),
        }
    ]
    print(line("fitted model (no refinement)", results[0]["scores"]), flush=True)
    for text in args.variants:
        variant = json.loads(text)
        opts = DynamicGaussOptions(**{**shared, **variant})
        start = time.perf_counter()
        refined, history = refine_frames(
            gaussians, data, background, opts, generator=torch.Generator().manual_seed(opts.seed)
        )
        seconds = time.perf_counter() - start
        s = scores(refined, scene, data, mask_ids, background, contact)
        results.append(
            {
                "variant": variant,
                "seconds": seconds,
                "scores": s,
                "loss_first_last": [history[0], history[-1]] if history else None,
            }
        )
        print(line(json.dumps(variant), s, seconds), flush=True)
    if args.out:
        args.out.write_text(json.dumps(results, indent=2) + "\n", encoding="utf-8")
    return results


if __name__ == "__main__":
    main(sys.argv[1:])
