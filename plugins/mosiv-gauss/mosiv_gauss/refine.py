"""Per-frame refinement: a free centre and radius offset per Gaussian and frame, after eq. 2.

Eq. 1 moves every Gaussian with a few temporal bases shared by the whole scene. That is a strong
prior for the smooth parts of a clip, but it spreads an impact (two bodies that stop against
each other between two frames) over several frames: the drawn bodies at the collision frame are
a blend of before and after, and their silhouettes there score far below the other frames
(docs/BENCHMARKS.md, "Reconstruction (Gaussians, Stage I)"). Four times the steps, more bases and
more time octaves did not change that, so the fix here is outside the bases.

After training, the deformed Gaussians of each frame t get offsets d_t [G, 3] (hull voxels) and
s_t [G] (log-radius), starting at zero and fitted, with colours, opacities and the networks
frozen, to the views of their frame by the same loss as training (photometric, per-object
masks, radius, and the hull term when it is on), plus a neighbour term that keeps each object
moving as a body rather than as loose points:

    L_smooth = mean_{t, g, j in N(g)} |d_t[g] - d_t[j]|^2 + |s_t[g] - s_t[j]|^2

with N(g) the ``neighbours`` nearest canonical centres of g's own object (at frame 0 of the
fitted model). Hidden Gaussians, which no image moves, follow their visible neighbours through
it (slowly at the default weight, which the 11-camera sweep chose); an object's Gaussians
never join another object's neighbourhoods, so the term cannot pull one body's Gaussians into
the other across a contact.

Each frame's offsets are their own tensor, so Adam moves only the frames of the current batch
(one shared tensor would keep moving every frame on stale momentum).
"""

from __future__ import annotations

import torch

from mosiv_framework.types import GaussianFrames
from mosiv_gauss.dynamic_options import DynamicGaussOptions
from mosiv_gauss.train import (
    FINAL_LR_FRACTION,
    TrainingData,
    _bar,
    batch_view_loss,
    sample_views,
    shape_terms,
)

Tensor = torch.Tensor

#: rows of the distance matrix computed at once when finding neighbours
NEIGHBOUR_BLOCK = 2048


def object_neighbours(means: Tensor, object_ids: Tensor, k: int) -> Tensor:
    """Indices [G, k] of each point's k nearest other points of the same object (fewer
    available: the point itself fills the rest, which adds nothing to the smoothness term).
    means [G, 3]; object_ids [G]."""
    n = means.shape[0]
    out = torch.arange(n, device=means.device).unsqueeze(1).repeat(1, max(k, 1))
    for obj in object_ids.unique().tolist():
        mine = torch.nonzero(object_ids == obj).squeeze(1)
        take = min(k, len(mine) - 1)
        if take <= 0:
            continue
        points = means[mine]
        # row blocks keep the distance matrix at NEIGHBOUR_BLOCK x n_obj, whatever n_obj is
        for start in range(0, len(mine), NEIGHBOUR_BLOCK):
            rows = torch.arange(start, min(start + NEIGHBOUR_BLOCK, len(mine)), device=means.device)
            d = torch.cdist(points[rows], points)
            d[torch.arange(len(rows), device=means.device), rows] = float("inf")  # not itself
            nearest = d.topk(take, largest=False).indices  # into `mine`
            out[mine[rows], :take] = mine[nearest]
    return out[:, :k]


def smoothness(offsets: Tensor, log_scales: Tensor, neighbours: Tensor) -> Tensor:
    """Mean squared difference of each Gaussian's offsets [F, G, 3] (voxels) and log-radius
    offsets [F, G] from its neighbours' (``neighbours`` [G, k])."""
    d_pos = offsets.unsqueeze(2) - offsets[:, neighbours]  # [F, G, k, 3]
    d_rad = log_scales.unsqueeze(2) - log_scales[:, neighbours]  # [F, G, k]
    return d_pos.square().sum(-1).mean() + d_rad.square().mean()


def refine_frames(
    gaussians: GaussianFrames,
    data: TrainingData,
    background: Tensor,
    opts: DynamicGaussOptions,
    *,
    generator: torch.Generator | None = None,
) -> tuple[GaussianFrames, list[float]]:
    """Fit per-frame offsets to ``gaussians`` (the trained model at every frame, detached) for
    ``opts.refine_iterations`` steps; returns the refined frames and the loss per step.

    background [C, H, W, 3] in [0, 1] (the trained one). The colours, opacities and object ids
    are returned unchanged.
    """
    base_means = gaussians.means.detach()
    base_log_radii = gaussians.radii.detach().log()
    n_frames, n_gauss = base_means.shape[:2]
    device = base_means.device
    voxel = data.voxel_size
    offsets = [torch.zeros(n_gauss, 3, device=device, requires_grad=True) for _ in range(n_frames)]
    scales = [torch.zeros(n_gauss, device=device, requires_grad=True) for _ in range(n_frames)]
    optimizer = torch.optim.Adam(
        [
            {"params": offsets, "lr": opts.lr_refine_position},
            {"params": scales, "lr": opts.lr_refine_radius},
        ]
    )
    base_lrs = [g["lr"] for g in optimizer.param_groups]
    neighbours = object_neighbours(base_means[0], gaussians.object_ids, opts.refine_neighbours)
    colors, opacities = gaussians.colors.detach(), gaussians.opacities.detach()
    history: list[float] = []
    order: list[int] = []
    bar = _bar(range(opts.refine_iterations), opts.progress, "gauss refinement")
    for step in bar:
        decay = FINAL_LR_FRACTION ** (step / max(1, opts.refine_iterations))
        for g, lr in zip(optimizer.param_groups, base_lrs, strict=True):
            g["lr"] = lr * decay
        batch = sample_views(data, opts.views_per_step, order, generator)
        frames = sorted({t for t, _ in batch})
        d = torch.stack([offsets[t] for t in frames])  # [F, G, 3] voxels
        s = torch.stack([scales[t] for t in frames])  # [F, G]
        means = base_means[frames] + d * voxel
        radii = (base_log_radii[frames] + s).exp()
        loss = batch_view_loss(
            means,
            radii,
            colors,
            opacities,
            gaussians.object_ids,
            frames,
            batch,
            data,
            background,
            opts,
        )
        loss = loss + shape_terms(
            means, radii, frames, gaussians.object_ids, data, opts, generator=generator
        )
        loss = loss + opts.lambda_refine_smooth * smoothness(d, s, neighbours)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        history.append(loss.item())
        if opts.progress and step % 20 == 0:
            bar.set_postfix(loss=f"{history[-1]:.4f}")
    with torch.no_grad():
        means = base_means + torch.stack(offsets) * voxel
        radii = (base_log_radii + torch.stack(scales)).exp()
    refined = GaussianFrames(means, radii, colors, opacities, gaussians.object_ids)
    return refined, history
