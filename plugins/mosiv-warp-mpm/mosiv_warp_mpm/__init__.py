"""mosiv-warp-mpm: differentiable multi-object MLS-MPM on NVIDIA Warp.

Importing this package does not import Warp; the simulator module does, on first use.
"""

from mosiv_warp_mpm.options import WarpMPMOptions

__all__ = ["WarpMPMOptions"]
