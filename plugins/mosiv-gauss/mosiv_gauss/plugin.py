"""Entry point of the mosiv-gauss plugin: registers the ``gauss-torch`` renderer and the
``gauss-dynamic`` reconstructor."""

from __future__ import annotations

from mosiv_framework.registry import Component, hookimpl
from mosiv_gauss.dynamic_options import DynamicGaussOptions
from mosiv_gauss.options import TorchRasterizerOptions


def make_torch_rasterizer(**options):
    """Build a TorchRasterizer from keyword options (validated by TorchRasterizerOptions)."""
    from mosiv_gauss.rasterizer import TorchRasterizer

    return TorchRasterizer(TorchRasterizerOptions(**options))


def make_dynamic_reconstructor(**options):
    """Build a GaussDynamicReconstructor from keyword options (validated by
    DynamicGaussOptions); torch training code is imported only when one is built."""
    from mosiv_gauss.reconstructor import GaussDynamicReconstructor

    return GaussDynamicReconstructor(**options)


@hookimpl
def mosiv_reconstructors(register):
    register(
        Component(
            "reconstructor",
            "gauss-dynamic",
            factory=make_dynamic_reconstructor,
            options=DynamicGaussOptions,
            description="object-aware dynamic Gaussians (paper eq. 1-2): visual-hull init, "
            "basis/coefficient deformation networks, photometric + per-object mask training",
        )
    )


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
