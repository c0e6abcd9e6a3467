"""Space carving of one object from its frame-0 Gaussians and the recorded masks.

Random samples are drawn uniformly in a box around the object's frame-0 Gaussians (the box is
cut into cells of the shared emission grid, so every cell gets the same expected number of
samples). A sample is kept when it is consistent with every view:
- recorded views (the scene's cameras at frame 0): the sample must project onto a pixel that
  the dilated foreground mask covers (its own object, or another object that may hide it), in
  all but ``mask_views_missed`` of the views that see it, and onto its own object's (dilated)
  mask in at least one view;
- virtual views (cameras on a Fibonacci sphere around the object, paper section 3.3 "several
  views"): the object's Gaussians alone are rendered; the sample must fall on a pixel whose
  object alpha reaches ``alpha_threshold`` and must not lie in front of the rendered surface
  depth ``depth / alpha`` by more than ``depth_tolerance`` (space in front of a visible surface
  is empty).
Virtual views see the object from every side, below included, which the recorded cameras on the
upper hemisphere cannot; the recorded masks guard against Gaussians that float off the object.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from mosiv_framework.scene.cameras import Camera
from mosiv_framework.types import GaussianFrames

Tensor = torch.Tensor


@dataclass(frozen=True)
class Box:
    """An axis-aligned block of the shared emission grid.

    The grid has cells of side ``cell`` (m) with cell (0, 0, 0) starting at ``origin`` (m).
    ``lower`` is the integer index of the block's first cell, ``shape`` its size in cells
    (each a multiple of ``2^(levels-1)``, so coarser levels tile it exactly).
    """

    origin: tuple[float, float, float]
    cell: float
    lower: tuple[int, int, int]
    shape: tuple[int, int, int]

    @property
    def world_lower(self) -> Tensor:
        """World position (m) of the block's lower corner, [3] float64."""
        return torch.tensor(self.origin, dtype=torch.float64) + self.cell * torch.tensor(
            self.lower, dtype=torch.float64
        )

    @property
    def n_cells(self) -> int:
        return self.shape[0] * self.shape[1] * self.shape[2]


