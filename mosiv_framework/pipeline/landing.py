"""The ground's Coulomb coefficient read off the recorded landings, before any simulation.

A body's total momentum changes only through gravity and the external contacts, whatever
happens inside it. Over a window in which a body lands on the table and touches nothing else,

    J_n = m (v_n(b) - v_n(a)) + m g (t_b - t_a)      the table's normal impulse
    J_t = m |v_t(b) - v_t(a)|                         its tangential (friction) impulse

with v the centroid's velocity. Coulomb friction gives J_t <= mu J_n, with equality while the
body's contact slides throughout; a body that stops sliding, or whose contact stops while it
rolls or tumbles, gives less. So J_t / J_n of an isolated landing is a lower bound on mu, and
the largest over the landings is the estimate. The masses cancel. On recorded data a
neighbour's push or the frame differences can also take a reading above mu.

Identification starts the coefficient here with ``identify.ground_friction_start: landing``
(docs/PHYSICS.md, Ground friction): the data-independent start (the centre of 0-2) is ten
times Genesis's 0.1, and the observed frames, four of them after a landing, hardly move it
(docs/RESULTS.md, Future error on Genesis scenes).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from mosiv_framework.pipeline.params import point_spacing
from mosiv_framework.types import World

#: a body has landed once its lowest point is within this many point spacings of the table
LANDING_SPACINGS = 1.5
#: a landing counts only while no other body comes within this many point spacings of it:
#: a neighbour's push would enter the impulses
CLEAR_SPACINGS = 1.5
#: a landing whose normal velocity changes by less than this (m/s) is a touch, too small an
#: impulse for a ratio
MIN_NORMAL_CHANGE = 0.3


@dataclass(frozen=True)
class Landing:
    """One body's landing: the frame its lowest point reached the table, and J_t / J_n over
    the frames around it."""

    object_id: int
    frame: int
    ratio: float


def landings(
    points: dict[int, torch.Tensor],
    world: World,
    frames: int,
    *,
    clear_spacings: float = CLEAR_SPACINGS,
) -> list[Landing]:
    """Each body's first landing within the first ``frames`` frames of ``points`` (object id
    -> [F, N, 3] m) that is clear of the other bodies (no point of another within
    ``clear_spacings`` point spacings) and strong enough to read; a body that starts on the
    table, or lands too near the first or the last frame, is not read.

    The table is the plane z = ``world.ground_height``. Around the landing frame f the
    centroid's velocities are the differences f - 2 -> f - 1 and f + 1 -> f + 2, which stand
    for the midpoints f - 1.5 and f + 1.5, three frames apart; the table's impulse per unit
    mass between them is the velocity change less gravity's share, split into its normal (z)
    and tangential parts.
    """
    if world.ground_height is None:
        return []
    gravity = np.asarray(world.gravity, dtype=float)
    dt = 1.0 / world.fps
    clouds = {k: p[:frames].detach().cpu().double().numpy() for k, p in points.items()}
    out = []
    for k, cloud in clouds.items():
        if cloud.shape[1] < 2 or not np.isfinite(cloud).all():
            continue
        spacing = point_spacing(points[k][0])
        heights = cloud[:, :, 2] - world.ground_height
        touching = np.nonzero(heights.min(axis=1) < LANDING_SPACINGS * spacing)[0]
        if not len(touching):
            continue
        f = int(touching[0])
        if f < 2 or f + 2 >= len(cloud):
            continue
        if not _clear(k, clouds, range(f - 2, f + 3), clear_spacings * spacing):
            continue
        centroids = cloud.mean(axis=1)
        before = (centroids[f - 1] - centroids[f - 2]) / dt
        after = (centroids[f + 2] - centroids[f + 1]) / dt
        impulse = after - before - gravity * 3 * dt
        if float(after[2] - before[2]) < MIN_NORMAL_CHANGE or impulse[2] <= 0:
            continue
        out.append(Landing(k, f, float(np.linalg.norm(impulse[:2])) / float(impulse[2])))
    return out


def _clear(k: int, clouds: dict[int, np.ndarray], window: range, distance: float) -> bool:
    """Whether no other body comes within ``distance`` (m) of body ``k`` over ``window``."""
    from scipy.spatial import cKDTree

    for f in window:
        tree = cKDTree(clouds[k][f])
        for other, cloud in clouds.items():
            if other != k and tree.query(cloud[f], k=1)[0].min() < distance:
                return False
    return True


def landing_friction(
    points: dict[int, torch.Tensor],
    world: World,
    frames: int,
    *,
    clear_spacings: float = CLEAR_SPACINGS,
) -> tuple[float | None, list[Landing]]:
    """The ground's Coulomb coefficient estimated from the landings in the first ``frames``
    frames (the largest J_t / J_n, clamped to 0-2), or None without a readable landing; and
    the landings it read."""
    found = landings(points, world, frames, clear_spacings=clear_spacings)
    if not found:
        return None, found
    return min(2.0, max(0.0, max(x.ratio for x in found))), found
