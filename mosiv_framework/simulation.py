"""Options every MPM simulator backend shares, so recipes and parity runs use one vocabulary.

A backend subclasses ``MPMOptions`` (adding its own options or limits) and registers the
subclass as its option schema; ``grid``, ``substeps``, ``device`` and ``contact`` then mean the
same thing whichever backend a recipe names.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from mosiv_framework.errors import ConfigError

CONTACT_MODES = ("multi_field", "single_field")


@dataclass(frozen=True)
class MPMOptions:
    """grid: cells along the longest side of the scene domain (dx = longest side / grid);
    substeps: MPM steps per video frame (dt = 1 / (fps * substeps), s);
    device: "cpu", "cuda" or "auto" (cuda when available);
    contact: "multi_field" (one velocity field per object, Coulomb contact) or
    "single_field" (all objects share one field: classic sticky MPM contact)."""

    grid: int = 64
    substeps: int = 100
    device: str = "cpu"
    contact: str = "multi_field"

    #: registered name used in error messages
    backend: ClassVar[str] = "mpm"
    #: device names the backend accepts
    devices: ClassVar[tuple[str, ...]] = ("cpu", "cuda", "auto")

    def problems(self) -> list[str]:
        """Every invalid option, each naming the option, its value and what is valid."""
        out = []
        if isinstance(self.grid, bool) or not isinstance(self.grid, int) or self.grid < 8:
            out.append(
                f"grid={self.grid!r}: must be an integer >= 8 (cells along the longest side)"
            )
        if (
            isinstance(self.substeps, bool)
            or not isinstance(self.substeps, int)
            or self.substeps < 1
        ):
            out.append(f"substeps={self.substeps!r}: must be an integer >= 1 per video frame")
        if self.device not in self.devices:
            out.append(f"device={self.device!r}: valid values are {list(self.devices)}")
        if self.contact not in CONTACT_MODES:
            out.append(f"contact={self.contact!r}: valid values are {list(CONTACT_MODES)}")
        return out

    def __post_init__(self) -> None:
        problems = self.problems()
        if problems:
            raise ConfigError([f"simulator {self.backend} option {p}" for p in problems])
