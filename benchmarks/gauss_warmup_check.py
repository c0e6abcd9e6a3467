"""Does the network warm-up of ``gauss-dynamic`` replace its drift guard on a from-video scene?

Usage:
    python benchmarks/gauss_warmup_check.py [--out runs/warmup_check]

Generates the from-video suite's S-S scene (``recipes/video_quickstart.yaml`` with two sand
bodies, seed 9, 14 frames: ``benchmarks/video_suite.py``'s scene for that pair) and fits it
with the recipe's reconstructor four times: drift guard (``lambda_track``) on or off, times
network warm-up on (default) or off. Prints, per fit, the largest offset (hull voxels) between
an object's mean Gaussian centre and its hull centroid over the first 30 steps and at the
last step, and the per-frame training-view IoU of each object. CPU, about 20 s per fit.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch
from omegaconf import OmegaConf

ROOT = Path(__file__).resolve().parent.parent
#: (label, options): the guard's "off" keeps a negligible weight so its offsets are still logged
VARIANTS = (
    ("guard on, warm-up on", {"lambda_track": 0.01}),
    ("guard on, warm-up off", {"lambda_track": 0.01, "network_warmup": 0}),
    ("guard off, warm-up on", {"lambda_track": 1e-12}),
    ("guard off, warm-up off", {"lambda_track": 1e-12, "network_warmup": 0}),
)


def main(argv=None) -> None:
    import mosiv_gauss.train as train

    from mosiv_framework.registry import get_registry
    from mosiv_framework.scene import read_scene

    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--out", type=Path, default=Path("runs/warmup_check"))
    args = p.parse_args(argv)
    recipe = OmegaConf.to_container(OmegaConf.load(ROOT / "recipes/video_quickstart.yaml"))
    source = {k: v for k, v in recipe["scene"]["source"].items() if k != "name"}
    source.update(materials="sand,sand", seed=9, n_frames=14, observed_frames=9, progress=False)
    registry = get_registry()
    folder = args.out / "scene"
    if not (folder / "scene.json").is_file():
        registry.create("scene_source", "synth", source).generate(folder)
    scene = read_scene(folder)
    fit = {k: v for k, v in recipe["reconstructor"].items() if k != "name"}
    fit["save_dir"] = ""

    track_loss = train.track_loss
    for label, options in VARIANTS:
        offsets: list[float] = []

        def logged(means, frames, object_ids, data, *, tolerance, offsets=offsets):
            with torch.no_grad():
                step = [
                    float(o) for _, _, o in train.track_offsets(means, frames, object_ids, data)
                ]
            offsets.append(max(step, default=0.0))
            return track_loss(means, frames, object_ids, data, tolerance=tolerance)

        train.track_loss = logged
        try:
            recon = registry.create("reconstructor", "gauss-dynamic", {**fit, **options}).fit(scene)
        finally:
            train.track_loss = track_loss
        iou = recon.extras["training"]["iou"]
        print(
            f"{label}: largest offset {max(offsets[:30]):.1f} voxels in the first 30 steps, "
            f"{offsets[-1]:.1f} at the last",
            flush=True,
        )
        for k, values in iou.items():
            print(f"  object {k} IoU per frame: " + " ".join(f"{v:.2f}" for v in values))


if __name__ == "__main__":
    main(sys.argv[1:])
