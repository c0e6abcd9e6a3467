"""Options of the warp-mpm simulator: the shared MPM options, plus CUDA device ordinals."""

from __future__ import annotations

from dataclasses import dataclass

from mosiv_framework.simulation import MPMOptions


@dataclass(frozen=True)
class WarpMPMOptions(MPMOptions):
    """The shared MPM options (see mosiv_framework.simulation.MPMOptions); ``device`` may also
    name one GPU as "cuda:N"."""

    backend = "warp-mpm"

    def problems(self) -> list[str]:
        problems = super().problems()
        if str(self.device).startswith("cuda:"):  # Warp addresses GPUs by ordinal
            problems = [p for p in problems if not p.startswith("device=")]
        return problems
