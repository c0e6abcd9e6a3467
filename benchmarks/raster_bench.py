"""The Gaussian rasterizer's two compositing backends side by side: time and agreement.

Renders one frame of random Gaussians (``--gaussians``) through an oblique camera at
``--size`` pixels with the torch backend (the reference) and the Warp backend, forward and
backward (a weighted sum of every output), and prints per backend the mean time of
``--repeats`` renders after a warm-up, plus the PSNR between the two RGB images and the
largest relative gradient difference. Examples:

    python benchmarks/raster_bench.py --device cpu --size 128 --gaussians 5000
    python benchmarks/raster_bench.py --device cuda --size 256 --gaussians 20000
"""

from __future__ import annotations

import argparse
import json
import math
import time

import torch
from mosiv_gauss.options import TorchRasterizerOptions
from mosiv_gauss.rasterizer import rasterize

from mosiv_framework.scene.cameras import Camera
from mosiv_framework.types import GaussianFrames


def scene(n: int, device: str) -> GaussianFrames:
    gen = torch.Generator().manual_seed(0)
    means = (torch.rand(1, n, 3, generator=gen) - 0.5) * 0.6
    radii = 0.004 + 0.012 * torch.rand(1, n, generator=gen)
    colors = torch.rand(n, 3, generator=gen)
    opacities = 0.3 + 0.6 * torch.rand(n, generator=gen)
    leaves = [t.to(device).requires_grad_(True) for t in (means, radii, colors, opacities)]
    return GaussianFrames(*leaves, (torch.arange(n) % 2 + 1).to(device))


def _sync(device: str) -> float:
    if device.startswith("cuda"):
        torch.cuda.synchronize()
    return time.perf_counter()


def run(backend: str, args) -> dict:
    cam = Camera.look_at(
        (0.5, -1.6, 0.8), (0.0, 0.0, 0.0), width=args.size, height=args.size, fx=1.2 * args.size
    )
    opts = TorchRasterizerOptions(tile_size=args.tile, backend=backend, checkpoint=False)
    gauss = scene(args.gaussians, args.device)
    times = []
    for i in range(args.repeats + 1):
        for leaf in (gauss.means, gauss.radii, gauss.colors, gauss.opacities):
            leaf.grad = None
        t0 = _sync(args.device)
        out, stats = rasterize(gauss, cam, n_objects=2, options=opts)
        loss = out.rgb.sum() + 0.5 * out.alpha.sum() + out.depth.sum() + out.object_alpha[0].sum()
        loss.backward()
        t1 = _sync(args.device)
        if i > 0:  # the first call compiles kernels / warms caches
            times.append(t1 - t0)
    return {
        "rgb": out.rgb.detach(),
        "grads": [
            g.grad.detach() for g in (gauss.means, gauss.radii, gauss.colors, gauss.opacities)
        ],
        "mean_s": sum(times) / len(times),
        "tile_pairs": stats.n_tile_pairs,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--gaussians", type=int, default=5000)
    ap.add_argument("--tile", type=int, default=16)
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args()
    ref, fast = run("torch", args), run("warp", args)
    mse = float((ref["rgb"] - fast["rgb"]).square().mean())
    psnr = math.inf if mse == 0 else 10 * math.log10(1.0 / mse)
    grad_rel = max(
        float((a - b).abs().max()) / max(float(b.abs().max()), 1e-30)
        for a, b in zip(fast["grads"], ref["grads"])
    )
    report = {
        "device": torch.cuda.get_device_name() if args.device.startswith("cuda") else "cpu",
        "size": args.size,
        "gaussians": args.gaussians,
        "tile_pairs": ref["tile_pairs"],
        "torch_forward_backward_s": ref["mean_s"],
        "warp_forward_backward_s": fast["mean_s"],
        "speedup": ref["mean_s"] / fast["mean_s"],
        "psnr_warp_vs_torch_db": psnr,
        "max_relative_gradient_difference": grad_rel,
    }
    print(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
