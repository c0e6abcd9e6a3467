"""benchmarks/contact_exposure.py: shares of particles near the other body, counted by hand on
two lattice blocks a known gap apart."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"


def _exposure():
    sys.path.insert(0, str(BENCHMARKS))
    try:
        from contact_exposure import exposure
    finally:
        sys.path.remove(str(BENCHMARKS))
    return exposure


def _block(layers: int, x0: float, h: float) -> np.ndarray:
    """``layers`` planes of 4 x 4 points, spacing ``h``, the first plane at x = ``x0``."""
    x, y, z = np.meshgrid(x0 + np.arange(layers) * h, np.arange(4) * h, np.arange(4) * h)
    return np.stack([x.ravel(), y.ravel(), z.ravel()], axis=1)


def test_only_the_facing_layers_are_near_and_touching_needs_one_spacing():
    exposure = _exposure()
    h = 0.008
    a = _block(5, 0.0, h)  # planes at x = 0 .. 4h
    b = _block(5, 4 * h + 1.5 * h, h)  # facing plane 1.5 h past a's last one
    apart = _block(5, 4 * h + 3.0 * h, h)  # 3 h past it
    positions = np.stack([np.concatenate([a, b]), np.concatenate([a, apart])])
    result = exposure(positions, [len(a), len(b)], radius=2 * h, touch=h)
    # frame 0: within 2h of the other block are a's last plane and b's first (1.5 h);
    # the next planes are 2.5 h away; frame 1: nothing within 2 h
    assert result["near_share"] == pytest.approx([2 * 16 / 160, 0.0])
    assert result["touching"] == [False, False]  # 1.5 h is not within one spacing
    touching = exposure(positions, [len(a), len(b)], radius=2 * h, touch=1.6 * h)
    assert touching["touching"] == [True, False]


def test_more_than_two_objects_are_refused():
    exposure = _exposure()
    with pytest.raises(ValueError, match="two objects"):
        exposure(np.zeros((1, 3, 3)), [1, 1, 1], radius=0.01, touch=0.01)
