"""Per-camera foreground from a static background: background estimate, colour distance, a
threshold (Otsu's or a set value) and morphological cleanup.

Every function works on one camera's video, uint8 [T, H, W, 3]; distances are Euclidean in
8-bit RGB units (0 .. 255 * sqrt(3)).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy import ndimage

#: frames (or image rows) per block in the whole-video steps below: the float32 working copies
#: stay a few blocks in size however long and large the clip (a 300-frame 1080p camera is
#: 1.9 GB as uint8, and a float32 copy of its RGB differences 22 GB), with the same results as
#: one pass, as every step works per pixel or per frame
BLOCK = 8


def estimate_background(video: np.ndarray, frames: Sequence[int] | None = None) -> np.ndarray:
    """Static background of one camera, float32 [H, W, 3]: the per-pixel temporal median.

    Args:
        video: uint8 [T, H, W, 3].
        frames: frame indices that show the empty scene (or mostly so); None uses every frame.
            The median is right wherever each pixel shows the background in more than half of
            the frames used, so a clip in which an object rests for most of it needs frames
            that do not show it.
    """
    if frames is not None:
        video = video[list(frames)]
    out = np.empty(video.shape[1:], dtype=np.float32)
    rows = max(1, BLOCK * video.shape[1] // max(1, len(video)))  # about BLOCK frames' worth
    for top in range(0, video.shape[1], rows):
        block = video[:, top : top + rows].astype(np.float32)
        out[top : top + rows] = np.median(block, axis=0, overwrite_input=True)
    return out


def colour_distance(video: np.ndarray, background: np.ndarray) -> np.ndarray:
    """Per-pixel Euclidean RGB distance to the background, float32 [T, H, W]."""
    background = background.astype(np.float32)[None]
    out = np.empty(video.shape[:3], dtype=np.float32)
    for start in range(0, len(video), BLOCK):
        diff = video[start : start + BLOCK].astype(np.float32) - background
        out[start : start + BLOCK] = np.sqrt((diff * diff).sum(axis=-1))
    return out


def otsu_threshold(values: np.ndarray, bins: int = 256) -> float:
    """Otsu's threshold of ``values``: the cut that maximises the between-class variance of
    the two classes below and above it (Otsu 1979). Returns the cut as a value of ``values``."""
    values = np.asarray(values, dtype=np.float64).ravel()
    hi = float(values.max()) if values.size else 0.0
    if hi <= 0.0:
        return 0.0
    hist, edges = np.histogram(values, bins=bins, range=(0.0, hi))
    centres = 0.5 * (edges[:-1] + edges[1:])
    weight_below = np.cumsum(hist)
    weight_above = weight_below[-1] - weight_below
    sum_below = np.cumsum(hist * centres)
    mean_below = sum_below / np.maximum(weight_below, 1)
    mean_above = (sum_below[-1] - sum_below) / np.maximum(weight_above, 1)
    between = weight_below * weight_above * (mean_below - mean_above) ** 2
    # the cut after bin i separates bins <= i from bins > i; empty bins between two modes give
    # a plateau of equal scores, whose middle keeps the cut away from both modes' tails
    best = np.flatnonzero(between >= between.max() * (1.0 - 1e-9))
    return float(0.5 * (edges[best[0] + 1] + edges[best[-1] + 1]))


#: the background's noise is measured on the pixels farther than this (pixels) from any
#: candidate object (``noise_threshold``): the objects and their rims stay out of it
NOISE_MARGIN_PX = 3
#: the noise level is this quantile of those pixels' distances: compression and resampling
#: noise is heavy-tailed (at 48 px through H.264 the 99.9th percentile is 10x the median), so
#: a Gaussian's spread from the median would sit inside it
NOISE_QUANTILE = 0.99
#: the threshold is this multiple of the noise level. Chosen on development captures (seeds 7
#: and 8 of benchmarks/capture_roundtrip.py --quick, 48 px): it puts the threshold at 18-30
#: there, where the masks come closest to the scene's
NOISE_FACTOR = 2.5
#: the automatic thresholds ``foreground`` can pick
AUTO_THRESHOLDS = ("noise", "otsu")


def noise_threshold(values: np.ndarray, floor: float = 0.0) -> float:
    """A cut just above the background's own noise, for one camera's distances [T, H, W].

    The candidate objects are the blobs (at least 3x3 pixels) above a Gaussian bound on the
    noise (median + 6 x 1.4826 x MAD of all distances, at least ``floor``): dim and bright
    objects alike, while the codec's isolated specks stay background. The noise level is the
    NOISE_QUANTILE of the distances farther than NOISE_MARGIN_PX from any candidate, and the
    cut NOISE_FACTOR times it. Right however many objects of whatever contrasts are in view
    (Otsu's cut, made for two classes, falls between a dim object and a bright one when both
    are there), and above compression and resampling noise, whose tail a Gaussian misses."""
    values = np.asarray(values, dtype=np.float32)
    if values.ndim != 3 or not values.size:
        raise ValueError(f"distances must be [T, H, W], got {list(values.shape)}")
    work = values.copy()  # one working copy, reordered by the medians in place
    centre = float(np.median(work, overwrite_input=True))
    np.abs(np.subtract(values, centre, out=work), out=work)
    bound = max(centre + 6.0 * 1.4826 * float(np.median(work, overwrite_input=True)), floor)
    del work
    blobs = ndimage.binary_opening(values > bound, structure=np.ones((1, 3, 3), dtype=bool))
    size = 2 * NOISE_MARGIN_PX + 1
    near = ndimage.binary_dilation(blobs, structure=np.ones((1, size, size), dtype=bool))
    far = values[~near] if not near.all() else values.ravel().copy()  # reordered below
    return NOISE_FACTOR * float(np.quantile(far, NOISE_QUANTILE, overwrite_input=True))


def trim_rim(distance: np.ndarray, mask: np.ndarray, fraction: float) -> np.ndarray:
    """``mask`` without the rim pixels an object covers by less than ``fraction``, bool
    [T, H, W].

    A rim pixel (in the mask, next to a pixel outside it) that an object covers by a fraction
    a of its area differs from the background by about a times the object's own distance (the
    colours mix linearly); the object's distance there is the mean over the pixel's neighbours
    inside the rim. With fraction 0.5 a rim pixel counts where the object covers at least half
    of it: the rule by which a renderer or an annotator draws a mask. A threshold just above
    the noise alone also takes the mixed pixels, which at a few pixels across an object makes
    its mask a third larger. Interior pixels stay whatever their distance (a textured object
    is not cut), and so does a rim pixel with no interior neighbour (a thin part)."""
    out = np.empty(mask.shape, dtype=bool)
    for start in range(0, len(mask), BLOCK):  # every step below acts on each frame alone
        part = slice(start, start + BLOCK)
        out[part] = _trim_rim_block(distance[part], mask[part], fraction)
    return out


def _trim_rim_block(distance: np.ndarray, mask: np.ndarray, fraction: float) -> np.ndarray:
    """``trim_rim`` on a block of frames."""
    inner = ndimage.binary_erosion(mask, structure=np.ones((1, 3, 3), dtype=bool))
    rim = mask & ~inner
    weight = inner.astype(np.float32)
    around = ndimage.uniform_filter(distance * weight, size=(1, 3, 3), mode="constant")
    count = ndimage.uniform_filter(weight, size=(1, 3, 3), mode="constant")
    own = around / np.maximum(count, 1e-6)
    covered = (count < 1e-6) | (distance >= fraction * own)
    return inner | (rim & covered)


def _disk(radius: int) -> np.ndarray:
    """A 2D disk structuring element of ``radius`` pixels, as a [1, 2r+1, 2r+1] stack that acts
    on each frame of a [T, H, W] video separately. Offsets with x^2 + y^2 <= r (r + 1) count,
    so radius 1 is the full 3x3 square (a cross would cut the corners of every shape)."""
    r = np.arange(-radius, radius + 1)
    disk = (r[:, None] ** 2 + r[None, :] ** 2) <= radius * (radius + 1)
    return disk[None]


def clean_mask(mask: np.ndarray, *, open_px: int, close_px: int) -> np.ndarray:
    """Morphological cleanup of a bool [T, H, W] foreground, frame by frame: opening removes
    specks smaller than ``open_px``, closing bridges gaps up to ``close_px`` (both radii in
    pixels, 0 skips the step), then holes enclosed by foreground are filled."""
    out = mask
    if open_px > 0:
        out = ndimage.binary_opening(out, structure=_disk(open_px))
    if close_px > 0:
        # pad so the closing does not eat the foreground at the image border
        pad = ((0, 0), (close_px, close_px), (close_px, close_px))
        padded = np.pad(out, pad, mode="edge")
        closed = ndimage.binary_closing(padded, structure=_disk(close_px))
        out = closed[:, close_px:-close_px, close_px:-close_px]
    holes = np.zeros((3, 3, 3), dtype=bool)
    holes[1] = ndimage.generate_binary_structure(2, 1)
    return ndimage.binary_fill_holes(out, structure=holes)


def foreground(
    video: np.ndarray,
    background: np.ndarray,
    *,
    threshold: float | None,
    min_threshold: float,
    open_px: int,
    close_px: int,
    auto: str = "noise",
    edge_fraction: float = 0.0,
) -> tuple[np.ndarray, float]:
    """Foreground of one camera, bool [T, H, W], and the distance threshold used.

    Args:
        video: uint8 [T, H, W, 3]; background: float [H, W, 3].
        threshold: RGB distance above which a pixel is foreground; None picks it from this
            camera's distances by ``auto`` ("noise": ``noise_threshold``; "otsu":
            ``otsu_threshold``), raised to at least ``min_threshold`` so that sensor noise
            alone (no object in view) is never foreground.
        open_px, close_px: radii of the cleanup (see ``clean_mask``).
        edge_fraction: keep the mask's rim pixels that reach this fraction of the object's
            distance next to them (``trim_rim``); 0 keeps every pixel above the threshold.
    """
    distance = colour_distance(video, background)
    if threshold is None:
        if auto not in AUTO_THRESHOLDS:
            raise ValueError(f"auto threshold {auto!r}: valid values are {list(AUTO_THRESHOLDS)}")
        if auto == "noise":
            threshold = max(noise_threshold(distance, floor=min_threshold), min_threshold)
        else:
            threshold = max(otsu_threshold(distance), min_threshold)
    mask = distance > threshold
    if edge_fraction > 0.0:
        mask = trim_rim(distance, mask, edge_fraction)
    return clean_mask(mask, open_px=open_px, close_px=close_px), float(threshold)
