"""Options of the warp-mpm simulator: the shared MPM options, plus CUDA device ordinals and
Warp's deterministic atomics."""

from __future__ import annotations

from dataclasses import dataclass

from mosiv_framework.simulation import MPMOptions


@dataclass(frozen=True)
class WarpMPMOptions(MPMOptions):
    """The shared MPM options (see mosiv_framework.simulation.MPMOptions); ``device`` may also
    name one GPU as "cuda:N".

    deterministic: sum every atomic update (particle-to-grid transfers, the adjoints' scatters)
    in a fixed order on CUDA (Warp's ``DeterministicMode.RUN_TO_RUN``), so two runs on the same
    GPU give bit-identical rollouts and gradients. Slower (benchmarks/determinism_check.py
    measures by how much); CPU runs are sequential and reproducible either way. A Warp module
    option: one process runs all its warp-mpm simulators one way or the other."""

    deterministic: bool = False

    backend = "warp-mpm"

    def problems(self) -> list[str]:
        problems = super().problems()
        if str(self.device).startswith("cuda:"):  # Warp addresses GPUs by ordinal
            problems = [p for p in problems if not p.startswith("device=")]
        if not isinstance(self.deterministic, bool):
            problems.append(f"deterministic={self.deterministic!r}: must be true or false")
        return problems
