"""Lens distortion of the OpenCV / COLMAP family, its inverse, and frames remapped through it.

Both models act on normalised camera coordinates ``(x, y) = ((u - cx) / fx, (v - cy) / fy)``.
The perspective model (``model="opencv"``; OpenCV's rational model, COLMAP's FULL_OPENCV)::

    r2 = x^2 + y^2
    radial = (1 + k1 r2 + k2 r2^2 + k3 r2^3) / (1 + k4 r2 + k5 r2^2 + k6 r2^3)
    x_d = x radial + 2 p1 x y + p2 (r2 + 2 x^2)
    y_d = y radial + p1 (r2 + 2 y^2) + 2 p2 x y

COLMAP's SIMPLE_RADIAL (k), RADIAL (k1, k2), OPENCV (k1, k2, p1, p2) and FULL_OPENCV and
nerfstudio's k1, k2, k3, p1, p2 are all special cases; ``k1 < 0`` is barrel distortion (the
image edge pulled inward). The fisheye model (``model="fisheye"``; OpenCV's fisheye module,
COLMAP's SIMPLE_RADIAL_FISHEYE, RADIAL_FISHEYE and OPENCV_FISHEYE, nerfstudio's OPENCV_FISHEYE)
bends the angle from the optical axis, theta = atan(r), so that a lens can see 180 degrees::

    theta_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8)
    (x_d, y_d) = (x, y) theta_d / r

All its coefficients zero is the equidistant fisheye, not a pinhole. Both are radial maps
``(x, y) radial(r2)`` plus the tangential terms, so one Jacobian serves both. The forward map
has no closed-form inverse: ``undistort_points`` runs Newton's method on its 2x2 Jacobian, which
reaches 1e-12 in a few steps where the fixed-point iteration ``x <- (x_d - tangential) /
radial`` needs dozens and stalls for strong lenses.

Undistorting a frame needs only the forward map (each pinhole pixel looks up where the lens put
it); distorting one (what ``mosiv data capture`` records) needs the inverse. Pixel coordinates
follow docs/SCENE_FORMAT.md and COLMAP: pixel centres at integer + 0.5. Functions that take
intrinsics ``k`` accept anything with ``fx, fy, cx, cy`` (and ``width, height`` for whole
frames): an ``Intrinsics`` or a ``scene.cameras.Camera``.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
import torch

#: coefficient names, in the order of ``Distortion`` fields (OpenCV's order)
COEFFICIENTS = ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")
#: the lens models: perspective (rational radial + tangential) and fisheye (radial in angle)
LENS_MODELS = ("opencv", "fisheye")
#: the coefficients a fisheye lens has (theta^2 .. theta^8)
FISHEYE_COEFFICIENTS = ("k1", "k2", "k3", "k4")
#: Newton iterations of the inverse; moderate lenses converge to 1e-12 in fewer than 10
UNDISTORT_ITERATIONS = 30
#: stop once every point moved less than this (normalised units) in one Newton step
UNDISTORT_TOL = 1e-14
#: below this r^2 the fisheye's radial factor is its series 1 + (k1 - 1/3) r^2 (theta_d / r is
#: 0 / 0 at the axis): the factor's error, O(r^4), is below float64 rounding there; its
#: derivative's, O(r^2) relative, is 1e-8, and the Jacobian multiplies it by x^2 < 1e-8)
FISHEYE_SERIES_R2 = 1e-8


@dataclass(frozen=True)
class Distortion:
    """A lens: ``model`` "opencv" (radial k1, k2, k3 over k4, k5, k6 and tangential p1, p2;
    all zero = a pinhole lens) or "fisheye" (k1..k4 on the angle theta; p1, p2, k5, k6 zero)."""

    k1: float = 0.0
    k2: float = 0.0
    p1: float = 0.0
    p2: float = 0.0
    k3: float = 0.0
    k4: float = 0.0
    k5: float = 0.0
    k6: float = 0.0
    model: str = "opencv"

    def __post_init__(self) -> None:
        if self.model not in LENS_MODELS:
            raise ValueError(f"lens model {self.model!r}: choose one of {', '.join(LENS_MODELS)}")
        if self.model == "fisheye":
            extra = {k: getattr(self, k) for k in ("p1", "p2", "k5", "k6") if getattr(self, k)}
            if extra:
                raise ValueError(
                    f"a fisheye lens has only {', '.join(FISHEYE_COEFFICIENTS)}; got {extra}"
                )

    @classmethod
    def from_mapping(cls, data: Mapping[str, float], model: str = "opencv") -> Distortion:
        return cls(**{k: float(data.get(k, 0.0)) for k in COEFFICIENTS}, model=model)

    @classmethod
    def parse(cls, text: str) -> Distortion:
        """``"k1,k2"`` or ``"k1,k2,p1,p2"`` (OpenCV), or ``"fisheye:k1[,k2[,k3[,k4]]]"``
        (ValueError naming the text otherwise)."""
        fisheye = text.strip().lower().startswith("fisheye:")
        body = text.split(":", 1)[1] if fisheye else text
        parts = [p.strip() for p in body.split(",") if p.strip()]
        valid = 1 <= len(parts) <= 4 if fisheye else len(parts) in (2, 4)
        if not valid:
            raise ValueError(
                f"distortion {text!r}: give k1,k2 or k1,k2,p1,p2 (OpenCV), or "
                "fisheye:k1[,k2[,k3[,k4]]]"
            )
        try:
            values = [float(p) for p in parts]
        except ValueError:
            raise ValueError(f"distortion {text!r}: coefficients must be numbers") from None
        if not all(np.isfinite(values)):
            raise ValueError(f"distortion {text!r}: coefficients must be finite numbers")
        if fisheye:
            return cls.from_mapping(dict(zip(FISHEYE_COEFFICIENTS, values)), model="fisheye")
        return cls(*values)

    @property
    def is_zero(self) -> bool:
        """A pinhole lens: nothing to undo (an all-zero fisheye is not one)."""
        return self.model == "opencv" and all(getattr(self, k) == 0.0 for k in COEFFICIENTS)

    @property
    def radial_only(self) -> bool:
        """Only k1 and k2 of the perspective model: what COLMAP's RADIAL model can hold."""
        rest = ("p1", "p2", "k3", "k4", "k5", "k6")
        return self.model == "opencv" and all(getattr(self, k) == 0.0 for k in rest)

    @property
    def polynomial(self) -> bool:
        """A perspective lens without the rational denominator (k4 = k5 = k6 = 0): what
        COLMAP's OPENCV model and nerfstudio's perspective cameras can hold."""
        return self.model == "opencv" and self.k4 == self.k5 == self.k6 == 0.0

    @property
    def coefficients(self) -> tuple[float, ...]:
        """The coefficients in ``COEFFICIENTS`` order (without the model)."""
        return tuple(getattr(self, k) for k in COEFFICIENTS)

    def as_dict(self) -> dict[str, float | str]:
        return {"model": self.model, **{k: getattr(self, k) for k in COEFFICIENTS}}


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics (pixels) of a width x height image."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float

    def resized(self, width: int, height: int) -> Intrinsics:
        """The same camera for its frames resampled to ``width`` x ``height`` pixels (pixel
        centres at integer + 0.5, so every coordinate scales by the size ratio)."""
        sx, sy = width / self.width, height / self.height
        return Intrinsics(width, height, self.fx * sx, self.fy * sy, self.cx * sx, self.cy * sy)


