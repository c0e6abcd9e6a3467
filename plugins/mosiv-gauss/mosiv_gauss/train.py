"""Training of the dynamic Gaussians (paper eq. 2) with object-aware mask supervision.

Per step, a few (frame, camera) images are rendered with the torch rasterizer over the static
background of their camera and compared with the video:

    L = L1(I_hat, I) + lambda_ssim (1 - SSIM(I_hat, I))              (eq. 2, photometric)
        + lambda_mask mean_k L1(A_k, M_k)                           (per-object silhouettes)
        + lambda_mask_coarse mean_k L1(P(A_k), P(M_k))              (the same, block means)
        + lambda_radius mean(r_t) / voxel                           (eq. 2's |r_t|_1)

where A_k is the rendered alpha of object k's Gaussians (occlusion included, it is composited)
and M_k the instance mask of object k. The mask term is what keeps a Gaussian's object id
meaningful through contact: a Gaussian of object 1 that drifts into object 2 is drawn into A_1
where M_1 is 0 and is pushed back out. P averages over ``mask_pool`` x ``mask_pool`` pixel
blocks: where a body spread thinner than a pixel shows as scattered dots (sand or a liquid
drawn as its particles), the per-pixel L1 is lowest with nothing drawn at all (every gap costs
what a dot gains), while the block means ask for a faint cover of the right density where the
dots are. On a solid body the two terms agree.

Before the photometric steps, ``fit_motion_prior`` fits the deformation networks to the
per-object visual-hull centroid tracks, so training starts with every object roughly where the
video shows it (photometric gradients only reach a few pixels). Densification clones or splits
Gaussians whose mean positional gradient is large and pruning drops nearly transparent ones, as
in 3D Gaussian splatting (Kerbl et al. 2023); Adam moments follow the Gaussians they belong to.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import kornia
import torch

from mosiv_framework.types import GaussianFrames
from mosiv_gauss.dynamic_options import DynamicGaussOptions
from mosiv_gauss.model import DynamicGaussians
from mosiv_gauss.options import TorchRasterizerOptions
from mosiv_gauss.rasterizer import rasterize
from mosiv_gauss.step_guard import non_finite_parts, skip_or_stop

Tensor = torch.Tensor

#: radius of a fresh Gaussian, in voxels of the hull grid (std-dev: 3 sigma spans 3 voxels)
INIT_RADIUS_VOXELS = 0.5
#: Gaussians wider than this (voxels) are split when densified, narrower ones cloned
SPLIT_RADIUS_VOXELS = 0.75
#: a split replaces a Gaussian by two whose radius is this many times smaller (3DGS uses 1.6)
SPLIT_SHRINK = 1.6
#: each object keeps at least this many Gaussians however transparent they become
MIN_PER_OBJECT = 4
#: learning rates decay exponentially to this fraction of their start over training
FINAL_LR_FRACTION = 0.1
#: window of kornia's SSIM (pixels)
SSIM_WINDOW = 11


@dataclass
class TrainingData:
    """What training compares against, on the training device.

    rgb [T, C, H, W, 3] in [0, 1]; masks [T, C, K, H, W] in {0, 1}; cameras: C cameras in the
    order of the image stacks; background [C, H, W, 3]; voxel_size (m) of the hull grid;
    tracks [T, K, 3] (m) visual-hull centroids and track_valid [T, K] where the hull is
    non-empty (``init.HullInit``), for the track anchor (None: no anchor); hulls[t][k] [N, 3]
    (m) voxel centres of object k+1's hull at frame t (``init.HullInit.hulls``), for the hull
    term (None: no hull term); views [T, C] bool: the (frame, camera) views the scene
    recorded (None: all; the others' images are black and never sampled).
    """

    rgb: Tensor
    masks: Tensor
    cameras: list
    background: Tensor
    voxel_size: float
    tracks: Tensor | None = None
    track_valid: Tensor | None = None
    hulls: list[list[Tensor]] | None = None
    views: Tensor | None = None

    @property
    def n_frames(self) -> int:
        return self.rgb.shape[0]

    @property
    def n_objects(self) -> int:
        return self.masks.shape[2]


@dataclass
class TrainingHistory:
    """Loss per step, Gaussian count after each densification, and the final background."""

    loss: list[float] = field(default_factory=list)
    motion_loss: list[float] = field(default_factory=list)
    n_gaussians: list[int] = field(default_factory=list)
    background: Tensor | None = None
    #: steps skipped because their loss or a gradient was not finite
    skipped_steps: list[int] = field(default_factory=list)


def estimate_background(rgb: Tensor, mask_ids: Tensor, views: Tensor | None = None) -> Tensor:
    """Static background per camera [C, H, W, 3]: the per-pixel median over the frames where no
    object covers the pixel; pixels covered in every frame take the median of the camera's
    background pixels. rgb [T, C, H, W, 3]; mask_ids [T, C, H, W] (0 = background); views
    [T, C] bool, the recorded views (None: all)."""
    free = mask_ids == 0
    if views is not None:
        free = free & views[:, :, None, None]
    free = free.unsqueeze(-1).expand_as(rgb)
    # NaN marks covered samples; nanmedian ignores them
    values = torch.where(free, rgb, torch.full_like(rgb, float("nan")))
    median = values.nanmedian(dim=0).values  # [C, H, W, 3]
    for c in range(median.shape[0]):
        hole = torch.isnan(median[c])
        if hole.any():
            fill = values[:, c].reshape(-1, 3).nanmedian(dim=0).values
            fill = torch.nan_to_num(fill, nan=0.5)  # a camera that never sees background
            median[c] = torch.where(hole, fill.expand_as(median[c]), median[c])
    return median


def view_loss(rgb: Tensor, object_alpha: Tensor, target: Tensor, masks: Tensor, opts) -> Tensor:
    """Eq. 2's photometric terms plus the per-object mask L1 (and, when
    ``opts.lambda_mask_coarse`` is on, its block-mean version), mean over a batch of images.

    rgb, target [B, H, W, 3]; object_alpha, masks [B, K, H, W].
    """
    l1 = (rgb - target).abs().mean()
    pred = rgb.permute(0, 3, 1, 2)
    true = target.permute(0, 3, 1, 2)
    structural = 1.0 - kornia.metrics.ssim(pred, true, SSIM_WINDOW).mean()
    mask = (object_alpha - masks).abs().mean()
    loss = l1 + opts.lambda_ssim * structural + opts.lambda_mask * mask
    if opts.lambda_mask_coarse > 0:
        loss = loss + opts.lambda_mask_coarse * coarse_mask_l1(object_alpha, masks, opts.mask_pool)
    return loss


def coarse_mask_l1(object_alpha: Tensor, masks: Tensor, pool: int) -> Tensor:
    """Mean L1 between the ``pool`` x ``pool`` block means of the rendered per-object alphas and
    of the masks, both [B, K, H, W] (a partial block at the border is averaged over the pixels
    it has)."""

    def blocks(x: Tensor) -> Tensor:
        return torch.nn.functional.avg_pool2d(x, pool, stride=pool, ceil_mode=True)

    return (blocks(object_alpha) - blocks(masks)).abs().mean()


def sample_views(
    data: TrainingData, n: int, order: list[int], generator: torch.Generator | None
) -> list[tuple[int, int]]:
    """The next ``n`` (frame, camera) pairs: every recorded view once per epoch, in a fresh
    random order each epoch. ``order`` holds the rest of the current epoch and is consumed."""
    n_cams = len(data.cameras)
    total = data.n_frames * n_cams if data.views is None else int(data.views.sum())
    batch = []
    while len(batch) < min(n, total):
        if not order:  # a new epoch: the recorded views' flat indices, shuffled
            shuffled = torch.randperm(total, generator=generator)
            if data.views is not None:
                shuffled = torch.nonzero(data.views.reshape(-1).cpu()).squeeze(1)[shuffled]
            order.extend(shuffled.tolist())
        index = order.pop()
        batch.append((index // n_cams, index % n_cams))
    return batch


def batch_view_loss(
    means: Tensor,
    radii: Tensor,
    colors: Tensor,
    opacities: Tensor,
    object_ids: Tensor,
    frames: list[int],
    batch: list[tuple[int, int]],
    data: TrainingData,
    background: Tensor,
    opts: DynamicGaussOptions,
) -> Tensor:
    """``view_loss`` of the Gaussians (means [F, G, 3] m and radii [F, G] m at ``frames``)
    drawn through the (frame, camera) views of ``batch`` over their cameras' background."""
    raster = TorchRasterizerOptions(
        tile_size=opts.tile_size, checkpoint=opts.raster_checkpoint, backend=opts.raster_backend
    )
    rendered, alphas = [], []
    for t, c in batch:
        i = frames.index(t)
        gauss = GaussianFrames(means[i : i + 1], radii[i : i + 1], colors, opacities, object_ids)
        out, _ = rasterize(
            gauss,
            data.cameras[c],
            n_objects=data.n_objects,
            options=raster,
            background=background[c].clamp(0.0, 1.0),
        )
        rendered.append(out.rgb)
        alphas.append(out.object_alpha)
    ts, cs = [t for t, _ in batch], [c for _, c in batch]
    return view_loss(
        torch.stack(rendered), torch.stack(alphas), data.rgb[ts, cs], data.masks[ts, cs], opts
    )


