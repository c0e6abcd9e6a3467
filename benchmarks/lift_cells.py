"""How the lift's cell size bounds its voxel IoU on the generated shapes.

Usage:
    python benchmarks/lift_cells.py ceiling --shapes pawn,banana --draws 2 --cells 0.006,0.003
    python benchmarks/lift_cells.py relift RECONSTRUCTION_DIR SCENE_DIR [...] --cells 0.006,0.003

``ceiling``: the IoU of a PERFECT lift. Each draw makes a ``mosiv_synth`` mesh in a random
rotation, its ground-truth particles on the generator's lattice (``--spacing``, random phase),
and the exact more-than-half-inside occupancy of the mesh on a lift grid of each ``--cells``
size at another random phase (``--samples``^3 points per cell). That occupancy, emitted one
particle per cell, is scored like a lift (``mosiv_lift.quality.lift_geometry``): what is lost
is the two grids' quantisation alone.

``relift``: lifts saved ``gauss-dynamic`` reconstructions (``lift_shapes.py
--save-reconstructions``) at each cell size with the ``lift_shapes.py`` full preset otherwise,
and scores them on the ground-truth lattice.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).parent))  # lift_shapes' presets, for ``relift``


def perfect_occupancy(mesh, origin: np.ndarray, cell: float, samples: int) -> np.ndarray:
    """Centres [M, 3] (m) of the cells of the grid (``origin``, ``cell``) that ``mesh`` fills
    more than half of, measured with ``samples``^3 points per cell."""
    from mosiv_synth.sampling import inside_mask

    lo, hi = mesh.bounds
    first = np.floor((lo - origin) / cell).astype(int) - 1
    last = np.ceil((hi - origin) / cell).astype(int) + 1
    axes = [origin[d] + cell * (np.arange(first[d], last[d]) + 0.5) for d in range(3)]
    centres = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    f = (np.arange(samples) + 0.5) / samples - 0.5
    offsets = np.stack(np.meshgrid(f, f, f, indexing="ij"), axis=-1).reshape(-1, 3) * cell
    points = (centres[:, None, :] + offsets[None]).reshape(-1, 3)
    share = inside_mask(points, mesh.vertices, mesh.faces).reshape(len(centres), -1).mean(axis=1)
    return centres[share > 0.5]


def ceiling(args) -> None:
    from mosiv_lift.quality import lift_geometry
    from mosiv_synth.sampling import random_rotation, sample_inside
    from mosiv_synth.shapes import make_shape

    from mosiv_framework.types import ParticleSet

    rng = np.random.default_rng(args.seed)
    cells = [float(c) for c in args.cells.split(",")]
    print("| shape | " + " | ".join(f"perfect lift, {1000 * c:g} mm cell" for c in cells) + " |")
    print("|---|" + "---|" * len(cells))
    for name in args.shapes.split(","):
        scores = {c: [] for c in cells}
        for _ in range(args.draws):
            mesh = make_shape(name, rng)
            mesh.vertices = mesh.vertices @ random_rotation(rng).T
            lattice = sample_inside(mesh, args.spacing, offset=rng.uniform(0.0, 1.0, 3))
            gt = torch.from_numpy(lattice)
            origin = rng.uniform(0.0, args.spacing, 3)  # the lift grid's phase
            for c in cells:
                centres = torch.from_numpy(perfect_occupancy(mesh, origin, c, args.samples))
                n = len(centres)
                lift = ParticleSet(
                    positions=centres,
                    volumes=torch.full((n,), c**3, dtype=torch.float64),
                    object_ids=torch.ones(n, dtype=torch.int64),
                    materials={1: "elastic"},
                )
                score = lift_geometry(lift, {1: gt}, gt_spacing=args.spacing, cell=args.spacing)
                scores[c].append(score[1]["iou"])
        row = " | ".join(f"{min(v):.3f}-{max(v):.3f}" for v in scores.values())
        print(f"| {name} | {row} |", flush=True)


def relift(args) -> None:
    from lift_shapes import PRESETS, lift_scene
    from mosiv_gauss.reconstructor import load_reconstruction

    from mosiv_framework.scene import read_scene

    if len(args.folders) % 2:
        raise SystemExit("relift takes pairs: RECONSTRUCTION_DIR SCENE_DIR ...")
    cells = args.cells.split(",")
    print(
        "| shape | "
        + " | ".join(
            f"volume error / IoU / min gap (cells) / PSNR full (dB), {1000 * float(c):g} mm"
            for c in cells
        )
        + " |"
    )
    print("|---|" + "---|" * len(cells))
    for recon_dir, scene_dir in zip(args.folders[::2], args.folders[1::2]):
        scene = read_scene(scene_dir)
        reconstruction = load_reconstruction(recon_dir)
        rows = {str(o.id): [o.name] for o in scene.objects}
        for c in cells:
            options = {**PRESETS["full"]["lift"], "cell_size": float(c)}
            score = lift_scene(reconstruction, scene, options, gt_spacing=args.spacing)
            for k, s in score["objects"].items():
                rows[k].append(
                    f"{100 * s['volume_error']:+.1f} % / {s['iou']:.3f} / "
                    f"{score['min_gap_cells']:.1f} / {score['psnr']['full']:.1f}"
                )
        for row in rows.values():
            print("| " + " | ".join(row) + " |", flush=True)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    sub = p.add_subparsers(dest="command", required=True)
    c = sub.add_parser("ceiling", help="IoU of perfect lifts of the generator's meshes")
    c.add_argument("--shapes", default="egg,pawn,banana,cushion,mushroom")
    c.add_argument("--draws", type=int, default=2)
    c.add_argument("--samples", type=int, default=3, help="points per cell and axis")
    c.add_argument("--seed", type=int, default=5)
    r = sub.add_parser("relift", help="lift saved reconstructions at several cell sizes")
    r.add_argument("folders", nargs="+", help="RECONSTRUCTION_DIR SCENE_DIR pairs")
    for q in (c, r):
        q.add_argument("--cells", default="0.006,0.003", help="lift cell sizes (m)")
        q.add_argument("--spacing", type=float, default=0.006, help="ground-truth lattice (m)")
    args = p.parse_args(argv)
    if args.command == "ceiling":
        ceiling(args)
    else:
        relift(args)


if __name__ == "__main__":
    main(sys.argv[1:])
