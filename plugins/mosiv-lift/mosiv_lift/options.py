"""Options of the ``gaussians`` lifter (the registry validates recipe/CLI options against them).

Lengths in metres, densities in kg/m^3. Every problem is reported at once, naming the option,
its value and what would be valid.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

from mosiv_framework.errors import ConfigError


def _is_int(value: object) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _is_number(value: object) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


#: share of the virtual views that must agree a sample is inside a reconstruction's own
#: (trained, widened) Gaussians: a point just outside a smooth surface is hidden behind it
#: from at most the half of all directions behind its tangent plane, so it passes at most
#: half of the views; a point inside a closed surface passes all of them. The threshold is
#: the midpoint of the two, 3/4, the widest margin on either side. (Gaussians seeded from
#: points use 1: they are closed by construction and no view sees through them.)
TRAINED_AGREEMENT = 0.75


@dataclass
class GaussiansLifterOptions:
    """How the ``gaussians`` lifter carves, refines, emits and binds.

    cell_size (m): side of the emission grid shared by all objects (aligned with the scene
        domain's lower corner).
    particles_per_cell: particles per occupied cell, a cube n^3 (1, 8, 27, 64), on an n x n x n
        sub-lattice; each carries cell_size^3 / n^3 of rest volume.
    samples_per_cell: random carving samples per finest cell of an object's box (expected).
        A cell's measured occupancy is the kept share of its samples, with binomial standard
        error sqrt(f (1 - f) / n); the default, 32, keeps a cell three quarters inside (or
        outside) the object on the right side of the 1/2 threshold up to 0.25 / 0.077 = 3.3
        standard errors (8 samples: 1.6, so about one such boundary cell in twenty flips).
    levels: coarse-to-fine levels of the density grid; the coarsest cell is
        cell_size * 2^(levels - 1).
    prior_weight: how many samples' worth of evidence the upsampled, filtered coarser level
        carries when a cell's own samples are blended in (larger = smoother).
    padding (m): margin around the bounding box of an object's frame-0 Gaussians (None: one
        cell plus twice the largest Gaussian radius).
    mask_views_missed: recorded views in which a sample may fall on background and still be
        kept (tolerates mask noise; 0 = strict visual hull).
    mask_dilation_px: recorded masks are dilated by this many pixels before the test (their
        pixels are coarse relative to the Gaussians).
    virtual_views: views around each object (Fibonacci sphere) in which its Gaussians are
        rendered for the depth and silhouette test; 0 uses recorded masks only.
    virtual_resolution: width = height (pixels) of those views.
    alpha_threshold: rendered object alpha above which a pixel counts as covered by the object.
    depth_tolerance (m): a sample closer to a virtual camera than the rendered surface by more
        than this is free space (None: 0; the surface is the ray's median-like depth, see
        ``surface_fraction``, with each Gaussian counted from its half-density point, which
        already balances the volume of opaque Gaussians on the ten benchmark shapes).
    surface_fraction: the rendered surface along a virtual view's ray lies where this fraction
        of the pixel's opacity has accumulated (None: half the median opacity of the object's
        Gaussians: 0.5 for opaque Gaussians seeded from points, less for trained Gaussians that
        fill the volume with semi-transparent ones).
    widen_radius (m): in the virtual views the Gaussians are drawn with radii
        sqrt(r^2 + widen_radius^2) (blurred by a Gaussian of that standard deviation), so that
        neighbouring Gaussians overlap into a closed surface; the depth test still counts each
        one from its own half-density front. None: for a reconstruction's own (trained)
        Gaussians half the median distance between neighbouring Gaussians of the object (the
        radius the lifter gives points, ``seed.default_point_radius``): trained on images
        sampled at pixel centres they are small and sparse, and between the training rays
        the virtual views would see through them; 0 for Gaussians seeded from points (their
        radius is already that spacing).
    virtual_agreement: fraction of the virtual views in which a sample must pass that test
        (1 = every view, strict carving; less lets the other views outvote one that sees
        into the object through a gap of a trained reconstruction, e.g. its unobserved
        underside). None: 1 for Gaussians the lifter seeds from points (closed by
        construction), ``TRAINED_AGREEMENT`` for a reconstruction's own Gaussians.
    density: kg/m^3, one number for all objects or a mapping object id -> density (the masses
        a recipe gives the particles; simulators take rho from the parameters).
    point_radius (m): Gaussian radius given to reconstruction points when the reconstruction has
        no Gaussians (the oracle); None: half the median nearest-neighbour distance.
    bind_neighbors: particles of the same object each Gaussian is bound to.
    bind_power: exponent p of the inverse-distance weights 1 / (d + eps)^p.
    renderer: registered renderer used for the virtual views and for appearance.
    renderer_options: options of that renderer (small tiles suit the small virtual views).
    max_samples: refuse boxes that would need more carving samples than this (memory guard).
    seed: seeds every random draw (the lift is deterministic for a given seed).
    """

    cell_size: float = 0.01
    particles_per_cell: int = 1
    samples_per_cell: float = 32.0
    levels: int = 3
    prior_weight: float = 2.0
    padding: float | None = None
    mask_views_missed: int = 0
    mask_dilation_px: int = 1
    virtual_views: int = 14
    virtual_resolution: int = 64
    alpha_threshold: float = 0.5
    depth_tolerance: float | None = None
    surface_fraction: float | None = None
    widen_radius: float | None = None
    virtual_agreement: float | None = None
    density: Any = 1000.0
    point_radius: float | None = None
    bind_neighbors: int = 4
    bind_power: float = 2.0
    renderer: str = "gauss-torch"
    renderer_options: dict[str, Any] = field(default_factory=lambda: {"tile_size": 8})
    max_samples: int = 20_000_000
    seed: int = 0

    def __post_init__(self) -> None:
        problems = self._sampling_problems() + self._view_problems() + self._binding_problems()
        if problems:
            raise ConfigError([f"lifter gaussians: {p}" for p in problems])
        self.renderer_options = dict(self.renderer_options)
        if isinstance(self.density, dict) or hasattr(self.density, "items"):
            self.density = {int(k): float(v) for k, v in self.density.items()}
        else:
            self.density = float(self.density)

    def _sampling_problems(self) -> list[str]:
        """Problems of the grid, sampling and mask options."""
        problems: list[str] = []
        if not _is_number(self.cell_size) or self.cell_size <= 0:
            problems.append(f"cell_size={self.cell_size!r}: must be a positive length (m)")
        n = round(self.particles_per_cell ** (1.0 / 3.0)) if _is_int(self.particles_per_cell) else 0
        if not _is_int(self.particles_per_cell) or n < 1 or n**3 != self.particles_per_cell:
            problems.append(
                f"particles_per_cell={self.particles_per_cell!r}: must be a cube of an integer "
                "(1, 8, 27, 64, ...) so particles sit on a regular sub-lattice"
            )
        if not _is_number(self.samples_per_cell) or self.samples_per_cell <= 0:
            problems.append(f"samples_per_cell={self.samples_per_cell!r}: must be a number > 0")
        if not _is_int(self.levels) or not 1 <= self.levels <= 6:
            problems.append(f"levels={self.levels!r}: must be an integer in 1..6")
        if not _is_number(self.prior_weight) or self.prior_weight < 0:
            problems.append(f"prior_weight={self.prior_weight!r}: must be a number >= 0")
        if self.padding is not None and (not _is_number(self.padding) or self.padding < 0):
            problems.append(f"padding={self.padding!r}: must be None or a length >= 0 (m)")
        if not _is_int(self.mask_views_missed) or self.mask_views_missed < 0:
            problems.append(
                f"mask_views_missed={self.mask_views_missed!r}: must be an integer >= 0"
            )
        if not _is_int(self.mask_dilation_px) or not 0 <= self.mask_dilation_px <= 16:
            problems.append(
                f"mask_dilation_px={self.mask_dilation_px!r}: must be an integer in 0..16"
            )
        return problems

    def _view_problems(self) -> list[str]:
        """Problems of the virtual-view depth test's options."""
        problems: list[str] = []
        if not _is_int(self.virtual_views) or not (
            self.virtual_views == 0 or self.virtual_views >= 4
        ):
            problems.append(
                f"virtual_views={self.virtual_views!r}: must be 0 (masks only) or an integer >= 4"
            )
        if not _is_int(self.virtual_resolution) or not 16 <= self.virtual_resolution <= 1024:
            problems.append(
                f"virtual_resolution={self.virtual_resolution!r}: must be an integer in 16..1024 px"
            )
        if not _is_number(self.alpha_threshold) or not 0 < self.alpha_threshold < 1:
            problems.append(f"alpha_threshold={self.alpha_threshold!r}: must lie in (0, 1)")
        if self.depth_tolerance is not None and (
            not _is_number(self.depth_tolerance) or self.depth_tolerance < 0
        ):
            problems.append(
                f"depth_tolerance={self.depth_tolerance!r}: must be None or a length >= 0 (m)"
            )
        if self.surface_fraction is not None and (
            not _is_number(self.surface_fraction) or not 0 < self.surface_fraction < 1
        ):
            problems.append(
                f"surface_fraction={self.surface_fraction!r}: must be None or lie in (0, 1)"
            )
        if self.widen_radius is not None and (
            not _is_number(self.widen_radius) or self.widen_radius < 0
        ):
            problems.append(
                f"widen_radius={self.widen_radius!r}: must be None or a length >= 0 (m)"
            )
        if self.virtual_agreement is not None and (
            not _is_number(self.virtual_agreement) or not 0 < self.virtual_agreement <= 1
        ):
            problems.append(f"virtual_agreement={self.virtual_agreement!r}: must lie in (0, 1]")
        return problems

    def _binding_problems(self) -> list[str]:
        """Problems of the density, binding, renderer and budget options."""
        problems: list[str] = []
        problems += _density_problems(self.density)
        if self.point_radius is not None and (
            not _is_number(self.point_radius) or self.point_radius <= 0
        ):
            problems.append(f"point_radius={self.point_radius!r}: must be None or a length > 0 (m)")
        if not _is_int(self.bind_neighbors) or not 1 <= self.bind_neighbors <= 64:
            problems.append(f"bind_neighbors={self.bind_neighbors!r}: must be an integer in 1..64")
        if not _is_number(self.bind_power) or not 0 <= self.bind_power <= 8:
            problems.append(f"bind_power={self.bind_power!r}: must be a number in [0, 8]")
        if not isinstance(self.renderer, str) or not self.renderer:
            problems.append(f"renderer={self.renderer!r}: must be a registered renderer name")
        if not _is_int(self.max_samples) or self.max_samples < 1000:
            problems.append(f"max_samples={self.max_samples!r}: must be an integer >= 1000")
        if not _is_int(self.seed):
            problems.append(f"seed={self.seed!r}: must be an integer")
        return problems

    @property
    def sub_lattice(self) -> int:
        """n, the particles per cell along one axis."""
        return round(self.particles_per_cell ** (1.0 / 3.0))

    def density_of(self, object_id: int) -> float:
        """kg/m^3 of one object; raises naming the object when a mapping lacks it."""
        if isinstance(self.density, dict):
            if object_id not in self.density:
                raise ConfigError(
                    f"lifter gaussians: density gives no value for object {object_id}; "
                    f"it has objects {sorted(self.density)} (give one number for all objects "
                    "or one per object id)"
                )
            return self.density[object_id]
        return self.density


def _density_problems(density: Any) -> list[str]:
    items = density.items() if hasattr(density, "items") else [("all", density)]
    problems = []
    for key, value in items:
        if key != "all" and not (_is_int(key) or (isinstance(key, str) and key.isdigit())):
            problems.append(f"density: key {key!r} must be an object id (1..K)")
        if not _is_number(value) or not 0 < value <= 1e5:
            problems.append(
                f"density[{key}]={value!r}: must be a number in (0, 1e5] kg/m^3"
                if key != "all"
                else f"density={value!r}: must be a number in (0, 1e5] kg/m^3 or a mapping "
                "object id -> density"
            )
    return problems