def _hull_chamfer(points: Tensor, hull: Tensor, *, free: float = 0.0) -> Tensor:
    """Symmetric Chamfer (squared distances, input units) between two point sets, each
    distance less ``free`` (never below 0)."""
    d = torch.cdist(points, hull)
    if free > 0:
        d = (d - free).clamp(min=0.0)
    d = d.square()
    return d.min(dim=1).values.mean() + d.min(dim=0).values.mean()


def track_offsets(
    means: Tensor, frames: list[int], object_ids: Tensor, data: TrainingData
) -> list[tuple[int, int, Tensor]]:
    """(frame, object id, distance in hull voxels) between each object's mean Gaussian centre
    in ``means`` [len(frames), G, 3] and its visual-hull centroid, for the ``frames`` and
    objects whose hull is non-empty there (differentiable)."""
    out = []
    for i, t in enumerate(frames):
        for k in range(data.n_objects):
            mine = object_ids == k + 1
            if bool(data.track_valid[t, k]) and bool(mine.any()):
                offset = (means[i, mine].mean(dim=0) - data.tracks[t, k]).norm()
                out.append((t, k + 1, offset / data.voxel_size))
    return out


def track_loss(
    means: Tensor, frames: list[int], object_ids: Tensor, data: TrainingData, *, tolerance: float
) -> Tensor:
    """Mean squared excess (voxels^2) of the distance between each object's mean Gaussian
    centre and its visual-hull centroid over ``tolerance`` voxels, over the ``frames`` of
    ``means`` [len(frames), G, 3] and the objects whose hull is non-empty there; 0 when there
    is nothing to compare. The tolerance leaves the hull's own bias alone (a hull carved from
    cameras above the object reaches further down than the object), so the term only acts on
    an object drifting away."""
    total = means.new_zeros(())
    offsets = track_offsets(means, frames, object_ids, data)
    for _, _, offset in offsets:
        total = total + (offset - tolerance).clamp(min=0.0).square()
    return total / max(len(offsets), 1)


