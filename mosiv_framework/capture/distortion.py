"""Lens distortion of the OpenCV / COLMAP family and remapping of frames to a pinhole camera.

The model acts on normalised camera coordinates ``(x, y) = ((u - cx) / fx, (v - cy) / fy)``::

    r2 = x^2 + y^2
    radial = 1 + k1 r2 + k2 r2^2 + k3 r2^3
    x_d = x radial + 2 p1 x y + p2 (r2 + 2 x^2)
    y_d = y radial + p1 (r2 + 2 y^2) + 2 p2 x y

COLMAP's SIMPLE_RADIAL (k), RADIAL (k1, k2) and OPENCV (k1, k2, p1, p2) and nerfstudio's
k1, k2, k3, p1, p2 are all special cases. Undistorting an image needs only the forward model (each
pinhole pixel looks up where the lens put it); the inverse, used to distort an image, is found by
fixed-point iteration. Pixel coordinates follow docs/SCENE_FORMAT.md: centres at integer + 0.5.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
import torch

#: coefficient names, in the order of ``Distortion`` fields
COEFFICIENTS = ("k1", "k2", "p1", "p2", "k3")


@dataclass(frozen=True)
class Distortion:
    """Radial (k1, k2, k3) and tangential (p1, p2) coefficients; all zero = a pinhole lens."""

    k1: float = 0.0
    k2: float = 0.0
    p1: float = 0.0
    p2: float = 0.0
    k3: float = 0.0

    @classmethod
    def from_mapping(cls, data: Mapping[str, float]) -> Distortion:
        return cls(**{k: float(data.get(k, 0.0)) for k in COEFFICIENTS})

    @property
    def is_zero(self) -> bool:
        return all(getattr(self, k) == 0.0 for k in COEFFICIENTS)

    def as_dict(self) -> dict[str, float]:
        return {k: getattr(self, k) for k in COEFFICIENTS}


def distort_points(xy: np.ndarray, d: Distortion) -> np.ndarray:
    """Normalised undistorted coordinates [..., 2] -> distorted ones [..., 2]."""
    x, y = xy[..., 0], xy[..., 1]
    r2 = x * x + y * y
    radial = 1.0 + r2 * (d.k1 + r2 * (d.k2 + r2 * d.k3))
    xd = x * radial + 2.0 * d.p1 * x * y + d.p2 * (r2 + 2.0 * x * x)
    yd = y * radial + d.p1 * (r2 + 2.0 * y * y) + 2.0 * d.p2 * x * y
    return np.stack([xd, yd], axis=-1)


def undistort_points(
    xy_d: np.ndarray, d: Distortion, *, iterations: int = 50, tol: float = 1e-10
) -> np.ndarray:
    """Normalised distorted coordinates [..., 2] -> undistorted ones, by fixed-point iteration
    ``x <- (x_d - tangential(x)) / radial(x)`` (converges for the moderate distortion of real
    lenses; the residual of the forward model says how well)."""
    xy_d = np.asarray(xy_d, dtype=np.float64)
    x, y = xy_d[..., 0].copy(), xy_d[..., 1].copy()
    for _ in range(iterations):
        r2 = x * x + y * y
        radial = 1.0 + r2 * (d.k1 + r2 * (d.k2 + r2 * d.k3))
        dx = 2.0 * d.p1 * x * y + d.p2 * (r2 + 2.0 * x * x)
        dy = d.p1 * (r2 + 2.0 * y * y) + 2.0 * d.p2 * x * y
        x_new = (xy_d[..., 0] - dx) / radial
        y_new = (xy_d[..., 1] - dy) / radial
        step = max(float(np.max(np.abs(x_new - x), initial=0.0)), 0.0)
        step = max(step, float(np.max(np.abs(y_new - y), initial=0.0)))
        x, y = x_new, y_new
        if step < tol:
            break
    return np.stack([x, y], axis=-1)


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics (pixels) of a width x height image."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float

    def pixel_grid(self) -> np.ndarray:
        """[H, W, 2] normalised coordinates of every pixel centre."""
        u = (np.arange(self.width) + 0.5 - self.cx) / self.fx
        v = (np.arange(self.height) + 0.5 - self.cy) / self.fy
        vv, uu = np.meshgrid(v, u, indexing="ij")
        return np.stack([uu, vv], axis=-1)

    def to_pixels(self, xy: np.ndarray) -> np.ndarray:
        return np.stack([xy[..., 0] * self.fx + self.cx, xy[..., 1] * self.fy + self.cy], -1)


def remap(frames: np.ndarray, uv: np.ndarray, *, chunk: int = 16) -> np.ndarray:
    """Sample frames uint8 [T, H, W, C] at continuous pixel coordinates uv [H', W', 2]
    (bilinear; outside the image reads black) -> uint8 [T, H', W', C]."""
    t, h, w, c = frames.shape
    # grid_sample with align_corners=False uses the same pixel-centre convention (centre of
    # pixel i at i + 0.5 in a [0, W] span), so the mapping to [-1, 1] is a plain rescale
    grid = np.empty(uv.shape, dtype=np.float32)
    grid[..., 0] = 2.0 * uv[..., 0] / w - 1.0
    grid[..., 1] = 2.0 * uv[..., 1] / h - 1.0
    grid_t = torch.from_numpy(grid)[None]
    out = np.empty((t,) + uv.shape[:2] + (c,), dtype=np.uint8)
    for start in range(0, t, chunk):
        part = torch.from_numpy(np.ascontiguousarray(frames[start : start + chunk]))
        src = part.permute(0, 3, 1, 2).to(torch.float32)
        res = torch.nn.functional.grid_sample(
            src, grid_t.expand(src.shape[0], -1, -1, -1), mode="bilinear",
            padding_mode="zeros", align_corners=False,
        )  # fmt: skip
        res = res.permute(0, 2, 3, 1).round().clamp(0, 255).to(torch.uint8)
        out[start : start + chunk] = res.numpy()
    return out


def undistort_frames(frames: np.ndarray, k: Intrinsics, d: Distortion) -> np.ndarray:
    """Frames [T, H, W, 3] seen through lens ``d`` -> the same frames through a pinhole camera
    with the same intrinsics ``k``."""
    if d.is_zero:
        return frames
    return remap(frames, k.to_pixels(distort_points(k.pixel_grid(), d)))


def distort_frames(frames: np.ndarray, k: Intrinsics, d: Distortion) -> np.ndarray:
    """Pinhole frames [T, H, W, 3] -> what lens ``d`` with intrinsics ``k`` records (the
    inverse of ``undistort_frames`` up to interpolation)."""
    if d.is_zero:
        return frames
    return remap(frames, k.to_pixels(undistort_points(k.pixel_grid(), d)))