def object_box(
    means: Tensor, radii: Tensor, *, origin, cell: float, levels: int, padding: float | None
) -> Box:
    """The grid block holding the bounding box of ``means`` [G, 3] grown by ``padding`` (m;
    None: one cell plus two of the largest radii), rounded out to whole coarse cells."""
    pad = cell + 2.0 * float(radii.max()) if padding is None else padding
    lo = means.detach().double().min(dim=0).values - pad
    hi = means.detach().double().max(dim=0).values + pad
    org = torch.tensor(origin, dtype=torch.float64)
    first = torch.floor((lo - org) / cell).long()
    last = torch.ceil((hi - org) / cell).long()
    step = 2 ** (levels - 1)
    size = ((last - first + step - 1) // step) * step
    # grow symmetrically so the object stays centred in the rounded block
    first = first - (size - (last - first)) // 2
    return Box(tuple(float(v) for v in origin), cell, tuple(first.tolist()), tuple(size.tolist()))


def draw_samples(box: Box, *, per_cell: float, generator: torch.Generator, limit: int) -> Tensor:
    """Uniform random points (m) in ``box``, ``per_cell`` per cell on average: [S, 3] float64."""
    count = int(math.ceil(per_cell * box.n_cells))
    if count > limit:
        raise ValueError(
            f"carving a box of {list(box.shape)} cells at cell_size={box.cell} m needs {count} "
            f"samples, more than max_samples={limit}; raise cell_size, lower samples_per_cell "
            "or raise max_samples"
        )
    unit = torch.rand((count, 3), generator=generator, dtype=torch.float64)
    extent = torch.tensor(box.shape, dtype=torch.float64) * box.cell
    return box.world_lower + unit * extent


def _pixel_lookup(camera: Camera, points: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Row, column of the pixel each point falls in, its camera depth (m), and whether it lands
    inside the image in front of the camera."""
    uv, z = camera.project(points)
    col = torch.floor(uv[:, 0]).long()
    row = torch.floor(uv[:, 1]).long()
    inside = (z > 0) & (col >= 0) & (col < camera.width) & (row >= 0) & (row < camera.height)
    return row.clamp(0, camera.height - 1), col.clamp(0, camera.width - 1), z, inside


def _dilate(mask: Tensor, pixels: int) -> Tensor:
    """Binary dilation of a [H, W] bool mask by a (2p+1)^2 square."""
    if pixels == 0:
        return mask
    x = mask.float()[None, None]
    return torch.nn.functional.max_pool2d(x, 2 * pixels + 1, stride=1, padding=pixels)[0, 0] > 0


def mask_consistent(
    samples: Tensor,
    object_id: int,
    cameras: list[Camera],
    masks: list[Tensor],
    *,
    dilation: int,
    views_missed: int,
) -> Tensor:
    """[S] bool: samples consistent with the recorded instance masks (each [H, W] int64)."""
    misses = torch.zeros(samples.shape[0], dtype=torch.int64)
    own_hits = torch.zeros(samples.shape[0], dtype=torch.int64)
    for camera, mask in zip(cameras, masks):
        foreground = _dilate(mask > 0, dilation)
        own = _dilate(mask == object_id, dilation)
        row, col, _, inside = _pixel_lookup(camera, samples)
        misses += (inside & ~foreground[row, col]).long()
        own_hits += (inside & own[row, col]).long()
    return (misses <= views_missed) & (own_hits >= 1)


def fibonacci_directions(n: int) -> Tensor:
    """``n`` unit vectors spread evenly over the sphere (golden-angle spiral), [n, 3] float64."""
    i = torch.arange(n, dtype=torch.float64) + 0.5
    z = 1.0 - 2.0 * i / n
    phi = math.pi * (3.0 - math.sqrt(5.0)) * i
    r = torch.sqrt(1.0 - z * z)
    return torch.stack([r * torch.cos(phi), r * torch.sin(phi), z], dim=-1)


def virtual_cameras(centre: Tensor, radius: float, *, n: int, resolution: int) -> list[Camera]:
    """``n`` cameras looking at ``centre`` from a distance of 4 ``radius`` (m), framing a sphere
    of ``radius`` with a 15% margin; nearly orthographic, so pixel size varies little."""
    distance = 4.0 * radius
    fov = 2.0 * math.degrees(math.atan(1.15 * radius / (distance - radius)))
    cams = []
    for j, d in enumerate(fibonacci_directions(n)):
        up = (0.0, 0.0, 1.0) if abs(float(d[2])) < 0.9 else (0.0, 1.0, 0.0)
        eye = centre.double() + distance * d
        cams.append(
            Camera.look_at(
                eye.tolist(),
                centre.double().tolist(),
                up,
                id=f"virtual_{j:02d}",
                width=resolution,
                height=resolution,
                fov_deg=fov,
            )
        )
    return cams


def depth_consistent(
    samples: Tensor,
    gaussians: GaussianFrames,
    renderer,
    cameras: list[Camera],
    *,
    alpha_threshold: float,
    depth_tolerance: float,
) -> Tensor:
    """[S] bool: samples inside the rendered silhouette and not in front of the rendered
    surface in every view. ``gaussians`` hold one frame of a single object with id 1."""
    keep = torch.ones(samples.shape[0], dtype=torch.bool)
    for camera in cameras:
        with torch.no_grad():
            out = renderer.render(gaussians, camera, frame=0, n_objects=1)
        alpha = out.object_alpha[0].double()
        surface = out.depth.double() / alpha.clamp_min(1e-6)  # expected depth of the surface
        row, col, z, inside = _pixel_lookup(camera, samples)
        covered = alpha[row, col] >= alpha_threshold
        behind = z >= surface[row, col] - depth_tolerance
        keep &= inside & covered & behind
    return keep


@dataclass
class CarveResult:
    """samples: [S, 3] m (float64) drawn in ``box``; kept: [S] bool, the consistent ones."""

    box: Box
    samples: Tensor
    kept: Tensor


def carve_object(
    means: Tensor,
    radii: Tensor,
    colors: Tensor,
    opacities: Tensor,
    *,
    object_id: int,
    scene,
    masks: list[Tensor],
    renderer,
    options,
    generator: torch.Generator,
) -> CarveResult:
    """Carve one object from its frame-0 Gaussians (means [G, 3] m, radii [G] m, colors [G, 3],
    opacities [G]) and the recorded masks; ``options`` is a GaussiansLifterOptions."""
    box = object_box(
        means,
        radii,
        origin=scene.domain_lower,
        cell=options.cell_size,
        levels=options.levels,
        padding=options.padding,
    )
    samples = draw_samples(
        box, per_cell=options.samples_per_cell, generator=generator, limit=options.max_samples
    )
    kept = mask_consistent(
        samples,
        object_id,
        scene.cameras,
        masks,
        dilation=options.mask_dilation_px,
        views_missed=options.mask_views_missed,
    )
    if options.virtual_views:
        centre = 0.5 * (means.min(dim=0).values + means.max(dim=0).values)
        reach = float((means - centre).norm(dim=1).max()) + 3.0 * float(radii.max())
        single = GaussianFrames(
            means[None].float(),
            radii[None].float(),
            colors.float(),
            opacities.float(),
            torch.ones(means.shape[0], dtype=torch.int64),
        )
        tolerance = (
            (2.0 / 3.0) * options.cell_size
            if options.depth_tolerance is None
            else options.depth_tolerance
        )
        views = virtual_cameras(
            centre, reach, n=options.virtual_views, resolution=options.virtual_resolution
        )
        candidates = torch.nonzero(kept).squeeze(1)  # only test what the masks left
        ok = depth_consistent(
            samples[candidates],
            single,
            renderer,
            views,
            alpha_threshold=options.alpha_threshold,
            depth_tolerance=tolerance,
        )
        kept = torch.zeros_like(kept).index_fill(0, candidates[ok], True)
    return CarveResult(box, samples, kept)


def recorded_masks(scene) -> list[Tensor]:
    """Frame-0 instance masks of every camera, [H, W] int64 each, in cameras.json order."""
    return [torch.from_numpy(scene.mask(c.id, 0).astype(np.int64)) for c in scene.cameras]