#: at most this many Gaussians per object and frame enter the hull term (random subset)
HULL_TERM_POINTS = 2048


def hull_loss(
    means: Tensor,
    frames: list[int],
    object_ids: Tensor,
    hulls: list[list[Tensor]],
    *,
    voxel_size: float,
    generator: torch.Generator | None = None,
) -> Tensor:
    """Mean over (frame, object) pairs with a non-empty hull of the symmetric Chamfer
    (voxels^2) between the object's Gaussian centres ``means`` [len(frames), G, 3] (m) and
    its hull points, each distance less one voxel (a voxel-sized hull cannot place a point
    closer than that); 0 when there is nothing to compare."""
    total = means.new_zeros(())
    count = 0
    for i, t in enumerate(frames):
        for k, hull in enumerate(hulls[t]):
            mine = torch.nonzero(object_ids == k + 1).squeeze(1)
            if not len(hull) or not len(mine):
                continue
            if len(mine) > HULL_TERM_POINTS:
                pick = torch.randperm(len(mine), generator=generator)[:HULL_TERM_POINTS]
                mine = mine[pick.to(mine.device)]
            points = means[i, mine] / voxel_size
            total = total + _hull_chamfer(points, hull.to(means) / voxel_size, free=1.0)
            count += 1
    return total / max(count, 1)


