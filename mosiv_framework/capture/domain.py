"""Where the objects are: the region all cameras look at, the visual hull of the masks in it,
the ground fitted under the hull, and the simulation domain around it.

The region is a cube around the point nearest to every optical axis (least squares), large
enough to hold what the widest camera sees at that distance. The visual hull keeps the voxels
of that cube that every camera sees inside the image, in front of it, and on a foreground
pixel. Its lowest voxels in the first frames are the fitted ground (objects start at rest on
it); the box around the hull over every frame, widened by a margin and cut at the ground, is the
domain.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from mosiv_framework.capture.common import CaptureError
from mosiv_framework.scene.cameras import Camera


def region(cameras: Mapping[str, Camera]) -> tuple[np.ndarray, float]:
    """(centre, half side) (m) of the cube the cameras look at."""
    a = np.zeros((3, 3))
    b = np.zeros(3)
    for cam in cameras.values():
        c = cam.camera_center.numpy()
        d = cam.rotation.numpy()[2]  # optical axis in world coordinates
        p = np.eye(3) - np.outer(d, d)
        a += p
        b += p @ c
    if np.linalg.cond(a) > 1e8:
        raise CaptureError(
            "the cameras' optical axes are parallel or there is one camera: cannot locate "
            "the scene they look at"
        )
    centre = np.linalg.solve(a, b)
    half = 0.0
    for cam in cameras.values():
        dist = float(np.linalg.norm(cam.camera_center.numpy() - centre))
        half = max(half, 0.5 * dist * max(cam.width / cam.fx, cam.height / cam.fy))
    return centre, half


def check_in_front(point: np.ndarray, cameras: Mapping[str, Camera], origins, what: str) -> None:
    """CaptureError naming the camera (and where its pose was read) that has ``point`` behind
    it."""
    for cid, cam in cameras.items():
        depth = float(cam.world_to_camera_points(_t(point[None]))[0, 2])
        if depth <= 0:
            raise CaptureError(
                f"{origins[cid]}: the pose of camera {cid!r} puts the {what} "
                f"{np.round(point, 3).tolist()} (m) behind the camera (depth {depth:.3g} m); "
                "check that the pose is world-to-camera in the OpenCV convention"
            )


def _t(x: np.ndarray):
    import torch

    return torch.as_tensor(x, dtype=torch.float64)


def voxel_grid(lower: np.ndarray, upper: np.ndarray, n: int) -> tuple[np.ndarray, float]:
    """([V, 3] voxel centres, voxel side) of cubic voxels filling the box, ``n`` along its
    longest side."""
    lower, upper = np.asarray(lower, float), np.asarray(upper, float)
    step = float(np.max(upper - lower)) / n
    ticks = [lower[i] + (np.arange(max(1, round((upper[i] - lower[i]) / step))) + 0.5) * step
             for i in range(3)]  # fmt: skip
    g = np.stack(np.meshgrid(*ticks, indexing="ij"), axis=-1).reshape(-1, 3)
    return g, step


def _pixel_index(cam: Camera, points: np.ndarray) -> np.ndarray:
    """Flat pixel index of each point in ``cam`` (-1: behind it or outside the image)."""
    uv, z = cam.project(_t(points))
    uv, z = uv.numpy(), z.numpy()
    col, row = np.floor(uv[:, 0]), np.floor(uv[:, 1])
    ok = (z > 0) & (col >= 0) & (col < cam.width) & (row >= 0) & (row < cam.height)
    idx = np.where(ok, row * cam.width + col, -1)
    return np.nan_to_num(idx, nan=-1).astype(np.int64)


def visual_hull(
    masks: Mapping[str, np.ndarray],
    cameras: Mapping[str, Camera],
    points: np.ndarray,
    spans: Mapping[str, tuple[int, int]] | None = None,
) -> np.ndarray:
    """[T, V] bool: voxel v lies on foreground in every camera that recorded frame t;
    ``spans``: camera id -> (first, last) frames of a camera that did not record them all."""
    inside = None
    for cid, cam in cameras.items():
        idx = _pixel_index(cam, points)
        m = masks[cid].reshape(masks[cid].shape[0], -1) > 0
        seen = np.where(idx[None] >= 0, m[:, np.clip(idx, 0, None)], False)
        if spans and cid in spans:  # a frame the camera did not record carves nothing
            first, last = spans[cid]
            absent = np.ones(len(seen), dtype=bool)
            absent[first : last + 1] = False
            seen[absent] = True
        inside = seen if inside is None else inside & seen
    return inside


def fit_ground(hull: np.ndarray, points: np.ndarray, step: float, first: int = 3) -> float:
    """Height (m) of the lowest hull voxels over the first frames (objects rest on the ground
    there): their lowest z, minus half a voxel to reach the voxels' bottom. (A percentile
    would sit above the ground: a resting body touches it in a point.)"""
    z = points[hull[:first].any(axis=0), 2]
    if z.size == 0:
        raise CaptureError(
            "cannot fit the ground: the visual hull of the first frames is empty (masks and "
            "cameras disagree); give --ground"
        )
    return float(z.min()) - 0.5 * step


def hull_domain(
    hull: np.ndarray, points: np.ndarray, step: float, ground: float | None, margin: float
) -> tuple[np.ndarray, np.ndarray]:
    """(lower, upper) of the box around the hull over all frames, widened by ``margin`` x its
    largest side (at least one voxel), lower z set to the ground when there is one."""
    occupied = points[hull.any(axis=0)]
    if occupied.size == 0:
        raise CaptureError(
            "the visual hull is empty in every frame: no point is foreground in all cameras "
            "(wrong poses, wrong units, or masks that miss the objects)"
        )
    lo, hi = occupied.min(axis=0), occupied.max(axis=0)
    pad = max(margin * float(np.max(hi - lo)), step)
    lo, hi = lo - pad, hi + pad
    if ground is not None:
        lo[2] = ground
        hi[2] = max(hi[2], ground + pad)
    return lo, hi
