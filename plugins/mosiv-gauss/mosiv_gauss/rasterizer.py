"""A differentiable pure-torch rasterizer of isotropic 3D Gaussians (renderer ``gauss-torch``).

Image model, for one camera (pixel centres at integer + 0.5, OpenCV convention):

1. Projection. A Gaussian with centre ``x`` (m) and world standard deviation ``r`` (m) lands at
   ``(u, v)`` with camera depth ``z``; its footprint is an axis-aligned 2D Gaussian with standard
   deviations ``s_u = r fx / z`` and ``s_v = r fy / z`` (pixels). Centres with ``z < near`` are
   skipped.
2. Per-pixel opacity. ``alpha_g(p) = min(o_g exp(-q / 2), max_alpha)`` with the squared
   Mahalanobis distance ``q = (p_u - u)^2 / s_u^2 + (p_v - v)^2 / s_v^2``, and ``alpha_g(p) = 0``
   where ``q > cutoff_sigma^2``: the cut-off is part of the model, so splitting the image into
   tiles changes nothing.
3. Front-to-back compositing over Gaussians sorted by depth (3D Gaussian splatting, Kerbl et
   al. 2023, eq. 3): ``w_g = alpha_g T_g`` with ``T_g = prod_{h before g} (1 - alpha_h)``;
   ``rgb = sum_g w_g c_g (+ (1 - alpha) * background)``, ``alpha = sum_g w_g``,
   ``depth = sum_g w_g z_g`` and ``object_alpha[k] = sum_{g of object k+1} w_g``.

``depth`` is the *unnormalised* expected depth (m): it is 0 where nothing is drawn and shrinks
with coverage; divide by ``alpha`` where ``alpha > 0`` for the depth of the visible surface.

Bounded memory: the image is cut into square tiles, each tile only evaluates the Gaussians whose
cut-off ellipse reaches one of its pixel centres (a 3D-Gaussian-splatting-style duplicate-and-
sort of (tile, Gaussian) pairs), tiles are rendered in groups of at most ``pixel_chunk`` pixels,
and a group walks its depth-sorted Gaussians in slices of at most ``pair_chunk`` (pixel,
Gaussian) pairs, carrying the transmittance from slice to slice. With ``checkpoint`` each slice's
per-pixel values are recomputed in the backward pass instead of being stored.
"""

from __future__ import annotations

import bisect
from dataclasses import dataclass

import torch
from torch.utils.checkpoint import checkpoint

from mosiv_framework.interfaces import Renderer, RenderOutput
from mosiv_framework.types import GaussianFrames
from mosiv_gauss.options import TorchRasterizerOptions

Tensor = torch.Tensor

#: slack (pixels) added to each Gaussian's cut-off box when assigning it to tiles, so rounding
#: never drops a pixel that the exact ellipse test of ``_composite_slice`` would keep
_TILE_MARGIN_PX = 1e-3

#: leading feature channels composited per pixel: r, g, b, depth, 1 (alpha); object channels follow
_RGB, _DEPTH, _ALPHA, _OBJECTS = slice(0, 3), 3, 4, 5


@dataclass
class RasterStats:
    """Work done by one render, for profiling and for tests of the memory bound.

    n_gaussians: Gaussians given; n_visible: those in front of the near plane that reach at
    least one pixel; n_tile_pairs: (tile, Gaussian) overlaps after culling; n_steps: slices
    evaluated; n_evaluated: (pixel, Gaussian) pairs evaluated in all, padding included;
    max_step_pairs: the most (pixel, Gaussian) pairs evaluated in one slice.
    """

    n_gaussians: int = 0
    n_visible: int = 0
    n_tile_pairs: int = 0
    n_steps: int = 0
    n_evaluated: int = 0
    max_step_pairs: int = 0


@dataclass
class ScreenGaussians:
    """Visible Gaussians in the image, sorted front to back (index order = depth order).

    uv: [N, 2] centre (px); inv_var: [N, 2] 1/s_u^2, 1/s_v^2 (1/px^2); extent: [N, 2] half
    width and height of the cut-off box (px, no gradient); opacity: [N]; features: [N, 5 + K]
    the composited channels (r, g, b, depth z in m, 1, one-hot object id).
    """

    uv: Tensor
    inv_var: Tensor
    extent: Tensor
    opacity: Tensor
    features: Tensor


