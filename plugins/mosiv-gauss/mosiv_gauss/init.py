"""Initialisation of the dynamic Gaussians from the instance masks (per-object visual hulls).

A voxel grid fills the scene domain. Every voxel centre is projected once into every camera; a
voxel belongs to the hull of object ``k`` at a frame when

- no camera that sees it (projection inside the image, in front of the camera) shows background
  there (space carving), and
- it is seen by at least half the cameras (so the image borders do not leave uncarved slabs),

and among the cameras it gets the label ``k`` most often. The vote, rather than requiring ``k``
in every view, keeps the carving occlusion-aware: where object ``j`` hides object ``k`` the
mask says ``j``, which must not carve ``k`` away.

Frame 0's hull seeds the canonical Gaussians (object id, colour from the pixels that see them,
radius from the voxel size); the hull centroids of every frame give a coarse per-object track
that ``train.fit_motion_prior`` uses to start the deformation near the true motion.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

Tensor = torch.Tensor

#: at most this many voxel centres of each per-frame hull are kept for the motion prior
MAX_HULL_POINTS = 4000
#: voxels closer than this to a camera plane (m) count as not seen by it
_NEAR = 1e-3


@dataclass
class VoxelGrid:
    """Voxel centres [V, 3] (m) on a regular grid of the domain, with side ``voxel_size`` (m)."""

    centres: Tensor
    voxel_size: float


@dataclass
class HullInit:
    """Seeds of the canonical Gaussians and the per-frame hull tracks.

    means [G, 3] m; object_ids [G] int64 in 1..K; colors [G, 3] in [0, 1]; voxel_size m;
    tracks [T, K, 3] hull centroid of object k+1 at frame t (m), held from the nearest frame
    where its hull is empty; track_valid [T, K] whether the hull was non-empty there;
    hulls[t][k] [N, 3] voxel centres (m) of object k+1's hull at frame t (at most
    ``MAX_HULL_POINTS``, a random subset), empty where the hull is.
    """

    means: Tensor
    object_ids: Tensor
    colors: Tensor
    voxel_size: float
    tracks: Tensor
    track_valid: Tensor
    hulls: list[list[Tensor]]


def voxel_grid(lower, upper, *, resolution: int, device="cpu") -> VoxelGrid:
    """Cubic voxels over the box [lower, upper] (m), ``resolution`` along its longest side."""
    lo = torch.tensor(lower, dtype=torch.float32, device=device)
    hi = torch.tensor(upper, dtype=torch.float32, device=device)
    size = float((hi - lo).max()) / resolution
    axes = []
    for d in range(3):
        n = max(1, int(round(float(hi[d] - lo[d]) / size)))
        axes.append(lo[d] + (torch.arange(n, device=device, dtype=torch.float32) + 0.5) * size)
    grid = torch.stack(torch.meshgrid(*axes, indexing="ij"), dim=-1).reshape(-1, 3)
    return VoxelGrid(grid, size)


def pixel_lookup(points: Tensor, cameras) -> Tensor:
    """Flat pixel index (row * W + col) of each point in each camera, [C, V]; -1 where unseen."""
    out = []
    for cam in cameras:
        uv, z = cam.project(points)
        col = torch.floor(uv[:, 0]).long()
        row = torch.floor(uv[:, 1]).long()
        seen = (z > _NEAR) & (col >= 0) & (col < cam.width) & (row >= 0) & (row < cam.height)
        out.append(torch.where(seen, row * cam.width + col, torch.full_like(col, -1)))
    return torch.stack(out)


def dilate_ids(mask_ids: Tensor) -> Tensor:
    """Instance ids [C, H, W] with every background pixel next to an object (3x3 neighbourhood)
    given that object's id (the larger id where two meet)."""
    grown = torch.nn.functional.max_pool2d(mask_ids.float().unsqueeze(1), 3, stride=1, padding=1)
    return torch.where(mask_ids > 0, mask_ids, grown.squeeze(1).long())


def carve_labels(
    lookup: Tensor, mask_ids: Tensor, *, n_objects: int, views: Tensor | None = None
) -> Tensor:
    """Object label of every voxel at one frame (0 = empty), by occlusion-aware carving.

    lookup [C, V] from :func:`pixel_lookup`; mask_ids [C, H, W] instance ids of the frame. The
    masks are dilated by one pixel first: a mask labels pixel centres, while the object part a
    voxel stands for may cover only a pixel's edge, so the hull errs on the side of too large
    (training removes the excess) rather than cutting the object's rim off. ``views`` [C] bool:
    the cameras that recorded the frame (None: all); the others neither carve nor vote.
    """
    if views is not None:
        lookup = torch.where(views[:, None], lookup, torch.full_like(lookup, -1))
    n_cams = lookup.shape[0] if views is None else int(views.sum())
    flat = dilate_ids(mask_ids).reshape(lookup.shape[0], -1)
    seen = lookup >= 0
    labels = torch.gather(flat, 1, lookup.clamp(min=0))
    labels = torch.where(seen, labels, torch.full_like(labels, -1))  # -1: not seen
    carved = (labels == 0).any(dim=0)
    enough_views = seen.sum(dim=0) * 2 >= n_cams
    ids = torch.arange(1, n_objects + 1, device=lookup.device)
    votes = (labels.unsqueeze(0) == ids[:, None, None]).sum(dim=1)  # [K, V]
    best_votes, best = votes.max(dim=0)
    keep = ~carved & enough_views & (best_votes > 0)
    return torch.where(keep, best + 1, torch.zeros_like(best))


