"""Options of the CoupNeRF* components (validated by the registry before a factory runs)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

from mosiv_framework.errors import ConfigError
from mosiv_nerf.splat import KERNELS

DEVICES = ("cpu", "cuda", "auto")


def _problems_of(checks: list[tuple[bool, str]], component: str) -> None:
    """Raise one ConfigError listing every failed check."""
    problems = [message for ok, message in checks if not ok]
    if problems:
        raise ConfigError(f"{component}: " + "; ".join(problems))


def _positive(value: object) -> bool:
    return (
        isinstance(value, (int, float))
        and not isinstance(value, bool)
        and math.isfinite(value)
        and value > 0
    )


def _count(value: object, low: int = 1) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and value >= low


@dataclass
class NerfFieldOptions:
    """Options of the ``nerf-field`` reconstructor.

    resolution: voxels along the longest side of the field's box (the frame-0 visual hull's
        bounding box plus ``margin`` voxels; the box is never larger than the domain).
    margin: voxels added around the hull's bounding box.
    iterations: Adam steps of the frame-0 fit.
    rays_per_step: rays drawn at random from every camera's frame-0 pixels per step.
    lr: Adam learning rate of the density and colour grids (raw values, DVGO-style).
    step_ratio: ray-marching sample spacing in voxels (0.5: two samples per voxel).
    mask_weight: weight of the per-object mask L1 beside the photometric MSE.
    tv_weight: total-variation weight on the density grid (smooths empty-space floaters).
    hull_points: target points per object and frame (visual hull of the masks at every frame,
        what identification's initial-velocity fit and any Chamfer term read).
    hull_resolution: lattice nodes along the domain's longest side for the per-frame hulls.
    seed: seed of the ray batches and the hull point draws.
    device: ``cpu``, ``cuda`` or ``auto`` (cuda when available).
    """

    resolution: int = 64
    margin: int = 3
    iterations: int = 400
    rays_per_step: int = 4096
    lr: float = 0.1
    step_ratio: float = 0.5
    mask_weight: float = 1.0
    tv_weight: float = 1e-4
    hull_points: int = 2000
    hull_resolution: int = 64
    seed: int = 0
    device: str = "auto"

    def __post_init__(self) -> None:
        _problems_of(
            [
                (_count(self.resolution, 4), f"resolution={self.resolution!r}: integer >= 4"),
                (_count(self.margin, 0), f"margin={self.margin!r}: integer >= 0"),
                (_count(self.iterations, 0), f"iterations={self.iterations!r}: integer >= 0"),
                (_count(self.rays_per_step), f"rays_per_step={self.rays_per_step!r}: >= 1"),
                (_positive(self.lr), f"lr={self.lr!r}: number > 0"),
                (_positive(self.step_ratio), f"step_ratio={self.step_ratio!r}: number > 0"),
                (self.mask_weight >= 0, f"mask_weight={self.mask_weight!r}: >= 0"),
                (self.tv_weight >= 0, f"tv_weight={self.tv_weight!r}: >= 0"),
                (_count(self.hull_points), f"hull_points={self.hull_points!r}: >= 1"),
                (_count(self.hull_resolution, 4), "hull_resolution: integer >= 4"),
                (self.device in DEVICES, f"device={self.device!r}: one of {list(DEVICES)}"),
            ],
            "reconstructor nerf-field",
        )


@dataclass
class NerfGridOptions:
    """Options of the ``nerf-grid`` renderer (particles splatted to a grid, volume-rendered).

    cell: grid spacing (m); 0 takes the particles' own spacing (twice their median radius).
    kernel: P2G weights, ``bspline`` (quadratic B-spline, the MPM's) or ``trilinear``.
    step_ratio: ray-marching sample spacing in cells.
    max_samples: most samples per ray (bounds memory on large grids).
    """

    cell: float = 0.0
    kernel: str = "bspline"
    step_ratio: float = 0.5
    max_samples: int = 512

    def __post_init__(self) -> None:
        _problems_of(
            [
                (self.cell >= 0 and math.isfinite(self.cell), f"cell={self.cell!r}: >= 0 m"),
                (self.kernel in KERNELS, f"kernel={self.kernel!r}: one of {list(KERNELS)}"),
                (_positive(self.step_ratio), f"step_ratio={self.step_ratio!r}: number > 0"),
                (_count(self.max_samples, 2), f"max_samples={self.max_samples!r}: >= 2"),
            ],
            "renderer nerf-grid",
        )


@dataclass
class NerfParticlesOptions:
    """Options of the ``nerf-particles`` lifter.

    spacing: lattice spacing of the particles (m); 0 takes the field's voxel size.
    threshold: a lattice point becomes a particle where the field's opacity over one spacing,
        1 - exp(-sigma spacing), exceeds this; it belongs to the object of largest density.
    jitter: each lattice point moves by up to this fraction of a spacing along every axis.
    max_particles_per_object: an object with more particles keeps a random subset (0: all);
        the volume of the kept ones grows so the object's total volume stays the same.
    seed: seed of the jitter and of the subsets.
    renderer: the registered renderer that draws the particles (evaluation images) and its
        options.
    """

    spacing: float = 0.0
    threshold: float = 0.5
    jitter: float = 0.5
    max_particles_per_object: int = 20000
    seed: int = 0
    renderer: str = "nerf-grid"
    renderer_options: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        _problems_of(
            [
                (self.spacing >= 0, f"spacing={self.spacing!r}: >= 0 m"),
                (0 < self.threshold < 1, f"threshold={self.threshold!r}: in (0, 1)"),
                (0 <= self.jitter <= 1, f"jitter={self.jitter!r}: in [0, 1]"),
                (_count(self.max_particles_per_object, 0), "max_particles_per_object: >= 0"),
            ],
            "lifter nerf-particles",
        )


@dataclass
class NerfPhotometricOptions:
    """Options of the ``nerf-photometric`` loss (identification through rendered images).

    weight: factor of this term in the objective (>= 0).
    scene: the scene folder whose images and masks are the targets (``${scene.path}``).
    run_dir: the run folder whose particles.pt carries the particles' colours and densities
        (``${output.dir}``); identification runs after the lift that writes it.
    rgb_weight, mask_weight: factors of the per-pixel colour L1 and the per-object mask L1.
    size: images are rendered and compared at size x size pixels (area-averaged targets);
        0 keeps the cameras' resolution.
    cameras_per_call: cameras drawn at random per evaluation (0: every camera).
    seed: seed of the camera draws.
    renderer_options: options of the grid renderer (``NerfGridOptions``).
    """

    weight: float = 1.0
    scene: str = ""
    run_dir: str = ""
    rgb_weight: float = 1.0
    mask_weight: float = 1.0
    size: int = 0
    cameras_per_call: int = 0
    seed: int = 0
    renderer_options: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        _problems_of(
            [
                (self.weight >= 0, f"weight={self.weight!r}: >= 0"),
                (bool(self.scene), "scene: the scene folder, e.g. ${scene.path}"),
                (bool(self.run_dir), "run_dir: the run folder, e.g. ${output.dir}"),
                (self.rgb_weight >= 0 and self.mask_weight >= 0, "rgb/mask weights: >= 0"),
                (_count(self.size, 0), f"size={self.size!r}: integer >= 0"),
                (_count(self.cameras_per_call, 0), "cameras_per_call: integer >= 0"),
            ],
            "loss nerf-photometric",
        )
        NerfGridOptions(**dict(self.renderer_options))
