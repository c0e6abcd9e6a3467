"""Single change-point detectors for short residual series (a few to a few hundred frames).

Both are exact: every split is tried, so no tuning or library is needed at these lengths.
``hinge_change_point`` finds where a flat residual starts to rise (the onset of an unmodelled
effect); ``mean_shift_change_point`` finds a step in the mean.
"""

from __future__ import annotations

import numpy as np


def hinge_change_point(series: np.ndarray) -> tuple[int, float]:
    """Onset of a rise: least-squares fit of y = a (t < tau), a + b (t - tau) (t >= tau).

    Returns (tau, sse). Every tau in 0..T-2 is tried; for each, a and b come from linear least
    squares, so the answer is the exact single-change-point optimum of the hinge model.
    """
    y = np.asarray(series, dtype=np.float64)
    n = y.shape[0]
    if n < 3:
        return 0, 0.0
    t = np.arange(n, dtype=np.float64)
    best = (0, np.inf)
    for tau in range(n - 1):
        design = np.stack([np.ones(n), np.maximum(t - tau, 0.0)], axis=1)
        coef, *_ = np.linalg.lstsq(design, y, rcond=None)
        sse = float(((design @ coef - y) ** 2).sum())
        if sse < best[1] - 1e-15 * max(1.0, abs(best[1]) if np.isfinite(best[1]) else 1.0):
            best = (tau, sse)
    return best


def mean_shift_change_point(series: np.ndarray) -> tuple[int, float]:
    """Single change in mean: the split k minimising the two segments' summed squared errors.

    Returns (k, sse) where the second segment starts at index k (1..T-1), computed from
    cumulative sums in O(T).
    """
    y = np.asarray(series, dtype=np.float64)
    n = y.shape[0]
    if n < 2:
        return 0, 0.0
    c1, c2 = np.cumsum(y), np.cumsum(y**2)
    best = (1, np.inf)
    for k in range(1, n):
        left = c2[k - 1] - c1[k - 1] ** 2 / k
        right = (c2[-1] - c2[k - 1]) - (c1[-1] - c1[k - 1]) ** 2 / (n - k)
        if left + right < best[1]:
            best = (k, float(left + right))
    return best