def shape_terms(
    means: Tensor,
    radii: Tensor,
    frames: list[int],
    object_ids: Tensor,
    data: TrainingData,
    opts: DynamicGaussOptions,
    *,
    generator: torch.Generator | None = None,
) -> Tensor:
    """The geometric terms shared by training and the per-frame refinement: eq. 2's radius
    penalty (mean radius in hull voxels) plus the hull term when ``opts.lambda_hull`` is on.
    means [F, G, 3] and radii [F, G] (m) at ``frames``."""
    total = opts.lambda_radius * radii.mean() / data.voxel_size
    if opts.lambda_hull > 0 and data.hulls is not None:
        shape = hull_loss(
            means, frames, object_ids, data.hulls, voxel_size=data.voxel_size, generator=generator
        )
        total = total + opts.lambda_hull * shape
    return total


def fit_motion_prior(
    model: DynamicGaussians,
    tracks: Tensor,
    *,
    iterations: int,
    lr: float,
    voxel_size: float,
    hulls: list[list[Tensor]] | None = None,
    progress: bool = False,
) -> list[float]:
    """Fit the deformation so each object's Gaussians follow its visual hulls over time.

    tracks [T, K, 3] (m): hull centroids. Target of Gaussian g of object k at frame t:
    mu_g + track_k(t) - track_k(0), a translation per object (first half of the steps, and a
    weak anchor after). ``hulls[t][k]`` [N, 3] voxel centres of object k+1's hull at frame t:
    in the second half the symmetric Chamfer distance between each object's deformed Gaussians
    and its hull is added, so an object that flattens on impact is followed non-rigidly. Only
    the networks move. Returns the loss per step (voxels^2).
    """
    if iterations == 0:
        return []
    frames = list(range(model.n_frames))
    shift = tracks - tracks[:1]  # [T, K, 3]
    target = model.means.detach().unsqueeze(0) + shift[:, model.object_ids - 1]
    opt = torch.optim.Adam(model.network_parameters(), lr=lr)
    history: list[float] = []
    skipped: list[int] = []
    bar = _bar(range(iterations), progress, "gauss motion prior")
    for step in bar:
        means, _ = model.at(frames)
        offset = ((means - target) / voxel_size).square().sum(-1).mean()
        loss = offset
        if hulls is not None and step >= iterations // 2:
            loss = 0.1 * offset
            for t in frames:
                for k in range(model.n_objects):
                    hull = hulls[t][k]
                    mine = model.object_ids == k + 1
                    if len(hull) and mine.any():
                        loss = loss + _hull_chamfer(
                            means[t, mine] / voxel_size, hull / voxel_size
                        ) / (len(frames) * model.n_objects)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        bad = non_finite_parts(loss, {"network": model.network_parameters()})
        if bad:
            skip_or_stop(skipped, step, bad, "the Gaussians' motion prior")
            continue
        opt.step()
        history.append(loss.item())
    return history


