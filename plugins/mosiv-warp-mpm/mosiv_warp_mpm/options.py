"""Options of the warp-mpm simulator (the same names as every MOSIV MPM backend)."""

from __future__ import annotations

from dataclasses import dataclass

from mosiv_framework.errors import ConfigError

DEVICES = ("cpu", "cuda", "auto")
CONTACT_MODES = ("multi_field", "single_field")


@dataclass(frozen=True)
class WarpMPMOptions:
    """grid: cells along the longest side of the scene domain (dx = longest side / grid);
    substeps: MPM steps per video frame (dt = 1 / (fps * substeps), s);
    device: "cpu", "cuda" or "auto" (cuda when available);
    contact: "multi_field" (one velocity field per object, Coulomb contact) or
    "single_field" (all objects share one field: classic sticky MPM contact)."""

    grid: int = 64
    substeps: int = 100
    device: str = "cpu"
    contact: str = "multi_field"

    def __post_init__(self) -> None:
        problems = []
        if isinstance(self.grid, bool) or not isinstance(self.grid, int) or self.grid < 8:
            problems.append(
                f"grid={self.grid!r}: must be an integer >= 8 (cells along the longest side)"
            )
        if (
            isinstance(self.substeps, bool)
            or not isinstance(self.substeps, int)
            or self.substeps < 1
        ):
            problems.append(f"substeps={self.substeps!r}: must be an integer >= 1 per video frame")
        if self.device not in DEVICES and not str(self.device).startswith("cuda:"):
            problems.append(f"device={self.device!r}: valid values are {list(DEVICES)} or 'cuda:N'")
        if self.contact not in CONTACT_MODES:
            problems.append(f"contact={self.contact!r}: valid values are {list(CONTACT_MODES)}")
        if problems:
            raise ConfigError([f"simulator warp-mpm: {p}" for p in problems])
