"""The Warp compositing backend against the torch rasterizer (the reference): images within
1e-5 and gradients of a weighted image sum within 1e-3 relative, for every Gaussian input, also
behind thousands of overlapping Gaussians, on the device in MOSIV_TEST_DEVICE (default CPU;
"cuda" checks the CUDA fast path)."""

from __future__ import annotations

import os

import pytest
import torch
from mosiv_gauss.options import TorchRasterizerOptions
from mosiv_gauss.rasterizer import rasterize

from mosiv_framework.scene.cameras import Camera
from mosiv_framework.types import GaussianFrames

pytest.importorskip("warp")
DEVICE = os.environ.get("MOSIV_TEST_DEVICE", "cpu")


def oblique_camera(width: int, height: int) -> Camera:
    # fx != fy so the two footprint axes are exercised separately
    eye, target = (0.6, -2.0, 0.9), (0.0, 0.0, 0.0)
    return Camera.look_at(eye, target, width=width, height=height, fx=1.1 * width, fy=0.9 * width)


def _render(gauss: GaussianFrames, backend: str, *, tile: int = 8):
    opts = TorchRasterizerOptions(tile_size=tile, backend=backend, background=(0.2, 0.3, 0.4))
    out, stats = rasterize(gauss, oblique_camera(40, 32), n_objects=3, options=opts)
    return out, stats


def _scene(requires_grad: bool, g: int = 120, k: int = 3) -> GaussianFrames:
    """``g`` overlapping Gaussians of ``k`` objects around the origin (one frame)."""
    gen = torch.Generator().manual_seed(3)
    means = (torch.rand(1, g, 3, generator=gen) - 0.5) * 0.8
    radii = 0.03 + 0.09 * torch.rand(1, g, generator=gen)
    colors = torch.rand(g, 3, generator=gen)
    opacities = 0.3 + 0.6 * torch.rand(g, generator=gen)
    leaves = [t.to(DEVICE).requires_grad_(requires_grad) for t in (means, radii, colors, opacities)]
    return GaussianFrames(*leaves, (torch.arange(g) % k + 1).to(DEVICE))


def test_warp_images_match_the_torch_rasterizer():
    gauss = _scene(False)
    ref, _ = _render(gauss, "torch")
    out, stats = _render(gauss, "warp")
    assert stats.n_visible > 50 and float(ref.alpha.max()) > 0.9  # dense, overlapping splats
    for name in ("rgb", "alpha", "depth", "object_alpha"):
        a, b = getattr(out, name), getattr(ref, name)
        assert a.shape == b.shape and a.device == b.device, name
        assert float((a - b).abs().max()) < 1e-5, name


def _stack(
    requires_grad: bool, g: int = 3000, k: int = 3, opacity: tuple[float, float] = (0.2, 0.45)
) -> GaussianFrames:
    """``g`` Gaussians piled within 5 cm, opacities uniform in ``opacity``: a pixel sees all of
    them, so the transmittance behind them underflows float32 (as in a dense liquid after
    densification). Recovered by division from the final transmittance, as the backward once
    did, these gave NaN (3,000 half-transparent) or gradients 1e5-1e7 times too large (400
    nearly opaque)."""
    gen = torch.Generator().manual_seed(5)
    means = (torch.rand(1, g, 3, generator=gen) - 0.5) * 0.05
    radii = 0.05 + 0.02 * torch.rand(1, g, generator=gen)
    colors = torch.rand(g, 3, generator=gen)
    low, high = opacity
    opacities = low + (high - low) * torch.rand(g, generator=gen)
    leaves = [t.to(DEVICE).requires_grad_(requires_grad) for t in (means, radii, colors, opacities)]
    return GaussianFrames(*leaves, (torch.arange(g) % k + 1).to(DEVICE))


def _gradients_of_both_backends(make_scene):
    weights = None
    grads = {}
    for backend in ("torch", "warp"):
        gauss = make_scene(True)
        out, _ = _render(gauss, backend)
        images = [out.rgb, out.alpha, out.depth, out.object_alpha]
        if weights is None:  # one random weighting of every output channel, shared
            gen = torch.Generator().manual_seed(0)
            weights = [torch.rand(t.shape, generator=gen).to(DEVICE) for t in images]
        loss = sum((t * w).sum() for t, w in zip(images, weights))
        loss.backward()
        grads[backend] = [t.grad for t in (gauss.means, gauss.radii, gauss.colors, gauss.opacities)]
    return grads


def _opaque_stack(requires_grad: bool) -> GaussianFrames:
    return _stack(requires_grad, g=400, opacity=(0.85, 0.95))


@pytest.mark.parametrize(
    "make_scene",
    [_scene, _stack, _opaque_stack],
    ids=["overlapping", "thousands deep", "hundreds deep, nearly opaque"],
)
def test_warp_gradients_match_the_torch_rasterizer(make_scene):
    grads = _gradients_of_both_backends(make_scene)
    for name, a, b in zip(("means", "radii", "colors", "opacities"), grads["warp"], grads["torch"]):
        scale = float(b.abs().max())
        assert bool(torch.isfinite(a).all()), name
        assert scale > 0, name
        assert float((a - b).abs().max()) < 1e-3 * scale, (name, float((a - b).abs().max()), scale)


def test_warp_backend_draws_nothing_for_gaussians_behind_the_camera():
    gauss = _scene(False)
    behind = GaussianFrames(
        gauss.means + torch.tensor([0.0, -10.0, 0.0], device=DEVICE),  # behind the eye
        gauss.radii,
        gauss.colors,
        gauss.opacities,
        gauss.object_ids,
    )
    out, stats = _render(behind, "warp")
    assert stats.n_visible == 0
    assert float(out.alpha.abs().max()) == 0.0


def test_auto_backend_picks_warp_for_cuda_tensors_only():
    from mosiv_gauss.rasterizer import _use_warp

    assert not _use_warp("auto", torch.device("cpu"))  # the torch reference on the CPU
    assert _use_warp("auto", torch.device("cuda"))  # warp-lang is installed (importorskip)
    assert _use_warp("warp", torch.device("cpu")) and not _use_warp("torch", torch.device("cuda"))
