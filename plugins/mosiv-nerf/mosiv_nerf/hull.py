"""What the masks alone give: visual hulls of each object and static camera backgrounds.

A point belongs to object k's visual hull when every camera whose image contains its
projection sees mask k there (and at least ``min_views`` cameras see it). The hull bounds the
frame-0 field's box and seeds its density; hulls at every frame are the reconstruction's target
points (identification's initial-velocity fit reads their centroids). The background of a
camera is the per-pixel median of its frames where no object covers the pixel.
"""

from __future__ import annotations

import warnings

import numpy as np
import torch

from mosiv_framework.scene.cameras import Camera

Tensor = torch.Tensor


def carve(points: Tensor, cameras: list[Camera], mask_ids: Tensor, *, min_views: int = 2) -> Tensor:
    """Object id [M] (0: no hull) of each point [M, 3] (m) against instance masks
    ``mask_ids`` [C, H, W] (0 background, k object k) of ``cameras``."""
    m = points.shape[0]
    votes = None  # [M] id agreed so far (-1: contradicted)
    seen = torch.zeros(m, dtype=torch.long, device=points.device)
    for cam, ids in zip(cameras, mask_ids):
        uv, z = cam.project(points)
        col, row = torch.floor(uv[:, 0]).long(), torch.floor(uv[:, 1]).long()
        inside = (z > 1e-6) & (col >= 0) & (col < cam.width) & (row >= 0) & (row < cam.height)
        label = ids.to(points.device)[row.clamp(0, cam.height - 1), col.clamp(0, cam.width - 1)]
        label = torch.where(inside, label.long(), torch.full_like(label.long(), -2))
        seen += inside.long()
        if votes is None:
            votes = torch.where(inside, label, torch.full_like(label, -2))
            continue
        fresh = votes == -2
        votes = torch.where(fresh, label, votes)
        clash = inside & ~fresh & (label != votes)
        votes = torch.where(clash, torch.full_like(votes, -1), votes)
    if votes is None:
        return torch.zeros(m, dtype=torch.long, device=points.device)
    return torch.where((seen >= min_views) & (votes > 0), votes, torch.zeros_like(votes))


def lattice(lower, upper, nodes: int, *, device=None) -> tuple[Tensor, float]:
    """Cell-centred lattice over the box [lower, upper] with ``nodes`` cells along its longest
    side: (points [M, 3] m, cell m)."""
    lo = torch.as_tensor(lower, dtype=torch.float32, device=device)
    hi = torch.as_tensor(upper, dtype=torch.float32, device=device)
    cell = float((hi - lo).max()) / nodes
    axes = [
        lo[d] + cell * (0.5 + torch.arange(max(1, int(float(hi[d] - lo[d]) / cell)), device=device))
        for d in range(3)
    ]
    x, y, z = torch.meshgrid(*axes, indexing="ij")
    return torch.stack([x, y, z], dim=-1).reshape(-1, 3), cell


def frame_views(scene, frame: int, device=None) -> tuple[list[Camera], Tensor]:
    """(the cameras that recorded ``frame``, their instance masks [C, H, W] at it): a camera
    that started late neither carves nor colours the frames it missed."""
    cameras = scene.cameras_at(frame)
    ids = scene.load_mask_ids(frames=[frame], cameras=[c.id for c in cameras])[0]
    return cameras, ids.to(device)


def hull_points(
    scene, *, nodes: int, per_object: int, generator: torch.Generator, device=None
) -> dict[int, Tensor]:
    """Object id -> [T, per_object, 3] points drawn from its visual hull at every frame (CPU).

    Points are hull lattice cells, drawn with replacement when the hull has fewer cells, each
    moved uniformly inside its cell. A frame where an object's hull is empty repeats the
    previous frame's points (the object left the cameras' common view)."""
    grid, cell = lattice(*scene.domain, nodes, device=device)
    out: dict[int, list[Tensor]] = {k: [] for k in scene.object_ids}
    for t in range(scene.n_frames):
        labels = carve(grid, *frame_views(scene, t, device))
        for k in scene.object_ids:
            cells = grid[labels == k].cpu()
            if cells.shape[0] == 0:
                if not out[k]:
                    raise ValueError(
                        f"object {k} has an empty visual hull at frame {t}: no point is inside "
                        "its mask in every camera that sees it"
                    )
                out[k].append(out[k][-1])
                continue
            pick = torch.randint(cells.shape[0], (per_object,), generator=generator)
            jitter = (torch.rand(per_object, 3, generator=generator) - 0.5) * cell
            out[k].append(cells[pick] + jitter)
    return {k: torch.stack(v) for k, v in out.items()}


def backgrounds(scene) -> dict[str, Tensor]:
    """Camera id -> [H, W, 3] static background in [0, 1]: the median over the frames the camera
    recorded of the pixels no mask covers; pixels covered in every frame take the mean of the
    uncovered ones."""
    out = {}
    for cam in scene.cameras:
        frames = scene.recorded_frames(cam.id)
        rgb = np.stack([scene.rgb(cam.id, t) for t in frames]).astype(np.float32)
        covered = np.stack([scene.mask(cam.id, t) > 0 for t in frames])
        rgb[covered] = np.nan
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN pixels are filled below
            bg = np.nanmedian(rgb, axis=0)
        never = np.isnan(bg).any(axis=-1)
        if never.any():
            fill = np.nanmean(bg[~never], axis=0) if (~never).any() else np.zeros(3)
            bg[never] = fill
        out[cam.id] = torch.from_numpy(bg / 255.0).float()
    return out