def _bar(iterable, enabled: bool, desc: str):
    if not enabled:
        return iterable
    from tqdm import tqdm

    return tqdm(iterable, desc=desc, unit="it", leave=False)


def _canonical_optimizer(model: DynamicGaussians, opts: DynamicGaussOptions):
    rates = {
        "means": opts.lr_position,
        "log_radii": opts.lr_radius,
        "color_logits": opts.lr_color,
        "opacity_logits": opts.lr_opacity,
    }
    groups = [
        {"params": [getattr(model, n)], "lr": rates[n], "name": n} for n in model.canonical_names
    ]
    return torch.optim.Adam(groups)


def _reindex(model: DynamicGaussians, optimizer, index: Tensor, **new_values) -> None:
    """Apply ``model.reindex`` and carry each Gaussian's Adam moments along with it."""
    old = {n: optimizer.state.pop(getattr(model, n), None) for n in model.canonical_names}
    model.reindex(index, **new_values)
    for group in optimizer.param_groups:
        name = group["name"]
        param = getattr(model, name)
        group["params"] = [param]
        state = old[name]
        if state:
            optimizer.state[param] = {
                "step": state["step"],
                "exp_avg": state["exp_avg"][index].clone(),
                "exp_avg_sq": state["exp_avg_sq"][index].clone(),
            }


@torch.no_grad()
def densify_and_prune(
    model: DynamicGaussians,
    optimizer,
    grad_mean: Tensor,
    *,
    voxel_size: float,
    opts: DynamicGaussOptions,
    generator: torch.Generator | None = None,
) -> None:
    """Clone/split Gaussians whose mean positional gradient (times the voxel size) exceeds
    ``opts.densify_grad`` (up to ``opts.max_gaussians``), then prune those with opacity below
    ``opts.prune_opacity`` (each object keeps its ``MIN_PER_OBJECT`` most opaque)."""
    n = model.n_gaussians
    device = model.means.device
    score = grad_mean * voxel_size
    candidates = torch.nonzero(score > opts.densify_grad).squeeze(1)
    room = max(0, opts.max_gaussians - n)
    if len(candidates) > room:
        candidates = candidates[torch.argsort(score[candidates], descending=True)[:room]]
    radius = model.log_radii.exp()
    wide = radius[candidates] > SPLIT_RADIUS_VOXELS * voxel_size
    split, clone = candidates[wide], candidates[~wide]

    keep = torch.ones(n, dtype=torch.bool, device=device)
    keep[split] = False
    opacity = model.opacities()
    keep &= opacity >= opts.prune_opacity
    for k in range(1, model.n_objects + 1):
        mine = torch.nonzero(model.object_ids == k).squeeze(1)
        best = mine[torch.argsort(opacity[mine], descending=True)[:MIN_PER_OBJECT]]
        keep[best[~torch.isin(best, split)]] = True
    kept = torch.nonzero(keep).squeeze(1)

    # a clone starts half a radius away, so it does not receive exactly its twin's gradient
    def _offset(idx: Tensor, scale: float) -> Tensor:
        noise = torch.randn(len(idx), 3, generator=generator).to(device)
        return model.means[idx] + noise * radius[idx, None] * scale

    index = torch.cat([kept, clone, split, split])
    means = torch.cat(
        [model.means[kept], _offset(clone, 0.5), _offset(split, 1.0), _offset(split, 1.0)]
    )
    log_r = model.log_radii[index].clone()
    log_r[len(kept) + len(clone) :] -= math.log(SPLIT_SHRINK)
    _reindex(model, optimizer, index, means=means, log_radii=log_r)


def _schedule_learning_rates(step, iterations, optimizers, base_lrs, net_opt, warmup) -> None:
    """Exponential decay of every learning rate to FINAL_LR_FRACTION of its start; the
    networks' rates also ramp up linearly over the first ``warmup`` steps."""
    decay = FINAL_LR_FRACTION ** (step / max(1, iterations))
    for o, lrs in zip(optimizers, base_lrs, strict=True):
        for g, lr in zip(o.param_groups, lrs, strict=True):
            g["lr"] = lr * decay
    if warmup > 0:  # keep the motion prior's fit through Adam's first steps
        for g in net_opt.param_groups:
            g["lr"] *= min(1.0, (step + 1) / warmup)


