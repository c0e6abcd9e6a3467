"""Entry point of the mosiv-gauss plugin: registers the ``gauss-torch`` renderer."""

from __future__ import annotations

from mosiv_framework.registry import Component, hookimpl
from mosiv_gauss.options import TorchRasterizerOptions


def make_torch_rasterizer(**options):
    """Build a TorchRasterizer from keyword options (validated by TorchRasterizerOptions)."""
    from mosiv_gauss.rasterizer import TorchRasterizer

    return TorchRasterizer(TorchRasterizerOptions(**options))


@hookimpl
def mosiv_renderers(register):
    register(
        Component(
            "renderer",
            "gauss-torch",
            factory=make_torch_rasterizer,
            options=TorchRasterizerOptions,
            description="differentiable tiled rasterizer of isotropic 3D Gaussians in pure torch "
            "(CPU/GPU): rgb, alpha, depth, per-object alpha",
        )
    )