def _radial(r2: np.ndarray, d: Distortion) -> tuple[np.ndarray, np.ndarray]:
    """The radial factor (x_d = x radial + tangential) and its derivative d radial / d(r^2)."""
    if d.model == "fisheye":
        return _fisheye_radial(r2, d)
    num = 1.0 + r2 * (d.k1 + r2 * (d.k2 + r2 * d.k3))
    den = 1.0 + r2 * (d.k4 + r2 * (d.k5 + r2 * d.k6))
    dnum = d.k1 + r2 * (2.0 * d.k2 + 3.0 * d.k3 * r2)
    dden = d.k4 + r2 * (2.0 * d.k5 + 3.0 * d.k6 * r2)
    return num / den, (dnum * den - num * dden) / (den * den)


def _fisheye_radial(r2: np.ndarray, d: Distortion) -> tuple[np.ndarray, np.ndarray]:
    """theta_d / r and its derivative in r^2, with theta = atan(r) (OpenCV's fisheye)."""
    r2 = np.asarray(r2, dtype=np.float64)
    near = r2 < FISHEYE_SERIES_R2
    r = np.sqrt(np.where(near, 1.0, r2))  # 1 where the series applies: no 0 / 0 below
    theta = np.arctan(r)
    t2 = theta * theta
    theta_d = theta * (1.0 + t2 * (d.k1 + t2 * (d.k2 + t2 * (d.k3 + t2 * d.k4))))
    dtheta_d = 1.0 + t2 * (3.0 * d.k1 + t2 * (5.0 * d.k2 + t2 * (7.0 * d.k3 + t2 * 9.0 * d.k4)))
    dtheta_d_dr = dtheta_d / (1.0 + r * r)  # d theta / dr = 1 / (1 + r^2)
    radial = theta_d / r
    dradial = (dtheta_d_dr * r - theta_d) / (2.0 * r * r * r)  # (d radial / dr) / (2 r)
    series = d.k1 - 1.0 / 3.0  # theta_d / r = 1 + (k1 - 1/3) r^2 + O(r^4)
    return np.where(near, 1.0 + series * r2, radial), np.where(near, series, dradial)


