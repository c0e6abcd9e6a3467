"""Options of the taichi-mpm simulator: the shared MPM options with Taichi's grid limit."""

from __future__ import annotations

from dataclasses import dataclass

from mosiv_framework.simulation import MPMOptions


@dataclass(frozen=True)
class TaichiMPMOptions(MPMOptions):
    """The shared MPM options (see mosiv_framework.simulation.MPMOptions); grid <= 1024.

    fused_forward: advance the forward substeps, and recompute each substep's grid before its
    adjoints, with the fused kernels of forward_kernels.py (true, the default) or with the
    split kernels whose adjoints the reverse pass runs (false: the same equations, kept to
    measure what the fusion saves and to check it)."""

    fused_forward: bool = True

    backend = "taichi-mpm"

    def problems(self) -> list[str]:
        problems = super().problems()
        if isinstance(self.grid, int) and self.grid > 1024:
            problems.append(f"grid={self.grid!r}: must be <= 1024 cells")
        if not isinstance(self.fused_forward, bool):
            problems.append(f"fused_forward={self.fused_forward!r}: must be true or false")
        return problems
