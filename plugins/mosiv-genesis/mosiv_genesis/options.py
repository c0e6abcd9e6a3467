"""Options of the ``genesis`` scene source, validated without importing Genesis.

Names match the ``synth`` source where the setting is the same (``mosiv data synth`` flags map
onto them): n_objects, materials, shapes, resolution, n_cameras, n_frames, observed_frames, fps,
seed, scene_name, conceal.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from mosiv_framework.conceal import parse_conceal
from mosiv_framework.errors import ConfigError
from mosiv_framework.scene.protocol import check_clip, name_list
from mosiv_genesis.plan import GENESIS_FAMILIES, RANGE_PRESETS, SHAPE_NAMES

#: concealed effects Genesis can realise: drag and wind as its acceleration fields
#: (gs.force_fields.Drag / Constant), gravity through SimOptions, and the out-of-library
#: fields of ``mosiv_framework.conceal_fields`` (vortex: gs.force_fields.Vortex; attractor:
#: gs.force_fields.Point). Ground friction is not offered: Genesis' MPM-ground contact has no
#: coefficient to change.
GENESIS_KINDS = ("linear_drag", "quadratic_drag", "wind", "gravity", "vortex", "attractor")


@dataclass
class GenesisOptions:
    """Options of one Genesis scene.

    n_objects: 2 or 3; shapes / materials: "random", comma-separated names or a list, one per
    object (families: elastic, plasticine, newtonian, sand, snow -- Genesis' Elastic,
    ElastoPlastic, Liquid, Sand, Snow); resolution: image width = height (pixels); n_cameras;
    n_frames; observed_frames; fps (1/s); substeps: MPM substeps per frame (140 at 24 fps
    gives dt = 3e-4 s, inside Genesis' stability hint ~0.02 s / grid_density at 64 cells/m;
    raised where a stiff draw needs more, see ``plan.required_substeps``); ranges: parameter
    ranges, "paper" or "wide" (``plan.WIDE_COMMON``, ``plan.WIDE_EXTRA``); grid_density: MPM
    grid cells per metre (1/m); particle_size: MPM particle spacing (m); collision_frame: frame
    of the mid-air collision (0 = from the seed); conceal: "KIND[:param=value,...]" effects
    (linear_drag, quadratic_drag, wind, gravity; out of the diagnosis library: vortex,
    attractor) separated by ";" or a list; vis_mode: how
    Genesis draws MPM bodies ("visual": the object mesh skinned to its particles, for sand and
    liquid their particles; "particle"; "recon": a reconstructed surface); backend: "cpu" or "gpu"; seed; scene_name (empty =
    from materials and seed); progress: print one line per frame.
    """

    n_objects: int = 2
    shapes: Any = "random"
    materials: Any = "random"
    resolution: int = 128
    n_cameras: int = 11
    n_frames: int = 30
    observed_frames: int = 15
    fps: float = 24.0
    substeps: int = 140
    ranges: str = "paper"
    grid_density: float = 64.0
    particle_size: float = 0.01
    collision_frame: int = 0
    conceal: Any = None
    vis_mode: str = "visual"
    backend: str = "cpu"
    seed: int = 0
    scene_name: str = ""
    progress: bool = True

    def __post_init__(self) -> None:
        problems: list[str] = []
        self.shapes = name_list(self.shapes, "shapes", SHAPE_NAMES, problems)
        self.materials = name_list(self.materials, "materials", GENESIS_FAMILIES, problems)
        check_clip(
            n_objects=self.n_objects,
            per_object={"shapes": self.shapes, "materials": self.materials},
            resolution=self.resolution,
            n_cameras=self.n_cameras,
            n_frames=self.n_frames,
            observed_frames=self.observed_frames,
            problems=problems,
        )
        if self.fps <= 0 or self.substeps < 1:
            problems.append(f"fps={self.fps}, substeps={self.substeps}: must be positive")
        if not 0.003 <= self.particle_size <= 0.03:
            problems.append(f"particle_size={self.particle_size} m: must lie in [0.003, 0.03] m")
        if self.ranges not in RANGE_PRESETS:
            problems.append(f"ranges={self.ranges!r}: valid: {', '.join(RANGE_PRESETS)}")
        if self.grid_density <= 0:
            problems.append(f"grid_density={self.grid_density}: must be positive (cells/m)")
        if self.collision_frame != 0 and not 2 <= self.collision_frame < self.n_frames:
            problems.append(
                f"collision_frame={self.collision_frame}: must be 0 (automatic) or in "
                f"2..{self.n_frames - 1}"
            )
        if self.vis_mode not in ("visual", "particle", "recon"):
            problems.append(f"vis_mode={self.vis_mode!r}: valid: visual, particle, recon")
        if self.backend not in ("cpu", "gpu"):
            problems.append(f"backend={self.backend!r}: valid: cpu, gpu")
        try:
            self.conceal = [e.spec() for e in parse_conceal(self.conceal, kinds=GENESIS_KINDS)]
        except ValueError as exc:
            problems.append(f"conceal: {exc}")
        if problems:
            raise ConfigError([f"scene_source genesis: {p}" for p in problems])