def _training_loss(model, data, opts, background, order, generator) -> Tensor:
    """Eq. 2 on one batch of views: the photometric loss, the shape terms and (with tracks)
    the track anchor."""
    batch = sample_views(data, opts.views_per_step, order, generator)
    frames = sorted({t for t, _ in batch})
    means, radii = model.at(frames)
    loss = batch_view_loss(
        means,
        radii,
        model.colors(),
        model.opacities(),
        model.object_ids,
        frames,
        batch,
        data,
        background,
        opts,
    )
    loss = loss + shape_terms(
        means, radii, frames, model.object_ids, data, opts, generator=generator
    )
    if opts.lambda_track > 0 and data.tracks is not None:
        anchor = track_loss(means, frames, model.object_ids, data, tolerance=opts.track_tolerance)
        loss = loss + opts.lambda_track * anchor
    return loss


def train_dynamic(
    model: DynamicGaussians,
    data: TrainingData,
    opts: DynamicGaussOptions,
    *,
    generator: torch.Generator | None = None,
) -> TrainingHistory:
    """Optimise canonical Gaussians, networks (and a learned background) per eq. 2."""
    history = TrainingHistory()
    device = model.means.device
    canon_opt = _canonical_optimizer(model, opts)
    net_opt = torch.optim.Adam(model.network_parameters(), lr=opts.lr_network)
    background = data.background
    bg_opt = None
    if opts.background == "learned":
        background = torch.nn.Parameter(data.background.clone())
        bg_opt = torch.optim.Adam([background], lr=opts.lr_background)
    optimizers = [o for o in (canon_opt, net_opt, bg_opt) if o is not None]
    base_lrs = [[g["lr"] for g in o.param_groups] for o in optimizers]
    warmup = opts.iterations // 15 if opts.network_warmup is None else opts.network_warmup

    net_params = model.network_parameters()
    order: list[int] = []
    grad_sum = torch.zeros(model.n_gaussians, device=device)
    grad_count = torch.zeros(model.n_gaussians, device=device)
    bar = _bar(range(opts.iterations), opts.progress, "gauss training")
    for step in bar:
        trained = {"Gaussians": list(model.canonical_parameters()), "network": net_params}
        if bg_opt is not None:
            trained["background"] = [background]
        _schedule_learning_rates(step, opts.iterations, optimizers, base_lrs, net_opt, warmup)
        loss = _training_loss(model, data, opts, background, order, generator)
        for o in optimizers:
            o.zero_grad(set_to_none=True)
        loss.backward()
        bad = non_finite_parts(loss, trained)
        if bad:
            skip_or_stop(history.skipped_steps, step, bad, "Gaussian training")
            continue
        with torch.no_grad():
            norm = model.means.grad.norm(dim=-1)
            grad_sum += norm
            grad_count += (norm > 0).float()
        for o in optimizers:
            o.step()
        history.loss.append(loss.item())
        if opts.progress and step % 20 == 0:
            bar.set_postfix(loss=f"{history.loss[-1]:.4f}", gaussians=model.n_gaussians)

        due = step > 0 and step % opts.densify_every == 0
        if due and opts.densify_from <= step <= opts.densify_until:
            densify_and_prune(
                model,
                canon_opt,
                grad_sum / grad_count.clamp(min=1),
                voxel_size=data.voxel_size,
                opts=opts,
                generator=generator,
            )
            grad_sum = torch.zeros(model.n_gaussians, device=device)
            grad_count = torch.zeros(model.n_gaussians, device=device)
            history.n_gaussians.append(model.n_gaussians)
    history.background = background.detach().clamp(0.0, 1.0)
    return history