def project_isotropic(
    means: Tensor,
    radii: Tensor,
    colors: Tensor,
    opacities: Tensor,
    object_ids: Tensor,
    camera,
    *,
    n_objects: int,
    options: TorchRasterizerOptions,
) -> ScreenGaussians:
    """Project one frame's isotropic Gaussians (means [G, 3] m, radii [G] m) through ``camera``.

    Gaussians behind ``options.near`` or with a non-positive radius are dropped *before* any
    division by depth, so no NaN or inf can leak into the gradients of the others.
    """
    with torch.no_grad():
        z_all = camera.world_to_camera_points(means.detach())[:, 2]
        keep = (z_all >= options.near) & (radii.detach() > 0)
        order = torch.argsort(z_all[keep], stable=True)  # front to back
        index = torch.nonzero(keep).squeeze(1)[order]
    uv, z = camera.project(means[index])
    radius = radii[index]
    # footprint std-devs s = r f / z (pixels), one per image axis
    s_u = radius * camera.fx / z
    s_v = radius * camera.fy / z
    inv_var = torch.stack([s_u.reciprocal().square(), s_v.reciprocal().square()], dim=-1)
    extent = options.cutoff_sigma * torch.stack([s_u, s_v], dim=-1).detach()
    one_hot = torch.nn.functional.one_hot(object_ids[index] - 1, n_objects).to(means.dtype)
    ones = torch.ones_like(z).unsqueeze(1)
    features = torch.cat([colors[index].to(means.dtype), z.unsqueeze(1), ones, one_hot], dim=1)
    return ScreenGaussians(uv, inv_var, extent, opacities[index].to(means.dtype), features)


@dataclass
class TileBins:
    """(tile, Gaussian) overlaps grouped by tile, each tile's Gaussians front to back.

    gaussian: [P] screen-Gaussian index of each pair, sorted by tile then depth;
    start, count: [n_tiles] where each tile's pairs begin in ``gaussian`` and how many it has.
    """

    gaussian: Tensor
    start: Tensor
    count: Tensor