def distort_points(xy: np.ndarray, d: Distortion) -> np.ndarray:
    """Normalised ideal coordinates [..., 2] -> distorted ones [..., 2] (the forward map)."""
    xy = np.asarray(xy, dtype=np.float64)
    x, y = xy[..., 0], xy[..., 1]
    r2 = x * x + y * y
    radial, _ = _radial(r2, d)
    xd = x * radial + 2.0 * d.p1 * x * y + d.p2 * (r2 + 2.0 * x * x)
    yd = y * radial + d.p1 * (r2 + 2.0 * y * y) + 2.0 * d.p2 * x * y
    return np.stack([xd, yd], axis=-1)


def _jacobian(x: np.ndarray, y: np.ndarray, d: Distortion) -> tuple[np.ndarray, ...]:
    """Entries (a, b, c, e) of d(x_d, y_d)/d(x, y) = [[a, b], [c, e]]."""
    r2 = x * x + y * y
    radial, dradial = _radial(r2, d)  # dradial: d radial / d(r^2)
    a = radial + 2.0 * x * x * dradial + 2.0 * d.p1 * y + 6.0 * d.p2 * x
    b = 2.0 * x * y * dradial + 2.0 * d.p1 * x + 2.0 * d.p2 * y
    e = radial + 2.0 * y * y * dradial + 6.0 * d.p1 * y + 2.0 * d.p2 * x
    return a, b, b, e


def undistort_points(xy_d: np.ndarray, d: Distortion) -> np.ndarray:
    """Normalised distorted coordinates [..., 2] -> ideal ones [..., 2] (the inverse map).

    Newton's method from the distorted point itself; points where the lens model folds over
    (beyond its invertible radius) come back as NaN rather than as a wrong answer."""
    target = np.asarray(xy_d, dtype=np.float64)
    if d.is_zero:
        return target.copy()
    xy = target.copy()
    # beyond the fold (a fisheye's corner past 90 degrees, say) the iterates leave the model's
    # domain: inf and NaN there are expected and end as NaN below, without warnings
    with np.errstate(all="ignore"):
        for _ in range(UNDISTORT_ITERATIONS):
            residual = distort_points(xy, d) - target
            a, b, c, e = _jacobian(xy[..., 0], xy[..., 1], d)
            det = a * e - b * c
            step_x = (e * residual[..., 0] - b * residual[..., 1]) / det
            step_y = (a * residual[..., 1] - c * residual[..., 0]) / det
            xy = xy - np.stack([step_x, step_y], axis=-1)
            if np.nanmax(np.abs(np.stack([step_x, step_y])), initial=0.0) < UNDISTORT_TOL:
                break
        bad = ~np.all(np.abs(distort_points(xy, d) - target) < 1e-9, axis=-1)
    xy[bad] = np.nan
    return xy


def normalise(uv: np.ndarray, k) -> np.ndarray:
    """Pixel coordinates [..., 2] -> normalised camera coordinates."""
    uv = np.asarray(uv, dtype=np.float64)
    return np.stack([(uv[..., 0] - k.cx) / k.fx, (uv[..., 1] - k.cy) / k.fy], axis=-1)


def to_pixels(xy: np.ndarray, k) -> np.ndarray:
    """Normalised camera coordinates [..., 2] -> pixel coordinates."""
    return np.stack([xy[..., 0] * k.fx + k.cx, xy[..., 1] * k.fy + k.cy], axis=-1)


