"""Options of the ``taichi-mpm`` simulator (same names and meaning as the Warp backend)."""

from __future__ import annotations

from dataclasses import dataclass

from mosiv_framework.errors import ConfigError

DEVICES = ("cpu", "cuda", "auto")
CONTACT_MODES = ("multi_field", "single_field")


@dataclass(frozen=True, kw_only=True)
class TaichiMPMOptions:
    """grid: cells along the longest side of the scene domain (dx = longest side / grid);
    substeps: MPM substeps per video frame (dt = 1 / (fps * substeps), s);
    device: "cpu", "cuda" or "auto" (cuda when available);
    contact: "multi_field" (one velocity field per object, Coulomb contact) or
    "single_field" (one shared field, sticky contact)."""

    grid: int = 64
    substeps: int = 100
    device: str = "cpu"
    contact: str = "multi_field"

    def __post_init__(self) -> None:
        problems = []
        if not isinstance(self.grid, int) or isinstance(self.grid, bool) or self.grid < 8:
            problems.append(f"taichi-mpm option grid={self.grid!r} must be an integer >= 8")
        elif self.grid > 1024:
            problems.append(f"taichi-mpm option grid={self.grid!r} must be <= 1024 cells")
        if (
            not isinstance(self.substeps, int)
            or isinstance(self.substeps, bool)
            or self.substeps < 1
        ):
            problems.append(f"taichi-mpm option substeps={self.substeps!r} must be an integer >= 1")
        if self.device not in DEVICES:
            problems.append(f"taichi-mpm option device={self.device!r}; valid: {list(DEVICES)}")
        if self.contact not in CONTACT_MODES:
            problems.append(
                f"taichi-mpm option contact={self.contact!r}; valid: {list(CONTACT_MODES)}"
            )
        if problems:
            raise ConfigError(problems)
