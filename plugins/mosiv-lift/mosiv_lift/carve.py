"""Space carving of one object from its frame-0 Gaussians and the recorded masks.

Random samples are drawn uniformly in a box around the object's frame-0 Gaussians (the box is
cut into cells of the shared emission grid, so every cell gets the same expected number of
samples). A sample is kept when it is consistent with the views:
- recorded views (the scene's cameras at frame 0): the sample must project onto a pixel that
  the dilated foreground mask covers (its own object, or another object that may hide it), in
  all but ``mask_views_missed`` of the views that see it, and onto its own object's (dilated)
  mask in at least one view;
- virtual views (cameras on a Fibonacci sphere around the object, paper section 3.3 "several
  views"): the object's Gaussians alone are rendered; the sample must fall on a pixel whose
  object alpha reaches ``alpha_threshold`` and must not lie in front of the rendered surface
  by more than ``depth_tolerance`` (space in front of a visible surface is empty), in at least
  the share ``agreement`` of these views (all of them for closed Gaussians; fewer lets the
  others outvote a view that sees through a gap of a trained reconstruction). The surface is
  where a set share of the pixel's opacity has accumulated along the ray (see
  ``depth_consistent``), each Gaussian counted from its half-density front. Trained Gaussians
  are rendered widened (``widened_radii``): fitted to low-resolution images whose pixels are
  sampled at their centres, they are small and sparse, and between the training rays they
  leave gaps that the virtual views see through (the ray then meets the surface too deep, or
  not at all, and interior samples are voted out, thin parts first).
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


def mask_hull_box(object_id: int, scene, masks: list[Tensor], *, options) -> Box | None:
    """The grid block around object ``object_id``'s visual hull in the recorded ``masks``,
    found on a lattice of twice ``options.cell_size`` over the whole scene domain (so Gaussians
    in the wrong place cannot mislead it); None when no lattice point lies in the hull."""
    step = 2.0 * options.cell_size
    lower = torch.tensor(scene.domain_lower, dtype=torch.float64)
    upper = torch.tensor(scene.domain_upper, dtype=torch.float64)
    axes = [torch.arange(float(lower[d]) + step / 2, float(upper[d]), step) for d in range(3)]
    lattice = torch.stack(torch.meshgrid(*axes, indexing="ij"), dim=-1).reshape(-1, 3)
    inside = mask_consistent(
        lattice,
        object_id,
        scene.cameras_at(0),
        masks,
        dilation=options.mask_dilation_px,
        views_missed=options.mask_views_missed,
    )
    if not inside.any():
        return None
    points = lattice[inside]
    return object_box(
        points,
        torch.zeros(points.shape[0]),
        origin=scene.domain_lower,
        cell=options.cell_size,
        levels=options.levels,
        padding=step,
    )


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


#: most depth layers one virtual view is split into (bounds the renderer's channels)
MAX_DEPTH_LAYERS = 64
#: distance from a Gaussian's centre, in radii (standard deviations), at which its density
#: falls to half: sqrt(2 ln 2). The rendered silhouette edge of an opaque Gaussian lies there,
#: so along the ray its opacity is counted from there too, not from its centre.
HALF_DENSITY_RADII = math.sqrt(2.0 * math.log(2.0))


def widened_radii(radii: Tensor, widen: float) -> Tensor:
    """Radii (m) of Gaussians blurred by an isotropic Gaussian of standard deviation ``widen``
    (m): variances add under convolution, r' = sqrt(r^2 + widen^2)."""
    return torch.sqrt(radii.double() ** 2 + widen**2).to(radii.dtype)


def opacity_in_front(
    gaussians: GaussianFrames,
    renderer,
    camera: Camera,
    *,
    layer: float,
    front_radii: Tensor | None = None,
) -> tuple[Tensor, Tensor, float, float]:
    """Opacity accumulated along each pixel's ray in front of a set of depths, in one render.

    The Gaussians are cut into depth layers of ``layer`` m (at most ``MAX_DEPTH_LAYERS``) by
    the camera depth of their half-density fronts (centre depth minus HALF_DENSITY_RADII
    radii; ``front_radii`` [G] m when the rendered radii are widened, so the widening blurs
    the silhouette but does not move the surface outwards), and each layer is rendered as its
    own object channel;
    front-to-back compositing makes a channel the opacity its layer adds (eq. w_g = T_g a_g),
    so the cumulative sum over layers is the opacity accumulated in front of each layer edge.
    Returns alpha [H, W] (total), cumulative [L + 1, H, W] (edge j, 0 at the front edge), the
    front edge (m) and the layer thickness (m)."""
    _, z = camera.project(gaussians.means[0].double())
    own = gaussians.radii[0] if front_radii is None else front_radii
    z = z - HALF_DENSITY_RADII * own.double()
    reach = 3.0 * float(gaussians.radii[0].max())
    front, back = float(z.min()) - reach, float(z.max()) + reach
    n_layers = max(1, min(MAX_DEPTH_LAYERS, math.ceil((back - front) / layer)))
    thickness = (back - front) / n_layers
    index = ((z - front) / thickness).floor().long().clamp(0, n_layers - 1)
    layered = GaussianFrames(
        gaussians.means, gaussians.radii, gaussians.colors, gaussians.opacities, index + 1
    )
    with torch.no_grad():
        out = renderer.render(layered, camera, frame=0, n_objects=n_layers)
    layers = out.object_alpha.double()
    cumulative = torch.cat([torch.zeros_like(layers[:1]), layers.cumsum(dim=0)])
    return out.alpha.double(), cumulative, front, thickness


