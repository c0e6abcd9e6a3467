"""Entry point of the ``mosiv-taichi-mpm`` distribution (group ``mosiv``).

Registers the ``taichi-mpm`` simulator. Taichi itself is imported only when the factory runs,
so listing plugins never pays Taichi's start-up cost.
"""

from __future__ import annotations

from mosiv_framework.registry import Component, hookimpl
from mosiv_taichi_mpm.options import TaichiMPMOptions


def make_simulator(**options):
    """Factory: build a TaichiMPMSimulator from validated option values."""
    from mosiv_taichi_mpm.simulator import TaichiMPMSimulator  # lazy: imports taichi

    return TaichiMPMSimulator(TaichiMPMOptions(**options))


@hookimpl
def mosiv_simulators(register):
    register(
        Component(
            "simulator",
            "taichi-mpm",
            factory=make_simulator,
            options=TaichiMPMOptions,
            description="differentiable multi-object MLS-MPM on Taichi (CPU/CUDA), six laws",
        )
    )
