"""Positions and gradients of one differentiable taichi-mpm rollout, to compare two versions.

Usage:
    TI_OFFLINE_CACHE=0 PYTHONPATH=CHECKOUT/plugins/mosiv-taichi-mpm \\
        python benchmarks/taichi_gradient_snapshot.py write OLD.npz
    TI_OFFLINE_CACHE=0 python benchmarks/taichi_gradient_snapshot.py write NEW.npz
    python benchmarks/taichi_gradient_snapshot.py compare OLD.npz NEW.npz

``write`` rolls out a two-body scene (synthetic, built here: two blocks thrown sideways onto the
table, one starting inside the slip walls' layers, grid 16, 30 substeps, 4 frames) with linear
and quadratic drag, wind, material damping and ground restitution on, back-propagates a fixed
random projection of the positions into every floating-point parameter, and saves the
positions and gradients with the wall time (which includes building every kernel: with
``TI_OFFLINE_CACHE=0`` that is the build time of this layout). ``compare`` prints, per
quantity, the largest difference relative to the first file's largest magnitude, and whether
the positions are identical. The offline cache must be off for an A/B: Taichi keys its cache
by kernel, and two versions in one place should each build their own.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from mosiv_framework.registry import get_registry
from mosiv_framework.testing.shapes import block, combine, default_params
from mosiv_framework.types import World


def snapshot() -> dict[str, np.ndarray]:
    """Positions (frames + 1, n, 3) and d loss / d parameter for every floating parameter."""
    sim = get_registry().create(
        "simulator", "taichi-mpm", {"device": "cpu", "grid": 16, "substeps": 30}
    )
    world = World((0.0, 0.0, 0.0), (0.5, 0.5, 0.5), gravity=(0.0, 0.0, -9.8), ground_height=0.0)
    near_wall = block((0.03, 0.2, 0.02), (0.25, 0.3, 0.1), spacing=1.0 / 48, object_id=1)
    other = block((0.26, 0.2, 0.02), (0.34, 0.3, 0.1), spacing=1.0 / 48, object_id=2)
    particles = combine([near_wall, other])
    params = default_params(
        particles,
        overrides={1: {"friction": 0.5}, 2: {"friction": 0.3}},
        velocities={1: (-0.8, 0.6, -0.8), 2: (-0.8, -0.6, -0.8)},
        ground_friction=0.2,
        terms={
            "linear_drag": {"coefficient": 0.5},
            "quadratic_drag": {"coefficient": 0.3},
            "wind": {"acceleration": [0.5, -0.3, 0.0]},
            "material_damping": {"viscosity": 20.0},
            "ground_restitution": {"coefficient": 0.5},
        },
    )
    weights = torch.randn(len(particles), 3, generator=torch.Generator().manual_seed(1))
    named = dict(params.named_tensors())
    leaves = {
        name: t.detach().clone().requires_grad_(True)
        for name, t in named.items()
        if t.dtype.is_floating_point
    }
    traj = sim.rollout(particles, params.with_tensors(leaves), world=world, frames=4)
    loss = ((traj.positions[1:] - traj.positions[:1]) * weights).sum()
    grads = torch.autograd.grad(loss, list(leaves.values()), allow_unused=True)
    out = {"pos": traj.positions.detach().numpy()}
    for name, g in zip(leaves, grads):
        if g is not None:
            out["g_" + name] = g.numpy()
    return out


def compare(a_path: str, b_path: str) -> dict[str, float]:
    a, b = np.load(a_path), np.load(b_path)
    missing = sorted(set(a.files) ^ set(b.files))
    if missing:
        raise SystemExit(f"{a_path} and {b_path} hold different quantities: {missing}")
    rel = {}
    for k in a.files:
        if k == "wall_s":
            continue
        scale = max(float(np.abs(a[k]).max()), 1e-30)
        rel[k] = float(np.abs(a[k] - b[k]).max()) / scale
        print(f"{k:45s} {rel[k]:.2e}")
    print("positions identical:", bool(np.array_equal(a["pos"], b["pos"])))
    print(f"wall time (s): {float(a['wall_s']):.1f} and {float(b['wall_s']):.1f}")
    return rel


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="command", required=True)
    w = sub.add_parser("write", help="roll out, back-propagate, save positions and gradients")
    w.add_argument("out")
    c = sub.add_parser("compare", help="largest relative difference per quantity")
    c.add_argument("a")
    c.add_argument("b")
    args = ap.parse_args(argv)
    if args.command == "write":
        t0 = time.perf_counter()
        data = snapshot()
        data["wall_s"] = np.array(time.perf_counter() - t0)
        np.savez(args.out, **data)
        print(f"wrote {args.out}: {len(data) - 2} gradients, {float(data['wall_s']):.1f} s")
    else:
        compare(args.a, args.b)


if __name__ == "__main__":
    main()
