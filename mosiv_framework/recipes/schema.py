"""The structured schema of a recipe: one dataclass per section.

Component sections (reconstructor, lifter, simulator) are mappings with a ``name`` key naming a
registered component and that component's options beside it::

    simulator: {name: warp-mpm, grid: 64, substeps: 200}

``losses`` maps registered loss names to their options (``losses.chamfer.weight=0`` switches the
Chamfer term off). Everything else is plain typed fields with defaults.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

#: recipe section -> component kind its ``name`` refers to
COMPONENT_SECTIONS: dict[str, str] = {
    "reconstructor": "reconstructor",
    "lifter": "lifter",
    "simulator": "simulator",
}

#: which sections hold a mapping of several components of one kind, keyed by name
MULTI_COMPONENT_SECTIONS: dict[str, str] = {"losses": "loss"}


@dataclass
class SceneSection:
    """Where the recording is. ``path`` is a ``mosiv-scene/1`` folder. If it does not exist and
    ``source`` names a registered SceneSource (with its options), the scene is generated there
    first."""

    path: str = "scene"
    source: dict[str, Any] | None = None


@dataclass
class IdentifySection:
    """Stage III: initial velocity first, then per-object parameters (paper section 3.5)."""

    velocity_iterations: int = 80
    param_iterations: int = 200
    velocity_lr: float = 0.05
    param_lr: float = 0.05
    #: horizon curriculum: fit the first ``horizon_start`` frames first, then lengthen the
    #: rollout linearly so the whole observed window is used from ``horizon_full_at`` (a
    #: fraction of each phase's iterations) on
    horizon_start: int = 3
    horizon_full_at: float = 0.5
    #: re-synchronise the simulated particle state to the reconstruction every N frames (0 = off)
    resync_every: int = 0
    identify_friction: bool = True
    identify_ground_friction: bool = True
    seed: int = 0
    checkpoint_every: int = 10


@dataclass
class EvaluateSection:
    """Evaluation over observed and future frames (metrics.json, videos, plots)."""

    emd_samples: int = 2048
    render_videos: bool = True
    seed: int = 0


@dataclass
class DiagnoseSection:
    """Finding missing physics (DESIGN.md section 6)."""

    terms: list[str] = field(default_factory=list)
    max_candidates: int = 3
    bootstrap: int = 200
    starts: int = 2


@dataclass
class OutputSection:
    """The run folder and how to treat an existing one."""

    dir: str = "runs/default"
    resume: bool = True


@dataclass
class Recipe:
    scene: SceneSection = field(default_factory=SceneSection)
    reconstructor: dict[str, Any] = field(default_factory=lambda: {"name": "oracle"})
    lifter: dict[str, Any] = field(default_factory=lambda: {"name": "gt-points"})
    simulator: dict[str, Any] = field(default_factory=lambda: {"name": "warp-mpm"})
    losses: dict[str, Any] = field(
        default_factory=lambda: {"chamfer": {"weight": 1.0}, "silhouette": {"weight": 1.0}}
    )
    identify: IdentifySection = field(default_factory=IdentifySection)
    evaluate: EvaluateSection = field(default_factory=EvaluateSection)
    diagnose: DiagnoseSection = field(default_factory=DiagnoseSection)
    output: OutputSection = field(default_factory=OutputSection)
