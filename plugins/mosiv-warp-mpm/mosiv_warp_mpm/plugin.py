"""Entry point of the mosiv-warp-mpm plugin: registers the ``warp-mpm`` simulator.

Importing this module must stay cheap: Warp is imported only when the factory runs.
"""

from __future__ import annotations

from mosiv_framework.registry import Component, hookimpl
from mosiv_warp_mpm.options import WarpMPMOptions


def make_simulator(**options):
    """Build a WarpMPMSimulator from keyword options (validated by WarpMPMOptions)."""
    opts = WarpMPMOptions(**options)
    from mosiv_warp_mpm.simulator import WarpMPMSimulator  # imports warp lazily

    return WarpMPMSimulator(opts)


@hookimpl
def mosiv_simulators(register):
    register(
        Component(
            "simulator",
            "warp-mpm",
            factory=make_simulator,
            options=WarpMPMOptions,
            description="differentiable multi-object MLS-MPM on NVIDIA Warp (CPU/CUDA), six laws",
        )
    )
