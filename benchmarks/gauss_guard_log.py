"""When does gauss-dynamic's drift guard (``lambda_track``) act, and on which frames?

Usage:
    python benchmarks/gauss_guard_log.py SCENE_DIR [--out guard_log.json]

Fits ``gauss-dynamic`` with the ``lift_shapes.py`` full preset on the CPU and records, at every
step, the guard's value and each object's offset (in hull voxels) between its mean Gaussian
centre and its visual-hull centroid at the step's frames. It wraps
``mosiv_gauss.train.track_loss`` for the fit, so the training itself is unchanged.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).parent))  # lift_shapes' presets


def main(argv=None) -> None:
    import mosiv_gauss.train as train
    from lift_shapes import PRESETS

    from mosiv_framework.registry import get_registry
    from mosiv_framework.scene import read_scene

    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("scene", type=Path)
    p.add_argument("--out", type=Path, default=Path("guard_log.json"))
    args = p.parse_args(argv)

    steps = []
    track_loss = train.track_loss

    def logged(means, frames, object_ids, data, *, tolerance):
        value = track_loss(means, frames, object_ids, data, tolerance=tolerance)
        with torch.no_grad():
            offsets = [
                [t, k, round(float(off), 3)]
                for t, k, off in train.track_offsets(means, frames, object_ids, data)
            ]
        steps.append({"guard": float(value.detach()), "offsets": offsets})
        return value

    train.track_loss = logged
    options = {**PRESETS["full"]["fit"], "device": "cpu", "progress": False, "save_dir": ""}
    get_registry().create("reconstructor", "gauss-dynamic", options).fit(read_scene(args.scene))

    active = [i for i, s in enumerate(steps) if s["guard"] > 0]
    largest: dict[str, float] = {}
    for s in steps:
        for t, k, off in s["offsets"]:
            key = f"frame {t}, object {k}"
            largest[key] = max(largest.get(key, 0.0), off)
    summary = {"steps": len(steps), "active_steps": active, "largest_offset_voxels": largest}
    args.out.write_text(json.dumps({**summary, "log": steps}) + "\n", encoding="utf-8")
    print(json.dumps(summary, indent=1))
    for i in active:
        print(i, round(steps[i]["guard"], 3), steps[i]["offsets"])


if __name__ == "__main__":
    main(sys.argv[1:])