def distort_pixels(uv: np.ndarray, d: Distortion, k) -> np.ndarray:
    """Ideal (pinhole) pixel coordinates [..., 2] -> where the distorting lens records them."""
    return to_pixels(distort_points(normalise(uv, k), d), k)


def undistort_pixels(uv: np.ndarray, d: Distortion, k) -> np.ndarray:
    """Recorded (distorted) pixel coordinates [..., 2] -> ideal pinhole ones (NaN where the
    model cannot be inverted)."""
    return to_pixels(undistort_points(normalise(uv, k), d), k)


def pixel_grid(k) -> np.ndarray:
    """[H, W, 2] pixel coordinates (u, v) of every pixel centre of a k.width x k.height image."""
    vv, uu = np.meshgrid(np.arange(k.height) + 0.5, np.arange(k.width) + 0.5, indexing="ij")
    return np.stack([uu, vv], axis=-1)


def remap(
    frames: np.ndarray,
    uv: np.ndarray,
    *,
    outside: str = "black",
    chunk: int = 16,
    out: np.ndarray | None = None,
):
    """Sample frames uint8 [T, H, W, C] bilinearly at pixel coordinates uv [H', W', 2]
    -> uint8 [T, H', W', C]. Where uv leaves the image (or is NaN) ``outside`` decides:
    ``"black"`` reads zeros, ``"edge"`` repeats the nearest edge pixel. ``out``: the array to
    write into, which may be ``frames`` itself (each block of frames is read before it is
    written), so that a long clip is not held twice."""
    t, h, w, c = frames.shape
    # grid_sample with align_corners=False uses the same pixel-centre convention (centre of
    # pixel i at i + 0.5 in a [0, W] span), so the mapping to [-1, 1] is a plain rescale;
    # NaN (no inverse) goes far outside, where ``outside`` applies
    uv = np.nan_to_num(np.asarray(uv, dtype=np.float64), nan=-1e6)
    grid = np.empty(uv.shape, dtype=np.float32)
    grid[..., 0] = 2.0 * uv[..., 0] / w - 1.0
    grid[..., 1] = 2.0 * uv[..., 1] / h - 1.0
    grid_t = torch.from_numpy(grid)[None]
    padding = {"black": "zeros", "edge": "border"}[outside]
    shape = (t,) + uv.shape[:2] + (c,)
    if out is None:
        out = np.empty(shape, dtype=np.uint8)
    elif out.shape != shape or out.dtype != np.uint8 or not out.flags.writeable:
        raise ValueError(
            f"out: a writable uint8 {list(shape)} array expected, got {out.dtype} "
            f"{list(out.shape)}{'' if out.flags.writeable else ', read-only'}"
        )
    elif out is not frames and np.shares_memory(out, frames):
        raise ValueError("out: overlaps the frames without being them; give frames or a new array")
    for start in range(0, t, chunk):
        part = torch.from_numpy(np.ascontiguousarray(frames[start : start + chunk]))
        src = part.permute(0, 3, 1, 2).to(torch.float32)
        res = torch.nn.functional.grid_sample(
            src, grid_t.expand(src.shape[0], -1, -1, -1), mode="bilinear",
            padding_mode=padding, align_corners=False,
        )  # fmt: skip
        res = res.permute(0, 2, 3, 1).round().clamp(0, 255).to(torch.uint8)
        out[start : start + chunk] = res.numpy()
    return out


def undistort_frames(frames: np.ndarray, k, d: Distortion, *, in_place: bool = False) -> np.ndarray:
    """Frames [T, H, W, C] seen through lens ``d`` -> the same frames through a pinhole camera
    with the same intrinsics ``k``; rays the lens did not record read black. ``in_place``:
    overwrite ``frames`` (a writable uint8 array) instead of returning a new array."""
    if d.is_zero:
        return frames
    out = frames if in_place else None
    return remap(frames, distort_pixels(pixel_grid(k), d, k), outside="black", out=out)


def distort_frames(frames: np.ndarray, k, d: Distortion) -> np.ndarray:
    """Pinhole frames [T, H, W, C] -> what lens ``d`` with intrinsics ``k`` records (the
    inverse of ``undistort_frames`` up to interpolation). Where a recorded pixel looks past the
    pinhole image (a barrel lens sees more) the nearest edge pixel is repeated: the ideal camera
    never saw those rays, and a black wedge would look like an object to a segmenter."""
    if d.is_zero:
        return frames.copy()
    return remap(frames, undistort_pixels(pixel_grid(k), d, k), outside="edge")
