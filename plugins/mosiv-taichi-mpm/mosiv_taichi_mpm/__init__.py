"""MOSIV simulator plugin: differentiable multi-object MLS-MPM on Taichi.

Importing this package does not import taichi; the simulator module does, on first use.
"""

from mosiv_taichi_mpm.options import TaichiMPMOptions

__all__ = ["TaichiMPMOptions"]
