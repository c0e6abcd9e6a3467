"""Rendering a reconstruction through every camera and scoring it against the video.

Metrics (units as in ``mosiv_framework.metrics``): training-view PSNR (dB) of every (frame,
camera) image; per-object mask IoU per frame, pooled over the cameras (rendered object alpha
above 0.5 against the instance mask); per-object Chamfer distance per frame (mm^2) between the
Gaussian centres and a reference point set (ground truth, for evaluation only).
"""

from __future__ import annotations

import math

import torch

from mosiv_framework.metrics import chamfer_mm2, psnr
from mosiv_framework.types import GaussianFrames
from mosiv_gauss.options import TorchRasterizerOptions
from mosiv_gauss.rasterizer import rasterize

Tensor = torch.Tensor

#: rendered object alpha above this counts as the object's silhouette for the IoU
IOU_ALPHA = 0.5


@torch.no_grad()
def render_views(
    gaussians: GaussianFrames,
    cameras,
    *,
    n_objects: int,
    frames=None,
    background: Tensor | None = None,
    tile_size: int = 16,
) -> tuple[Tensor, Tensor]:
    """Render ``frames`` (default all) through ``cameras``: rgb [F, C, H, W, 3] and object
    alpha [F, C, K, H, W], on the Gaussians' device. ``background`` [C, H, W, 3] or None (black).
    Cameras must share one resolution."""
    sizes = {(c.width, c.height) for c in cameras}
    if len(sizes) != 1:
        raise ValueError(f"render_views needs cameras of one resolution, got {sorted(sizes)}")
    frames = list(range(gaussians.n_frames)) if frames is None else list(frames)
    opts = TorchRasterizerOptions(tile_size=tile_size)
    rgb, alpha = [], []
    for t in frames:
        row_rgb, row_alpha = [], []
        for c, cam in enumerate(cameras):
            bg = None if background is None else background[c]
            out, _ = rasterize(
                gaussians, cam, frame=t, n_objects=n_objects, options=opts, background=bg
            )
            row_rgb.append(out.rgb)
            row_alpha.append(out.object_alpha)
        rgb.append(torch.stack(row_rgb))
        alpha.append(torch.stack(row_alpha))
    return torch.stack(rgb), torch.stack(alpha)


def mask_iou(object_alpha: Tensor, mask_ids: Tensor) -> Tensor:
    """Per-object IoU per frame [F, K], pooled over cameras; NaN where the object is neither
    drawn nor in any mask of the frame. object_alpha [F, C, K, H, W]; mask_ids [F, C, H, W]."""
    n_objects = object_alpha.shape[2]
    ids = torch.arange(1, n_objects + 1, device=mask_ids.device)
    truth = mask_ids.unsqueeze(2) == ids[:, None, None]  # [F, C, K, H, W]
    drawn = object_alpha > IOU_ALPHA
    inter = (truth & drawn).sum(dim=(1, 3, 4)).double()
    union = (truth | drawn).sum(dim=(1, 3, 4)).double()
    return torch.where(union > 0, inter / union.clamp(min=1), torch.full_like(union, math.nan))


def drawn_area_ratio(object_alpha: Tensor, mask_ids: Tensor) -> Tensor:
    """Per-object drawn / recorded silhouette area per frame [F, K], pooled over cameras (NaN
    where the masks hold none of the object): above 1 the drawn silhouette is too fat, below 1
    too thin, which IoU alone cannot tell apart."""
    n_objects = object_alpha.shape[2]
    ids = torch.arange(1, n_objects + 1, device=mask_ids.device)
    truth = (mask_ids.unsqueeze(2) == ids[:, None, None]).sum(dim=(1, 3, 4)).double()
    drawn = (object_alpha > IOU_ALPHA).sum(dim=(1, 3, 4)).double()
    return torch.where(truth > 0, drawn / truth.clamp(min=1), torch.full_like(truth, math.nan))


def image_psnr(rendered: Tensor, target: Tensor) -> Tensor:
    """PSNR (dB) of every image, [F, C]; inputs [F, C, H, W, 3] in [0, 1]."""
    out = torch.empty(rendered.shape[:2], dtype=torch.float64)
    for f in range(rendered.shape[0]):
        for c in range(rendered.shape[1]):
            out[f, c] = psnr(rendered[f, c].clamp(0, 1), target[f, c])
    return out


def chamfer_per_frame(points: dict[int, Tensor], reference: dict[int, Tensor]) -> dict[int, list]:
    """Object id -> Chamfer distance (mm^2) per frame between ``points[k]`` [T, N, 3] and
    ``reference[k]`` [T, M, 3] (m)."""
    missing = sorted(set(reference) - set(points))
    if missing:
        raise ValueError(f"objects {missing} of the reference have no reconstructed points")
    return {
        k: [chamfer_mm2(points[k][t], reference[k][t]) for t in range(reference[k].shape[0])]
        for k in sorted(reference)
    }


def training_metrics(
    gaussians: GaussianFrames,
    cameras,
    rgb: Tensor,
    mask_ids: Tensor,
    background: Tensor,
    *,
    tile_size: int = 16,
    views: Tensor | None = None,
) -> dict:
    """JSON-ready scores of a fit on its own training views.

    rgb [T, C, H, W, 3] and mask_ids [T, C, H, W] of the scene; background [C, H, W, 3];
    views [T, C] bool, the recorded views the scores cover (None: all).
    Keys: psnr_mean, psnr_min (dB, over images), iou (object id as str -> IoU per frame, None
    where undefined), iou_min (lowest defined IoU over objects and frames), area_ratio (object
    id as str -> drawn / recorded silhouette area per frame, ``drawn_area_ratio``).
    """
    n_objects = int(gaussians.object_ids.max()) if len(gaussians.object_ids) else 1
    n_objects = max(n_objects, int(mask_ids.max()))
    rendered, alpha = render_views(
        gaussians, cameras, n_objects=n_objects, background=background, tile_size=tile_size
    )
    p = image_psnr(rendered.cpu(), rgb.cpu())
    alpha = alpha.cpu()
    if views is not None:  # a view not recorded counts neither as drawn nor as recorded
        recorded = views.cpu()
        p = p[recorded]
        alpha = alpha * recorded[:, :, None, None, None]
    iou = mask_iou(alpha, mask_ids.cpu())
    area = drawn_area_ratio(alpha, mask_ids.cpu())
    defined = iou[~torch.isnan(iou)]
    return {
        "psnr_mean": float(p.mean()),
        "psnr_min": float(p.min()),
        "iou": {
            str(k + 1): [None if math.isnan(v) else float(v) for v in iou[:, k].tolist()]
            for k in range(n_objects)
        },
        "iou_min": float(defined.min()) if len(defined) else None,
        "area_ratio": {
            str(k + 1): [None if math.isnan(v) else float(v) for v in area[:, k].tolist()]
            for k in range(n_objects)
        },
    }