def bin_to_tiles(
    screen: ScreenGaussians, *, width: int, height: int, tile: int, tiles_x: int
) -> TileBins:
    """Assign each screen Gaussian to every tile in which its cut-off box covers a pixel centre."""
    device = screen.uv.device
    n_tiles = tiles_x * ((height + tile - 1) // tile)
    with torch.no_grad():
        uv = screen.uv.detach().double()
        ext = screen.extent.double() + _TILE_MARGIN_PX
        size = torch.tensor([width, height], dtype=torch.float64, device=device)
        # pixel column/row i is covered when |i + 0.5 - u| <= extent
        lo = torch.ceil(uv - ext - 0.5)
        hi = torch.floor(uv + ext - 0.5)
        overlaps = ((hi >= 0) & (lo <= size - 1) & (lo <= hi)).all(dim=1)
        lo = torch.maximum(lo, torch.zeros_like(lo))
        hi = torch.minimum(hi, size - 1)
        t_lo = torch.div(lo, tile, rounding_mode="floor").long()
        t_hi = torch.div(hi, tile, rounding_mode="floor").long()
        span = (t_hi - t_lo + 1).clamp(min=0)
        n_per = torch.where(overlaps, span[:, 0] * span[:, 1], torch.zeros_like(span[:, 0]))
        # duplicate each Gaussian once per covered tile (pairs come out in depth order)
        gauss = torch.repeat_interleave(torch.arange(len(n_per), device=device), n_per)
        first = torch.cumsum(n_per, 0) - n_per
        k = torch.arange(len(gauss), device=device) - first[gauss]
        cols = span[gauss, 0]
        tile_x = t_lo[gauss, 0] + k % cols
        tile_y = t_lo[gauss, 1] + torch.div(k, cols, rounding_mode="floor")
        tile_id = tile_y * tiles_x + tile_x
        # a stable sort by tile keeps each tile's Gaussians in depth order
        tile_id, perm = torch.sort(tile_id, stable=True)
        count = torch.bincount(tile_id, minlength=n_tiles)
        start = torch.cumsum(count, 0) - count
    return TileBins(gauss[perm], start, count)


def _composite_slice(
    pix: Tensor,
    uv: Tensor,
    inv_var: Tensor,
    opacity: Tensor,
    features: Tensor,
    valid: Tensor,
    trans: Tensor,
    cutoff2: float,
    max_alpha: float,
) -> tuple[Tensor, Tensor]:
    """Composite one depth-ordered slice of Gaussians over a group of tiles (module eq. 2-3).

    pix [n, P, 2] pixel centres; uv, inv_var [n, S, 2], opacity [n, S], features [n, S, F] and
    valid [n, S] the slice's Gaussians per tile; trans [n, P] transmittance in front of the
    slice. Returns the slice's composited features [n, P, F] and the transmittance behind it.
    """
    d = pix.unsqueeze(1) - uv.unsqueeze(2)  # [n, S, P, 2]
    q = (d.square() * inv_var.unsqueeze(2)).sum(-1)  # squared Mahalanobis distance
    inside = (q <= cutoff2) & valid.unsqueeze(2)
    alpha = (opacity.unsqueeze(2) * torch.exp(-0.5 * q)).clamp(max=max_alpha)
    alpha = torch.where(inside, alpha, torch.zeros_like(alpha))
    keep = 1.0 - alpha
    # exclusive cumulative product: transmittance in front of each Gaussian of the slice
    through = torch.cumprod(keep, dim=1)
    t_before = torch.cat([torch.ones_like(through[:, :1]), through[:, :-1]], dim=1)
    weight = alpha * t_before * trans.unsqueeze(1)
    out = torch.einsum("nsp,nsf->npf", weight, features)
    return out, trans * through[:, -1]


def _render_group(
    screen: ScreenGaussians,
    count: Tensor,
    start: Tensor,
    pair_gaussian: Tensor,
    pix: Tensor,
    *,
    pair_chunk: int,
    cutoff2: float,
    max_alpha: float,
    use_checkpoint: bool,
    stats: RasterStats,
) -> Tensor:
    """Composite a group of tiles, sorted by ascending Gaussian count, slice by slice.

    count, start [n]: each tile's number of Gaussians and first entry in ``pair_gaussian``;
    pix [n, P, 2]: the tiles' pixel centres. A slice covers only the tiles that still have
    Gaussians at its depth slots (a suffix of the group, since counts ascend) and at most
    ``pair_chunk`` (pixel, Gaussian) pairs. Returns the composited features [n, P, F].
    """
    counts = count.tolist()
    n, px_per_tile = pix.shape[0], pix.shape[1]
    trans = torch.ones(n, px_per_tile, dtype=pix.dtype, device=pix.device)
    acc = pix.new_zeros(n, px_per_tile, screen.features.shape[1])
    finished = []  # composited features of tiles whose Gaussians are all used, in group order
    lo = s0 = 0  # first tile still active; first depth slot not composited yet
    while s0 < counts[-1]:
        first = bisect.bisect_right(counts, s0)  # tiles with count <= s0 are complete
        if first > lo:
            finished.append(acc[: first - lo])
            acc, trans, lo = acc[first - lo :], trans[first - lo :], first
        active = n - lo
        s1 = min(s0 + max(1, pair_chunk // (active * px_per_tile)), counts[-1])
        slots = torch.arange(s0, s1, device=pix.device)
        valid = slots.unsqueeze(0) < count[lo:].unsqueeze(1)
        pair = torch.where(valid, start[lo:].unsqueeze(1) + slots.unsqueeze(0), 0)
        idx = pair_gaussian[pair]  # [active, S] screen-Gaussian per (tile, slot)
        args = (
            pix[lo:],
            screen.uv[idx],
            screen.inv_var[idx],
            screen.opacity[idx],
            screen.features[idx],
            valid,
            trans,
            cutoff2,
            max_alpha,
        )
        if use_checkpoint:
            out, trans = checkpoint(_composite_slice, *args, use_reentrant=False)
        else:
            out, trans = _composite_slice(*args)
        acc = acc + out
        step_pairs = active * (s1 - s0) * px_per_tile
        stats.n_steps += 1
        stats.n_evaluated += step_pairs
        stats.max_step_pairs = max(stats.max_step_pairs, step_pairs)
        s0 = s1
    finished.append(acc)
    return torch.cat(finished)


def _tile_pixels(tile_ids: Tensor, *, tile: int, tiles_x: int, dtype, device) -> Tensor:
    """[n, tile*tile, 2] pixel-centre coordinates (u, v) of the given tiles, row-major inside."""
    local = torch.arange(tile * tile, device=device)
    row = torch.div(local, tile, rounding_mode="floor")
    col = local % tile
    ty = torch.div(tile_ids, tiles_x, rounding_mode="floor")
    tx = tile_ids % tiles_x
    u = (tx.unsqueeze(1) * tile + col.unsqueeze(0)).to(dtype) + 0.5
    v = (ty.unsqueeze(1) * tile + row.unsqueeze(0)).to(dtype) + 0.5
    return torch.stack([u, v], dim=-1)


def rasterize(
    gaussians: GaussianFrames,
    camera,
    *,
    frame: int = 0,
    n_objects: int,
    options: TorchRasterizerOptions | None = None,
    background: Tensor | None = None,
) -> tuple[RenderOutput, RasterStats]:
    """Render frame ``frame`` of ``gaussians`` through ``camera``; see the module docstring.

    ``background`` (a [3] colour or an [H, W, 3] image, linear RGB) overrides
    ``options.background``. Outputs have the dtype and device of ``gaussians.means``. When no
    Gaussian reaches the image the outputs are constant (zeros, or the background) and carry no
    autograd graph: their gradient with respect to the Gaussians is zero.
    """
    opts = options or TorchRasterizerOptions()
    _check_inputs(gaussians, frame=frame, n_objects=n_objects)
    means = gaussians.means[frame]
    dtype, device = means.dtype, means.device
    width, height, tile = camera.width, camera.height, opts.tile_size
    tiles_x = (width + tile - 1) // tile

    screen = project_isotropic(
        means,
        gaussians.radii[frame],
        gaussians.colors,
        gaussians.opacities,
        gaussians.object_ids,
        camera,
        n_objects=n_objects,
        options=opts,
    )
    bins = bin_to_tiles(screen, width=width, height=height, tile=tile, tiles_x=tiles_x)
    stats = RasterStats(n_gaussians=int(means.shape[0]), n_tile_pairs=int(bins.gaussian.numel()))
    stats.n_visible = int(torch.unique(bins.gaussian).numel())

    if _use_warp(opts.backend, device):
        image = _composite_warp(screen, bins, width=width, height=height, opts=opts, stats=stats)
    else:
        image = _composite_torch(screen, bins, width=width, height=height, opts=opts, stats=stats)
    alpha = image[..., _ALPHA]
    rgb = image[..., _RGB]
    bg = background if background is not None else opts.background
    if bg is not None:
        bg = torch.as_tensor(bg, dtype=dtype, device=device)
        if bg.shape not in ((3,), (height, width, 3)):
            raise ValueError(
                f"background has shape {list(bg.shape)}; expected [3] (a colour) or "
                f"[{height}, {width}, 3] (an image of camera {camera.id!r})"
            )
        rgb = rgb + (1.0 - alpha).unsqueeze(-1) * bg
    output = RenderOutput(
        rgb=rgb,
        alpha=alpha,
        depth=image[..., _DEPTH],
        object_alpha=image[..., _OBJECTS:].permute(2, 0, 1),
    )
    return output, stats


def _use_warp(backend: str, device: torch.device) -> bool:
    """Whether to composite with the Warp kernels (see TorchRasterizerOptions.backend)."""
    if backend != "auto":
        return backend == "warp"
    if device.type != "cuda":
        return False
    import importlib.util

    return importlib.util.find_spec("warp") is not None


def _composite_torch(screen, bins, *, width, height, opts, stats) -> Tensor:
    """Composited features [height, width, F] by torch slices (the reference backend)."""
    dtype, device = screen.uv.dtype, screen.uv.device
    tile = opts.tile_size
    tiles_x, tiles_y = (width + tile - 1) // tile, (height + tile - 1) // tile
    n_feat = screen.features.shape[1]
    px_per_tile = tile * tile
    # busy tiles, fewest Gaussians first: tiles grouped together have similar counts, so little
    # work is wasted padding every tile of a group to the group's largest count
    active = torch.nonzero(bins.count).squeeze(1)
    active = active[torch.argsort(bins.count[active], stable=True)]
    tiles_per_group = max(1, opts.pixel_chunk // px_per_tile)
    use_checkpoint = opts.checkpoint and torch.is_grad_enabled()
    done_tiles, done_values = [], []
    for g0 in range(0, len(active), tiles_per_group):
        tile_ids = active[g0 : g0 + tiles_per_group]
        pix = _tile_pixels(tile_ids, tile=tile, tiles_x=tiles_x, dtype=dtype, device=device)
        done_tiles.append(tile_ids)
        done_values.append(
            _render_group(
                screen,
                bins.count[tile_ids],
                bins.start[tile_ids],
                bins.gaussian,
                pix,
                pair_chunk=opts.pair_chunk,
                cutoff2=float(opts.cutoff_sigma) ** 2,
                max_alpha=float(opts.max_alpha),
                use_checkpoint=use_checkpoint,
                stats=stats,
            )
        )

    image = torch.zeros(tiles_x * tiles_y, px_per_tile, n_feat, dtype=dtype, device=device)
    if done_tiles:
        image = image.index_copy(0, torch.cat(done_tiles), torch.cat(done_values))
    # [tiles_y, tiles_x, row, col, F] -> [rows, cols, F], cropped to the real image
    image = image.reshape(tiles_y, tiles_x, tile, tile, n_feat).permute(0, 2, 1, 3, 4)
    image = image.reshape(tiles_y * tile, tiles_x * tile, n_feat)[:height, :width]
    return image


def _composite_warp(screen, bins, *, width, height, opts, stats) -> Tensor:
    """Composited features [height, width, F] by the Warp kernels (``warp_composite``)."""
    from mosiv_gauss.warp_composite import composite  # warp-lang is needed only here

    tile = opts.tile_size
    if bins.gaussian.numel() == 0:  # nothing reaches the image: constant, no graph
        return screen.uv.new_zeros(height, width, screen.features.shape[1])
    stats.n_steps = 1
    stats.n_evaluated = int((bins.count * tile * tile).sum())
    stats.max_step_pairs = stats.n_evaluated
    return composite(
        screen,
        bins,
        width=width,
        height=height,
        tile=tile,
        tiles_x=(width + tile - 1) // tile,
        cutoff2=float(opts.cutoff_sigma) ** 2,
        max_alpha=float(opts.max_alpha),
    )


def _check_inputs(gaussians: GaussianFrames, *, frame: int, n_objects: int) -> None:
    """Raise ValueError naming the field when the Gaussians cannot be rendered as given."""
    if gaussians.means.ndim != 3 or gaussians.means.shape[2] != 3:
        raise ValueError(
            f"GaussianFrames.means must be [T, G, 3], got {list(gaussians.means.shape)}"
        )
    t, g = gaussians.means.shape[0], gaussians.means.shape[1]
    expected = {
        "radii": (gaussians.radii, (t, g)),
        "colors": (gaussians.colors, (g, 3)),
        "opacities": (gaussians.opacities, (g,)),
        "object_ids": (gaussians.object_ids, (g,)),
    }
    for name, (tensor, shape) in expected.items():
        if tuple(tensor.shape) != shape:
            raise ValueError(
                f"GaussianFrames.{name} must have shape {list(shape)} for T={t}, G={g}; "
                f"got {list(tensor.shape)} (this renderer draws isotropic Gaussians)"
            )
    if not 0 <= frame < t:
        raise ValueError(f"frame={frame} is out of range: the Gaussians have frames 0..{t - 1}")
    if isinstance(n_objects, bool) or not isinstance(n_objects, int) or n_objects < 1:
        raise ValueError(f"n_objects={n_objects!r} must be an integer >= 1")
    if g and (gaussians.object_ids.min() < 1 or gaussians.object_ids.max() > n_objects):
        lo, hi = int(gaussians.object_ids.min()), int(gaussians.object_ids.max())
        raise ValueError(
            f"GaussianFrames.object_ids span {lo}..{hi}, outside the object ids 1..{n_objects} "
            f"(n_objects={n_objects})"
        )


class TorchRasterizer(Renderer):
    """The ``gauss-torch`` renderer: :func:`rasterize` with fixed options.

    ``last_stats`` holds the :class:`RasterStats` of the most recent render.
    """

    def __init__(self, options: TorchRasterizerOptions | None = None) -> None:
        self.options = options or TorchRasterizerOptions()
        self.last_stats: RasterStats | None = None

    def render(
        self,
        gaussians: GaussianFrames,
        camera,
        *,
        frame: int = 0,
        n_objects: int,
        background: Tensor | None = None,
    ) -> RenderOutput:
        output, self.last_stats = rasterize(
            gaussians,
            camera,
            frame=frame,
            n_objects=n_objects,
            options=self.options,
            background=background,
        )
        return output