def depth_consistent(
    samples: Tensor,
    gaussians: GaussianFrames,
    renderer,
    cameras: list[Camera],
    *,
    alpha_threshold: float,
    depth_tolerance: float,
    layer: float,
    surface_fraction: float,
    front_radii: Tensor | None = None,
) -> Tensor:
    """[S] int64: in how many of ``cameras`` each sample lies inside the rendered silhouette
    and not in front of the rendered surface. ``gaussians`` hold one frame of one object.

    The surface is where the accumulated opacity reaches ``surface_fraction`` of the pixel's
    total (0.5: the median depth). Unlike the alpha-weighted mean depth it does not sink into
    the object when the Gaussians behind the surface add opacity. A sample is in front of it
    by more than ``depth_tolerance`` when, at the sample's depth plus that tolerance, less
    than that share has been accumulated (linear in depth within a layer of ``layer`` m).
    ``front_radii``: see ``opacity_in_front``."""
    votes = torch.zeros(samples.shape[0], dtype=torch.int64)
    for camera in cameras:
        alpha, cumulative, front, thickness = opacity_in_front(
            gaussians, renderer, camera, layer=layer, front_radii=front_radii
        )
        row, col, z, inside = _pixel_lookup(camera, samples)
        n_layers = cumulative.shape[0] - 1
        t = ((z + depth_tolerance - front) / thickness).clamp(0.0, float(n_layers))
        j = t.floor().long().clamp(max=n_layers - 1)
        below = cumulative[j, row, col]
        above = cumulative[j + 1, row, col]
        accumulated = below + (t - j) * (above - below)
        covered = alpha[row, col] >= alpha_threshold
        behind = accumulated >= surface_fraction * alpha[row, col]
        votes += (inside & covered & behind).long()
    return votes


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
    agreement: float = 1.0,
    widen: float = 0.0,
    box: Box | None = None,
) -> CarveResult:
    """Carve one object from its frame-0 Gaussians (means [G, 3] m, radii [G] m, colors [G, 3],
    opacities [G]) and the recorded masks; ``options`` is a GaussiansLifterOptions; a sample
    must pass the virtual-view test in at least the fraction ``agreement`` of those views, in
    which the Gaussians are rendered with radii widened by ``widen`` m (``widened_radii``).
    Samples are drawn in ``box`` (default: around the Gaussians, ``object_box``)."""
    if box is None:
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
        scene.cameras_at(0),
        masks,
        dilation=options.mask_dilation_px,
        views_missed=options.mask_views_missed,
    )
    if options.virtual_views:
        kept = _virtual_view_test(
            samples, kept, means, radii, colors, opacities, renderer, options, agreement, widen
        )
    return CarveResult(box, samples, kept)


def _virtual_view_test(
    samples, kept, means, radii, colors, opacities, renderer, options, agreement, widen
) -> Tensor:
    """``kept`` narrowed to the samples that the Gaussians, rendered from
    ``options.virtual_views`` virtual cameras around them (radii widened by ``widen`` m), show
    inside in at least the fraction ``agreement`` of the views."""
    drawn = widened_radii(radii.float(), widen) if widen > 0 else radii.float()
    centre = 0.5 * (means.min(dim=0).values + means.max(dim=0).values)
    reach = float((means - centre).norm(dim=1).max()) + 3.0 * float(drawn.max())
    single = GaussianFrames(
        means[None].float(),
        drawn[None],
        colors.float(),
        opacities.float(),
        torch.ones(means.shape[0], dtype=torch.int64),
    )
    tolerance = 0.0 if options.depth_tolerance is None else options.depth_tolerance
    # the surface is crossed half-way through the first layer of Gaussians, which stops about as
    # much light as one typical Gaussian: half of the median opacity (0.5 for opaque Gaussians
    # seeded from points; trained Gaussians that fill the volume with semi-transparent ones
    # reach half the ray's opacity only a layer or more inside)
    fraction = (
        0.5 * float(opacities.float().median())
        if options.surface_fraction is None
        else options.surface_fraction
    )
    views = virtual_cameras(
        centre, reach, n=options.virtual_views, resolution=options.virtual_resolution
    )
    candidates = torch.nonzero(kept).squeeze(1)  # only test what the masks left
    votes = depth_consistent(
        samples[candidates],
        single,
        renderer,
        views,
        alpha_threshold=options.alpha_threshold,
        depth_tolerance=tolerance,
        layer=0.5 * options.cell_size,
        surface_fraction=fraction,
        front_radii=radii.float() if widen > 0 else None,
    )
    # a view that sees into the object through a gap of the reconstruction (say its unobserved
    # underside) is outvoted by the others
    ok = votes >= math.ceil(agreement * len(views) - 1e-9)
    return torch.zeros_like(kept).index_fill(0, candidates[ok], True)


def recorded_masks(scene) -> list[Tensor]:
    """Frame-0 instance masks, [H, W] int64 each, of the cameras that recorded frame 0
    (``scene.cameras_at(0)``, in cameras.json order)."""
    return [torch.from_numpy(scene.mask(c.id, 0).astype(np.int64)) for c in scene.cameras_at(0)]
