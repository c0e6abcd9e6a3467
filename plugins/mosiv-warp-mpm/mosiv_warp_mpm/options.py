"""Options of the warp-mpm simulator: the shared MPM options, plus CUDA device ordinals and
Warp's deterministic atomics."""

from __future__ import annotations

from dataclasses import dataclass

from mosiv_framework.simulation import MPMOptions

#: grid_window's values (WarpMPMOptions)
GRID_WINDOWS = ("auto", "particles", "device", "whole")


@dataclass(frozen=True)
class WarpMPMOptions(MPMOptions):
    """The shared MPM options (see mosiv_framework.simulation.MPMOptions); ``device`` may also
    name one GPU as "cuda:N".

    deterministic: sum every atomic update (particle-to-grid transfers, the adjoints' scatters)
    in a fixed order on CUDA (Warp's ``DeterministicMode.RUN_TO_RUN``), so two runs on the same
    GPU give bit-identical rollouts and gradients. Slower (benchmarks/determinism_check.py
    measures by how much); CPU runs are sequential and reproducible either way. A Warp module
    option: one process runs all its warp-mpm simulators one way or the other.

    grid_window: which grid nodes a substep's grid kernels visit. "auto": the box around the
    particles, found on the host and launched at its own size on the CPU, where Warp runs a
    kernel's threads one after another, and kept on the device on CUDA ("device");
    "particles": the host's box on CUDA too (reduced on the device and read back each
    substep, launches without a captured graph); "device": the box found and kept on the
    device, the grid kernels launched at a fixed size (state.WINDOW_THREADS), so that a frame
    and its adjoint stay captured graphs; "whole": the whole grid everywhere. Results are the
    same up to float rounding (bit for bit on the CPU); only the time differs
    (docs/BENCHMARKS.md, Grid window on CUDA)."""

    deterministic: bool = False
    grid_window: str = "auto"

    backend = "warp-mpm"

    def problems(self) -> list[str]:
        problems = super().problems()
        if str(self.device).startswith("cuda:"):  # Warp addresses GPUs by ordinal
            problems = [p for p in problems if not p.startswith("device=")]
        if not isinstance(self.deterministic, bool):
            problems.append(f"deterministic={self.deterministic!r}: must be true or false")
        if not isinstance(self.grid_window, str) or self.grid_window not in GRID_WINDOWS:
            problems.append(
                f"grid_window={self.grid_window!r}: valid values are {list(GRID_WINDOWS)}"
            )
        return problems
