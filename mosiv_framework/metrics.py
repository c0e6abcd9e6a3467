"""Evaluation metrics: image fidelity (PSNR, SSIM) and point-set distances (Chamfer, EMD).

Units, used everywhere MOSIV reports a number:

- ``psnr``: decibels (dB), images in [0, 1] unless ``max_value`` says otherwise;
- ``ssim``: dimensionless in [-1, 1] (1 for identical images);
- ``chamfer_mm2``: square millimetres (mm^2), from point sets given in metres;
- ``emd_mm``: millimetres (mm), from point sets given in metres.

These are evaluation metrics, not losses: they return plain floats and are not differentiable
(the differentiable objectives of identification live in ``mosiv_framework.losses``).
``frame_metrics`` aggregates them over frames, per object and per scene, into the dictionary
layout of ``metrics.json`` (docs/ARCHITECTURE.md, metrics.json).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import kornia
import numpy as np
import torch
from scipy.optimize import linear_sum_assignment
from scipy.spatial import cKDTree
from scipy.spatial.distance import cdist

from mosiv_framework.types import GeometryFrames

__all__ = [
    "M_TO_MM",
    "chamfer_floor_mm2",
    "chamfer_mm2",
    "emd_mm",
    "frame_metrics",
    "geometry_metrics",
    "image_metrics",
    "nearest_distances",
    "psnr",
    "ssim",
]

#: millimetres per metre; scene coordinates are metres, reported distances millimetres
M_TO_MM = 1000.0

ArrayLike = torch.Tensor | np.ndarray


# --------------------------------------------------------------------------------------------
# images


def _as_image_batch(image: ArrayLike, name: str) -> torch.Tensor:
    """[H, W, 3] or [B, 3, H, W] (torch or numpy) -> float64 [B, 3, H, W] on the CPU."""
    t = torch.as_tensor(image).detach().to("cpu", torch.float64)
    if t.ndim == 3 and t.shape[-1] == 3:
        return t.permute(2, 0, 1).unsqueeze(0)
    if t.ndim == 4 and t.shape[1] == 3:
        return t
    raise ValueError(
        f"{name} must be an image [H, W, 3] or a batch [B, 3, H, W], got shape {tuple(t.shape)}"
    )


def _image_pair(pred: ArrayLike, target: ArrayLike) -> tuple[torch.Tensor, torch.Tensor]:
    p, t = _as_image_batch(pred, "pred"), _as_image_batch(target, "target")
    if p.shape != t.shape:
        raise ValueError(
            f"pred and target images differ in shape: {tuple(p.shape)} vs {tuple(t.shape)}"
        )
    return p, t


def psnr(pred: ArrayLike, target: ArrayLike, *, max_value: float = 1.0) -> float:
    """Peak signal-to-noise ratio in dB: 10 log10(max_value^2 / MSE).

    Images are [H, W, 3] or [B, 3, H, W] floats in [0, max_value]. For a batch, the PSNR of
    each image (its own MSE) is averaged, so one bad frame does not hide behind good ones.
    Identical images give +inf.
    """
    p, t = _image_pair(pred, target)
    values = [kornia.metrics.psnr(p[i : i + 1], t[i : i + 1], max_value) for i in range(len(p))]
    return float(torch.stack(values).mean())


def region_psnr(
    pred: ArrayLike, target: ArrayLike, region: ArrayLike, *, max_value: float = 1.0
) -> float | None:
    """PSNR in dB over the pixels of ``region`` only: 10 log10(max_value^2 / MSE), the MSE
    over the region's pixels and the 3 channels, averaged over the images of a batch that
    have region pixels (None when none has).

    Images as in :func:`psnr`; ``region`` [H, W] or [B, H, W] bool (say, the objects'
    silhouettes). Where objects cover a small part of the frame, the full-image PSNR is mostly
    the background's; this one is the objects'.
    """
    p, t = _image_pair(pred, target)
    mask = torch.as_tensor(np.asarray(region)).bool().reshape(-1, *p.shape[-2:])
    if mask.shape[0] != p.shape[0]:
        raise ValueError(
            f"region_psnr: {mask.shape[0]} region masks for {p.shape[0]} images; give one "
            "[H, W] mask per image"
        )
    values = []
    for i in range(len(p)):
        inside = mask[i]
        if not bool(inside.any()):
            continue
        mse = (p[i] - t[i]).square()[:, inside].mean()
        values.append(float("inf") if mse == 0 else float(10 * torch.log10(max_value**2 / mse)))
    return float(np.mean(values)) if values else None


def ssim(pred: ArrayLike, target: ArrayLike, *, window: int = 11, max_value: float = 1.0) -> float:
    """Structural similarity (Wang et al. 2004), dimensionless, 1 for identical images.

    Gaussian window of ``window`` pixels (sigma 1.5, kornia's convention), mean of the SSIM map
    over pixels, channels and the batch. Images as in :func:`psnr`.
    """
    if window < 3 or window % 2 == 0:
        raise ValueError(f"ssim window must be an odd number of pixels >= 3, got {window}")
    p, t = _image_pair(pred, target)
    return float(kornia.metrics.ssim(p, t, window, max_val=max_value).mean())


# --------------------------------------------------------------------------------------------
# point sets


def _as_points(points: ArrayLike, name: str) -> np.ndarray:
    """Torch or numpy [N, 3] points (m) -> float64 numpy, validated."""
    if isinstance(points, torch.Tensor):
        points = points.detach().to("cpu", torch.float64).numpy()
    arr = np.asarray(points, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ValueError(f"{name} must be a point set [N, 3] in metres, got {arr.shape}")
    if arr.shape[0] == 0:
        raise ValueError(f"{name} is empty; a distance to an empty point set is undefined")
    if not np.isfinite(arr).all():
        raise ValueError(f"{name} contains non-finite coordinates")
    return arr


def nearest_distances(query: ArrayLike, reference: ArrayLike, *, workers: int = -1) -> np.ndarray:
    """Distance (m) from each query point to its nearest reference point, [N_query] float64.

    A KD-tree over ``reference`` keeps memory linear in the number of points (no N x M matrix);
    ``workers`` is the number of threads (-1: all cores).
    """
    q, r = _as_points(query, "query"), _as_points(reference, "reference")
    distances, _ = cKDTree(r).query(q, k=1, workers=workers)
    return distances


def chamfer_mm2(a: ArrayLike, b: ArrayLike, *, workers: int = -1) -> float:
    """Symmetric Chamfer distance in mm^2 between point sets ``a`` [N, 3] and ``b`` [M, 3] (m).

    CD = mean_{x in a} min_{y in b} |x - y|^2 + mean_{y in b} min_{x in a} |x - y|^2, with
    distances converted to millimetres before squaring. Exact nearest neighbours by KD-tree,
    memory O(N + M): 100k x 100k points take well under a second on two cores.
    """
    d_ab = nearest_distances(a, b, workers=workers) * M_TO_MM
    d_ba = nearest_distances(b, a, workers=workers) * M_TO_MM
    return float(np.mean(d_ab**2) + np.mean(d_ba**2))


def emd_mm(a: ArrayLike, b: ArrayLike, *, n_samples: int = 2048, seed: int = 0) -> float:
    """Earth mover's distance in mm: mean length of the optimal one-to-one matching.

    Both sets (m) are reduced to n = min(n_samples, len(a), len(b)) points drawn without
    replacement by a generator seeded with ``seed`` (the same call gives the same value), then
    matched exactly by the Hungarian algorithm on Euclidean distances
    (scipy.optimize.linear_sum_assignment). Cost grows as n^3; n = 2048 takes about 0.4 s.
    """
    if n_samples < 1:
        raise ValueError(f"emd_mm n_samples must be >= 1, got {n_samples}")
    pa, pb = _as_points(a, "a"), _as_points(b, "b")
    n = min(n_samples, len(pa), len(pb))
    rng = np.random.default_rng(seed)
    pa = pa[rng.choice(len(pa), size=n, replace=False)]
    pb = pb[rng.choice(len(pb), size=n, replace=False)]
    cost = cdist(pa, pb)  # [n, n] Euclidean distances (m)
    rows, cols = linear_sum_assignment(cost)
    return float(cost[rows, cols].mean() * M_TO_MM)


def chamfer_floor_mm2(
    points: Mapping[int, torch.Tensor], *, spacing: float, samples: int = 8, seed: int = 0
) -> float:
    """Chamfer (mm^2) of a perfect dense reconstruction: ``samples`` points drawn uniformly in
    every true particle's lattice cell (side ``spacing``, m) against the particles themselves,
    the worst object and frame. ``points``: object id -> [T, N, 3] (m). A volumetric
    reconstruction that does not know the lattice cannot go below it (about spacing^2 / 4), so
    a reconstruction's Chamfer is judged as a multiple of it."""
    gen = torch.Generator().manual_seed(seed)
    worst = 0.0
    for pts in points.values():
        pts = torch.as_tensor(pts, dtype=torch.float32)
        for t in range(pts.shape[0]):
            offsets = (torch.rand(pts.shape[1], samples, 3, generator=gen) - 0.5) * spacing
            dense = (pts[t].unsqueeze(1) + offsets).reshape(-1, 3)
            worst = max(worst, chamfer_mm2(dense, pts[t]))
    return worst


# --------------------------------------------------------------------------------------------
# aggregation over frames


PointFrames = Mapping[int, ArrayLike] | Mapping[int, Sequence[ArrayLike]] | GeometryFrames


def _frames_of(points: PointFrames, name: str) -> dict[int, list[ArrayLike]]:
    """Object id -> list of per-frame [N_k, 3] sets, from GeometryFrames, [T, N_k, 3] arrays
    (``Reconstruction.points``, ``gt/points.npz``) or lists of per-frame sets."""
    if isinstance(points, GeometryFrames):
        return {int(k): list(v) for k, v in points.points.items()}
    out: dict[int, list[ArrayLike]] = {}
    for k, v in points.items():
        if isinstance(v, (torch.Tensor, np.ndarray)):
            if v.ndim != 3 or v.shape[-1] != 3:
                raise ValueError(
                    f"{name}[{k}] must be [T, N, 3] points per frame, got {tuple(v.shape)}"
                )
            out[int(k)] = [v[t] for t in range(v.shape[0])]
        else:
            out[int(k)] = list(v)
    if not out:
        raise ValueError(f"{name} holds no objects")
    return out


def _union(sets: Sequence[ArrayLike]) -> np.ndarray:
    return np.concatenate([_as_points(s, "points") for s in sets], axis=0)


def geometry_metrics(
    predicted: PointFrames,
    target: PointFrames,
    *,
    frames: Sequence[int] | None = None,
    n_samples: int = 2048,
    seed: int = 0,
) -> dict:
    """Chamfer (mm^2) and EMD (mm), mean over frames, per object and for the whole scene.

    ``predicted`` and ``target`` map object id -> per-frame point sets in metres (see
    ``PointFrames``); they must hold the same objects and frame count. ``frames`` selects frame
    indices (default: all). The scene values compare the union of all objects' points, so they
    ignore which object a point belongs to; ``per_object`` keeps identities. Returns
    ``{"cd_mm2", "emd_mm", "per_object": {k: {"cd_mm2", "emd_mm"}}}``.
    """
    pred, targ = _frames_of(predicted, "predicted"), _frames_of(target, "target")
    if sorted(pred) != sorted(targ):
        raise ValueError(
            f"predicted objects {sorted(pred)} differ from target objects {sorted(targ)}"
        )
    n_frames = {len(v) for v in pred.values()} | {len(v) for v in targ.values()}
    if len(n_frames) != 1:
        raise ValueError(f"every object needs the same number of frames, got counts {n_frames}")
    total = n_frames.pop()
    chosen = list(range(total)) if frames is None else [int(f) for f in frames]
    bad = [f for f in chosen if not 0 <= f < total]
    if bad or not chosen:
        raise ValueError(f"frames {bad or chosen} are not in 0..{total - 1}")

    per_object: dict[int, dict[str, float]] = {}
    for k in sorted(pred):
        cd = [chamfer_mm2(pred[k][f], targ[k][f]) for f in chosen]
        emd = [emd_mm(pred[k][f], targ[k][f], n_samples=n_samples, seed=seed + f) for f in chosen]
        per_object[k] = {"cd_mm2": float(np.mean(cd)), "emd_mm": float(np.mean(emd))}

    scene_cd, scene_emd = [], []
    for f in chosen:
        pu = _union([pred[k][f] for k in sorted(pred)])
        tu = _union([targ[k][f] for k in sorted(targ)])
        scene_cd.append(chamfer_mm2(pu, tu))
        scene_emd.append(emd_mm(pu, tu, n_samples=n_samples, seed=seed + f))
    return {
        "cd_mm2": float(np.mean(scene_cd)),
        "emd_mm": float(np.mean(scene_emd)),
        "per_object": per_object,
    }


def image_metrics(
    predicted: Sequence[ArrayLike] | ArrayLike,
    target: Sequence[ArrayLike] | ArrayLike,
    *,
    max_value: float = 1.0,
    window: int = 11,
) -> dict[str, float]:
    """PSNR (dB) and SSIM, each the mean over frames (and cameras) of the per-image value.

    ``predicted`` and ``target`` are equally long sequences of images ([H, W, 3] or
    [B, 3, H, W]), or stacked arrays [F, H, W, 3]. A frame with identical images has infinite
    PSNR; it is kept (the mean becomes inf) rather than silently dropped.
    """
    if len(predicted) != len(target) or len(predicted) == 0:
        raise ValueError(
            f"image_metrics needs equally many predicted and target images (and at least one), "
            f"got {len(predicted)} and {len(target)}"
        )
    ps = [psnr(p, t, max_value=max_value) for p, t in zip(predicted, target, strict=True)]
    ss = [
        ssim(p, t, window=window, max_value=max_value)
        for p, t in zip(predicted, target, strict=True)
    ]
    return {"psnr": float(np.mean(ps)), "ssim": float(np.mean(ss))}


def frame_metrics(
    predicted_points: PointFrames,
    target_points: PointFrames,
    *,
    predicted_images: Sequence[ArrayLike] | None = None,
    target_images: Sequence[ArrayLike] | None = None,
    image_regions: Sequence[ArrayLike] | None = None,
    frames: Sequence[int] | None = None,
    n_samples: int = 2048,
    seed: int = 0,
) -> dict:
    """One block of ``metrics.json`` (``observed`` or ``future``) over a range of frames.

    Geometry as in :func:`geometry_metrics` (``frames`` selects point frames); when images are
    given (already restricted to the same frames by the caller), PSNR and SSIM as in
    :func:`image_metrics`, and with ``image_regions`` (one [B, H, W] bool per image batch) the
    PSNR over those regions (:func:`region_psnr`, mean over frames). Keys: ``cd_mm2`` (mm^2),
    ``emd_mm`` (mm), ``psnr`` (dB), ``ssim``, ``psnr_objects`` (dB), ``per_object``; the image
    keys are None without images (``psnr_objects`` also without regions).
    """
    out = geometry_metrics(
        predicted_points, target_points, frames=frames, n_samples=n_samples, seed=seed
    )
    if (predicted_images is None) != (target_images is None):
        raise ValueError("give both predicted_images and target_images, or neither")
    images = (
        image_metrics(predicted_images, target_images)
        if predicted_images is not None
        else {"psnr": None, "ssim": None}
    )
    objects_psnr = None
    if image_regions is not None and predicted_images is not None:
        if len(image_regions) != len(predicted_images):
            raise ValueError(
                f"{len(image_regions)} image_regions for {len(predicted_images)} images"
            )
        per_frame = [
            region_psnr(p, t, r)
            for p, t, r in zip(predicted_images, target_images, image_regions, strict=True)
        ]
        per_frame = [v for v in per_frame if v is not None]
        objects_psnr = float(np.mean(per_frame)) if per_frame else None
    return {
        "cd_mm2": out["cd_mm2"],
        "emd_mm": out["emd_mm"],
        "psnr": images["psnr"],
        "ssim": images["ssim"],
        "psnr_objects": objects_psnr,
        "per_object": out["per_object"],
    }
