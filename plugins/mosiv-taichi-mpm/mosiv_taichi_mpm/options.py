"""Options of the taichi-mpm simulator: the shared MPM options with Taichi's grid limit."""

from __future__ import annotations

from dataclasses import dataclass

from mosiv_framework.simulation import MPMOptions


@dataclass(frozen=True)
class TaichiMPMOptions(MPMOptions):
    """The shared MPM options (see mosiv_framework.simulation.MPMOptions); grid <= 1024."""

    backend = "taichi-mpm"

    def problems(self) -> list[str]:
        problems = super().problems()
        if isinstance(self.grid, int) and self.grid > 1024:
            problems.append(f"grid={self.grid!r}: must be <= 1024 cells")
        return problems
