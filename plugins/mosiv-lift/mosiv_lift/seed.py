"""Frame-0 appearance Gaussians for reconstructions that carry only points (the oracle).

The ``gaussians`` lifter needs Gaussians to carve and to carry appearance. A points-only
reconstruction gets one isotropic Gaussian per frame-0 point: radius ``point_radius`` (default
half the median nearest-neighbour distance, so neighbouring Gaussians overlap into a closed
surface), opacity 1, and the colour the recording shows where the point is visible:
1. all objects' Gaussians are rendered through every recorded camera (so objects occlude each
   other) to get the expected surface depth ``depth / alpha`` per pixel;
2. a point is visible in a camera when it projects inside the image onto a pixel of its own
   object's mask and lies no deeper than the rendered surface plus two radii;
3. its colour is the mean recorded colour over the cameras that see it; points seen by none
   (the interior) take the mean colour of their object's mask pixels.
Colours are stored in the recording's own encoding (sRGB values in [0, 1]), so rendering them
reproduces the recorded images without a colour transform.
"""

from __future__ import annotations

import numpy as np
import torch
from scipy.spatial import cKDTree

from mosiv_framework.types import GaussianFrames

Tensor = torch.Tensor


def default_point_radius(points: dict[int, Tensor]) -> float:
    """Half the median nearest-neighbour distance (m) over all objects' points."""
    dists = []
    for pts in points.values():
        arr = pts.detach().cpu().numpy().astype(np.float64)
        if len(arr) < 2:
            continue
        d, _ = cKDTree(arr).query(arr, k=2)
        dists.append(d[:, 1])
    if not dists:
        raise ValueError("cannot choose a Gaussian radius: every object has fewer than 2 points")
    return 0.5 * float(np.median(np.concatenate(dists)))


def gaussians_from_points(
    points: dict[int, Tensor],
    scene,
    renderer,
    *,
    radius: float,
) -> GaussianFrames:
    """One-frame Gaussians at ``points`` (object id -> [N_k, 3] m), coloured from frame 0."""
    ids = sorted(points)
    means = torch.cat([points[k].to(torch.float32) for k in ids])
    object_ids = torch.cat([torch.full((points[k].shape[0],), k, dtype=torch.int64) for k in ids])
    g = means.shape[0]
    radii = torch.full((1, g), float(radius))
    opacities = torch.ones(g)
    n_objects = max(scene.object_ids)
    grey = GaussianFrames(means[None], radii, torch.full((g, 3), 0.5), opacities, object_ids)

    color_sum = torch.zeros(g, 3)
    seen = torch.zeros(g)
    object_sum = torch.zeros(n_objects + 1, 3)
    object_count = torch.zeros(n_objects + 1)
    for cam in scene.cameras_at(0):  # a camera that started late has no frame 0
        rgb = torch.from_numpy(scene.rgb(cam.id, 0).astype(np.float32) / 255.0)
        mask = torch.from_numpy(scene.mask(cam.id, 0).astype(np.int64))
        with torch.no_grad():
            out = renderer.render(grey, cam, frame=0, n_objects=n_objects)
        surface = torch.where(out.alpha > 1e-3, out.depth / out.alpha.clamp_min(1e-3), 0.0)
        uv, z = cam.project(means)
        col = torch.floor(uv[:, 0]).long()
        row = torch.floor(uv[:, 1]).long()
        inside = (z > 0) & (col >= 0) & (col < cam.width) & (row >= 0) & (row < cam.height)
        col, row = col.clamp(0, cam.width - 1), row.clamp(0, cam.height - 1)
        own = mask[row, col] == object_ids
        # visible: on its own object's pixels and not hidden behind the rendered surface
        visible = inside & own & (z <= surface[row, col] + 2.0 * radius)
        color_sum += visible[:, None] * rgb[row, col]
        seen += visible.float()
        flat = mask.reshape(-1)
        object_sum.index_add_(0, flat, rgb.reshape(-1, 3))
        object_count.index_add_(0, flat, torch.ones_like(flat, dtype=torch.float32))
    fallback = object_sum / object_count.clamp_min(1.0)[:, None]
    colors = torch.where(
        seen[:, None] > 0, color_sum / seen.clamp_min(1.0)[:, None], fallback[object_ids]
    )
    return GaussianFrames(means[None], radii, colors.clamp(0.0, 1.0), opacities, object_ids)