def hull_tracks(labels_per_frame: list[Tensor], centres: Tensor, *, n_objects: int):
    """Per-object hull centroids [T, K, 3] (m) and validity [T, K]; empty hulls hold the
    centroid of the nearest frame where the hull is non-empty (a constant if it never is)."""
    n_frames = len(labels_per_frame)
    tracks = torch.zeros(n_frames, n_objects, 3, device=centres.device)
    valid = torch.zeros(n_frames, n_objects, dtype=torch.bool, device=centres.device)
    for t, labels in enumerate(labels_per_frame):
        for k in range(n_objects):
            inside = labels == k + 1
            if inside.any():
                tracks[t, k] = centres[inside].mean(dim=0)
                valid[t, k] = True
    for k in range(n_objects):
        good = torch.nonzero(valid[:, k]).squeeze(1)
        if len(good) == 0:
            continue
        for t in range(n_frames):
            if not valid[t, k]:
                nearest = good[torch.argmin((good - t).abs())]
                tracks[t, k] = tracks[nearest, k]
    return tracks, valid


def seed_colors(object_ids: Tensor, lookup: Tensor, mask_ids: Tensor, rgb: Tensor) -> Tensor:
    """Mean colour [G, 3] of the pixels that see each seed with its own object's label.

    lookup [C, G] pixel of each seed per camera; mask_ids [C, H, W]; rgb [C, H, W, 3] of frame 0.
    Seeds no camera sees with their label (hidden inside the hull) take their object's mean.
    """
    n_cams = lookup.shape[0]
    flat_ids = mask_ids.reshape(n_cams, -1)
    flat_rgb = rgb.reshape(n_cams, -1, 3)
    idx = lookup.clamp(min=0)
    label = torch.gather(flat_ids, 1, idx)
    ok = (lookup >= 0) & (label == object_ids.unsqueeze(0))  # [C, G]
    colour = torch.stack([flat_rgb[c][idx[c]] for c in range(n_cams)])  # [C, G, 3]
    total = (colour * ok.unsqueeze(-1)).sum(dim=0)
    count = ok.sum(dim=0)
    out = total / count.clamp(min=1).unsqueeze(-1)
    for k in object_ids.unique().tolist():
        mine = object_ids == k
        seen = mine & (count > 0)
        fallback = out[seen].mean(dim=0) if seen.any() else rgb.reshape(-1, 3).mean(dim=0)
        out[mine & (count == 0)] = fallback
    return out


def hull_init(
    cameras,
    mask_ids: Tensor,
    rgb0: Tensor,
    *,
    lower,
    upper,
    n_objects: int,
    resolution: int,
    max_gaussians: int,
    generator: torch.Generator | None = None,
    views: Tensor | None = None,
) -> HullInit:
    """Seed Gaussians in frame 0's per-object visual hulls and track every frame's hulls.

    mask_ids [T, C, H, W] instance ids; rgb0 [C, H, W, 3] frame-0 images in [0, 1]; lower/upper
    the domain box (m). At most ``max_gaussians`` seeds, split evenly between the objects.
    ``views`` [T, C] bool: the recorded views (None: all); a frame's hull is carved by the
    cameras that recorded it. Raises ValueError naming the object whose frame-0 hull is empty.
    """
    device = mask_ids.device
    grid = voxel_grid(lower, upper, resolution=resolution, device=device)
    lookup = pixel_lookup(grid.centres, cameras)
    labels = [
        carve_labels(
            lookup, mask_ids[t], n_objects=n_objects, views=None if views is None else views[t]
        )
        for t in range(len(mask_ids))
    ]
    tracks, valid = hull_tracks(labels, grid.centres, n_objects=n_objects)

    per_object = max(1, max_gaussians // n_objects)
    chosen, ids = [], []
    for k in range(1, n_objects + 1):
        inside = torch.nonzero(labels[0] == k).squeeze(1)
        if len(inside) == 0:
            raise ValueError(
                f"object {k}: its frame-0 visual hull is empty (no voxel of the "
                f"{resolution}-voxel grid projects into its mask in the views that see it); "
                "check the masks of frame 0 or raise hull_resolution"
            )
        if len(inside) > per_object:
            pick = torch.randperm(len(inside), generator=generator)[:per_object]
            inside = inside[pick.to(device)]
        chosen.append(inside)
        ids.append(torch.full((len(inside),), k, dtype=torch.long, device=device))
    voxels, ids_t = torch.cat(chosen), torch.cat(ids)
    seen0 = lookup[:, voxels]
    if views is not None:  # a camera that missed frame 0 gives no colour
        seen0 = torch.where(views[0][:, None], seen0, torch.full_like(seen0, -1))
    colors = seed_colors(ids_t, seen0, mask_ids[0], rgb0)
    hulls = []
    for frame_labels in labels:
        per_object = []
        for k in range(1, n_objects + 1):
            inside = torch.nonzero(frame_labels == k).squeeze(1)
            if len(inside) > MAX_HULL_POINTS:
                pick = torch.randperm(len(inside), generator=generator)[:MAX_HULL_POINTS]
                inside = inside[pick.to(device)]
            per_object.append(grid.centres[inside])
        hulls.append(per_object)
    return HullInit(grid.centres[voxels], ids_t, colors, grid.voxel_size, tracks, valid, hulls)
