"""Lens distortion of the OpenCV / COLMAP ``OPENCV`` camera model: forward and inverse.

A camera point (x, y, z) first becomes the ideal normalised coordinate ``(x/z, y/z)``. The lens
moves it to the distorted normalised coordinate

    r^2  = x^2 + y^2
    x_d  = x (1 + k1 r^2 + k2 r^4) + 2 p1 x y + p2 (r^2 + 2 x^2)
    y_d  = y (1 + k1 r^2 + k2 r^4) + p1 (r^2 + 2 y^2) + 2 p2 x y

and the sensor records it at pixel ``(u, v) = (fx x_d + cx, fy y_d + cy)``, with pixel centres at
integer + 0.5 as in ``mosiv-scene/1`` (and COLMAP). COLMAP's ``RADIAL`` model is the same map with
``p1 = p2 = 0`` and ``fx = fy``. ``k1 < 0`` is barrel distortion (the image edge pulled inward).

``distort_normalized`` is the forward map; ``undistort_normalized`` inverts it by Newton's
method on the 2x2 Jacobian (there is no closed form). ``distort_pixels`` / ``undistort_pixels``
do the same on pixel coordinates, and ``distort_image`` resamples an ideal pinhole image into
what the distorting lens would have recorded: each output (distorted) pixel centre is undistorted
to find where it lies in the ideal image, which is sampled bilinearly there.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Newton iterations of the inverse; moderate lenses converge to 1e-12 in fewer than 10
UNDISTORT_ITERATIONS = 30
#: stop once every point moved less than this (normalised units) in one Newton step
UNDISTORT_TOL = 1e-14


@dataclass(frozen=True)
class Distortion:
    """Radial (k1, k2) and tangential (p1, p2) coefficients of the OpenCV model."""

    k1: float = 0.0
    k2: float = 0.0
    p1: float = 0.0
    p2: float = 0.0

    @property
    def is_identity(self) -> bool:
        return self.k1 == self.k2 == self.p1 == self.p2 == 0.0

    @property
    def radial_only(self) -> bool:
        return self.p1 == self.p2 == 0.0

    @classmethod
    def parse(cls, text: str) -> Distortion:
        """``"k1,k2"`` or ``"k1,k2,p1,p2"`` (ValueError naming the text otherwise)."""
        parts = [p.strip() for p in text.split(",") if p.strip()]
        if len(parts) not in (2, 4):
            raise ValueError(f"distortion {text!r}: give k1,k2 or k1,k2,p1,p2")
        values = [float(p) for p in parts]
        if not all(np.isfinite(values)):
            raise ValueError(f"distortion {text!r}: coefficients must be finite numbers")
        return cls(*values)


def distort_normalized(xy: np.ndarray, d: Distortion) -> np.ndarray:
    """Ideal normalised coordinates [..., 2] -> distorted ones [..., 2] (the forward map)."""
    xy = np.asarray(xy, dtype=np.float64)
    x, y = xy[..., 0], xy[..., 1]
    r2 = x * x + y * y
    radial = 1.0 + d.k1 * r2 + d.k2 * r2 * r2
    xd = x * radial + 2.0 * d.p1 * x * y + d.p2 * (r2 + 2.0 * x * x)
    yd = y * radial + d.p1 * (r2 + 2.0 * y * y) + 2.0 * d.p2 * x * y
    return np.stack([xd, yd], axis=-1)


def _jacobian(x: np.ndarray, y: np.ndarray, d: Distortion) -> tuple[np.ndarray, ...]:
    """Entries (a, b, c, e) of d(x_d, y_d)/d(x, y) = [[a, b], [c, e]]."""
    r2 = x * x + y * y
    radial = 1.0 + d.k1 * r2 + d.k2 * r2 * r2
    dradial = d.k1 + 2.0 * d.k2 * r2  # d radial / d(r^2)
    a = radial + 2.0 * x * x * dradial + 2.0 * d.p1 * y + 6.0 * d.p2 * x
    b = 2.0 * x * y * dradial + 2.0 * d.p1 * x + 2.0 * d.p2 * y
    c = 2.0 * x * y * dradial + 2.0 * d.p1 * x + 2.0 * d.p2 * y
    e = radial + 2.0 * y * y * dradial + 6.0 * d.p1 * y + 2.0 * d.p2 * x
    return a, b, c, e


def undistort_normalized(xy_d: np.ndarray, d: Distortion) -> np.ndarray:
    """Distorted normalised coordinates [..., 2] -> ideal ones [..., 2] (the inverse map).

    Newton's method from the distorted point itself; points where the lens model folds over
    (beyond its invertible radius) come back as NaN rather than as a wrong answer."""
    target = np.asarray(xy_d, dtype=np.float64)
    if d.is_identity:
        return target.copy()
    xy = target.copy()
    for _ in range(UNDISTORT_ITERATIONS):
        residual = distort_normalized(xy, d) - target
        a, b, c, e = _jacobian(xy[..., 0], xy[..., 1], d)
        det = a * e - b * c
        with np.errstate(divide="ignore", invalid="ignore"):
            step_x = (e * residual[..., 0] - b * residual[..., 1]) / det
            step_y = (a * residual[..., 1] - c * residual[..., 0]) / det
        xy = xy - np.stack([step_x, step_y], axis=-1)
        if np.nanmax(np.abs(np.stack([step_x, step_y])), initial=0.0) < UNDISTORT_TOL:
            break
    bad = ~np.all(np.abs(distort_normalized(xy, d) - target) < 1e-9, axis=-1)
    xy[bad] = np.nan
    return xy


def _normalise(uv: np.ndarray, fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    uv = np.asarray(uv, dtype=np.float64)
    return np.stack([(uv[..., 0] - cx) / fx, (uv[..., 1] - cy) / fy], axis=-1)


def _to_pixels(xy: np.ndarray, fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    return np.stack([xy[..., 0] * fx + cx, xy[..., 1] * fy + cy], axis=-1)


def distort_pixels(
    uv: np.ndarray, d: Distortion, *, fx: float, fy: float, cx: float, cy: float
) -> np.ndarray:
    """Ideal (pinhole) pixel coordinates [..., 2] -> where the distorting lens records them."""
    return _to_pixels(distort_normalized(_normalise(uv, fx, fy, cx, cy), d), fx, fy, cx, cy)


def undistort_pixels(
    uv: np.ndarray, d: Distortion, *, fx: float, fy: float, cx: float, cy: float
) -> np.ndarray:
    """Recorded (distorted) pixel coordinates [..., 2] -> ideal pinhole ones (NaN where the
    model cannot be inverted)."""
    return _to_pixels(undistort_normalized(_normalise(uv, fx, fy, cx, cy), d), fx, fy, cx, cy)


def distort_image(
    image: np.ndarray, d: Distortion, *, fx: float, fy: float, cx: float, cy: float
) -> np.ndarray:
    """An ideal pinhole image [H, W, C] (uint8) as the distorting lens records it.

    Each output pixel centre is undistorted to its ideal position and the input is sampled there
    bilinearly. Where that position falls outside the input (a barrel lens sees more than the
    pinhole did) the nearest edge pixel is repeated: the ideal camera never saw those rays."""
    from scipy.ndimage import map_coordinates

    if d.is_identity:
        return image.copy()
    h, w = image.shape[:2]
    vv, uu = np.meshgrid(np.arange(h) + 0.5, np.arange(w) + 0.5, indexing="ij")
    src = undistort_pixels(np.stack([uu, vv], axis=-1), d, fx=fx, fy=fy, cx=cx, cy=cy)
    # continuous (u, v) with centres at +0.5 -> array indices (row, column)
    rows = np.nan_to_num(src[..., 1] - 0.5, nan=-1.0)
    cols = np.nan_to_num(src[..., 0] - 0.5, nan=-1.0)
    out = np.empty_like(image)
    channels = image[..., None] if image.ndim == 2 else image
    target = out[..., None] if image.ndim == 2 else out
    for ch in range(channels.shape[-1]):
        sampled = map_coordinates(
            channels[..., ch].astype(np.float64), [rows, cols], order=1, mode="nearest"
        )
        target[..., ch] = np.clip(np.round(sampled), 0, 255).astype(image.dtype)
    return out
