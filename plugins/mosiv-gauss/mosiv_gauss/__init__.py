"""mosiv-gauss: differentiable Gaussian rendering for MOSIV.

Importing the package stays light (options only); the rasterizer lives in
``mosiv_gauss.rasterizer``.
"""

from mosiv_gauss.options import TorchRasterizerOptions

__all__ = ["TorchRasterizerOptions"]
