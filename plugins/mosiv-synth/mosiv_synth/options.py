"""Options of the ``synth`` scene source (the registry validates recipe/CLI options against them).

Defaults follow the paper's benchmark protocol (section 4.1): 2 objects, 11 cameras on the upper
hemisphere, 30 frames at 24 fps of which 15 are observed. Tests shrink resolution, cameras,
frames and particle density to make scenes in seconds.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from mosiv_framework.conceal import parse_conceal
from mosiv_framework.errors import ConfigError
from mosiv_framework.recipes.schema import law_problems
from mosiv_framework.scene.protocol import check_clip, name_list
from mosiv_synth.materials import MATERIAL_RANGES, RANGE_PRESETS
from mosiv_synth.shapes import SHAPE_NAMES


@dataclass
class SynthOptions:
    """Options of one generated scene.

    n_objects: 2 or 3 objects; shapes / materials: "random", a comma-separated string or a list
    of names (one per object; shape names in ``mosiv_synth.shapes.SHAPE_NAMES``, families in
    ``mosiv_synth.materials.MATERIAL_RANGES``); resolution: image width = height (pixels);
    n_cameras, n_frames, observed_frames, fps (1/s); particle_spacing: lattice spacing of the
    simulation particles (m); simulator: registered simulator name; simulator_options: its
    options (grid, substeps, device, ...); collision_frame: frame at which the objects first
    touch (0 = choose from the seed); ranges: parameter ranges the materials are drawn from,
    "paper" (the paper's benchmark) or "wide" (``mosiv_synth.materials.WIDE_RANGES``; the
    simulator's substeps are raised where a stiff draw needs it, see ``mosiv_synth.stability``);
    conceal: "KIND[:param=value,...]" effects separated by
    ";" or a list of them (see ``mosiv_framework.conceal``); seed: everything random derives from
    it; scene_name: scene name (empty = derived from materials and seed); progress: show a bar;
    laws: the law that simulates a material where it is not the material's own, e.g.
    ``{elastic: elastic_corotated}`` (data made with another stress than identification's
    default; gt/params.json records it under ``generator_params.laws``).
    """

    n_objects: int = 2
    shapes: Any = "random"
    materials: Any = "random"
    resolution: int = 128
    n_cameras: int = 11
    n_frames: int = 30
    observed_frames: int = 15
    fps: float = 24.0
    particle_spacing: float = 0.008
    simulator: str = "warp-mpm"
    simulator_options: dict[str, Any] = field(default_factory=dict)
    collision_frame: int = 0
    ranges: str = "paper"
    conceal: Any = None
    seed: int = 0
    scene_name: str = ""
    progress: bool = True
    laws: dict[str, str] = field(default_factory=dict)

    def __post_init__(self) -> None:
        problems: list[str] = []
        self.shapes = name_list(self.shapes, "shapes", SHAPE_NAMES, problems)
        self.materials = name_list(self.materials, "materials", tuple(MATERIAL_RANGES), problems)
        check_clip(
            n_objects=self.n_objects,
            per_object={"shapes": self.shapes, "materials": self.materials},
            resolution=self.resolution,
            n_cameras=self.n_cameras,
            n_frames=self.n_frames,
            observed_frames=self.observed_frames,
            problems=problems,
        )
        if self.fps <= 0:
            problems.append(f"fps={self.fps}: must be positive (frames per second)")
        if not 0.002 <= self.particle_spacing <= 0.03:
            problems.append(
                f"particle_spacing={self.particle_spacing} m: must lie in [0.002, 0.03] m "
                "(objects are 0.08-0.15 m across)"
            )
        if self.collision_frame != 0 and not 2 <= self.collision_frame < self.n_frames:
            problems.append(
                f"collision_frame={self.collision_frame}: must be 0 (automatic) or in "
                f"2..n_frames-1={self.n_frames - 1}"
            )
        if self.ranges not in RANGE_PRESETS:
            problems.append(f"ranges={self.ranges!r}: valid: {', '.join(RANGE_PRESETS)}")
        try:
            self.conceal = [e.spec() for e in parse_conceal(self.conceal)]
        except ValueError as exc:
            problems.append(f"conceal: {exc}")
        problems += law_problems(dict(self.laws), key="laws")
        if problems:
            raise ConfigError([f"scene_source synth: {p}" for p in problems])
