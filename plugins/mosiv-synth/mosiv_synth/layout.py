"""Initial placement and velocities that make the objects collide in mid-air at a chosen time.

Before the collision every object flies freely under a uniform acceleration ``a`` (gravity,
plus steady wind when concealed), so its centroid follows x(t) = x0 + v0 t + a t^2 / 2 and the
launch velocity that reaches a target T at time t_c is v0 = (T - x0 - a t_c^2 / 2) / t_c.
A uniform acceleration cancels in relative motion, so the offset between two objects moves on
a straight line at constant velocity. Choosing the targets so that each offset at t_c is
parallel to the offset at t = 0 makes every approach a straight, head-on one along a known
direction u, and the exact distance at which two rigidly translating particle clouds first touch
along u (``first_contact_distance``) then makes them touch at t_c exactly: objects 1 and 2 touch
at t_c; a third object flies at the pair (frozen at its t_c positions) and touches it at t_c up
to the pair's own motion during contact.

Drag (when concealed) is not a uniform acceleration; it slows the approach, so the first
contact happens somewhat after the planned frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from mosiv_framework.scene.protocol import launch_velocity

# collision point: near the table centre, 0.22-0.32 m above it, so the fall after the collision
# lasts ~0.2-0.3 s and the objects land and settle inside a 30-frame clip at 24 fps
COLLISION_HEIGHT = (0.22, 0.32)
COLLISION_XY = 0.04
# horizontal gap between the bounding spheres at launch (m): 0.12-0.2 m covered in t_c gives
# approach speeds of ~0.5-1 m/s per object
LAUNCH_GAP = (0.12, 0.2)
LAUNCH_RISE = (-0.04, 0.1)  # launch height relative to the collision height (m)
MARGIN = 0.02  # clearance to walls and table kept by the planned flight (m)


@dataclass
class Layout:
    """Planned initial state: per object its start centroid x0 [3] (m), launch velocity v0
    [3] (m/s) and the centroid target at the collision time; plus the collision time (s) and
    the collision point (m)."""

    starts: np.ndarray  # [K, 3]
    velocities: np.ndarray  # [K, 3]
    targets: np.ndarray  # [K, 3]
    collision_time: float
    collision_point: np.ndarray

    def centroid_at(self, t: float, acceleration) -> np.ndarray:
        """Centroids [K, 3] (m) at time t (s) under free flight with ``acceleration`` (m/s^2)."""
        a = np.asarray(acceleration, dtype=np.float64)
        return self.starts + self.velocities * t + 0.5 * a * t * t


def first_contact_distance(
    fixed: np.ndarray, moving: np.ndarray, direction: np.ndarray, contact: float
) -> float:
    """Largest d at which ``moving`` (points relative to its centroid) placed at ``d *
    direction`` from ``fixed``'s origin comes within ``contact`` (m) of ``fixed``.

    Coming in from far along ``direction``, this is where the clouds first touch. For each
    pair w = q - p, |w + d u| = c has the roots d = -w.u +- sqrt((w.u)^2 - |w|^2 + c^2).
    """
    u = np.asarray(direction, dtype=np.float64)
    u = u / np.linalg.norm(u)
    best = -np.inf
    step = max(1, (1 << 21) // max(1, len(moving)))
    for start in range(0, len(fixed), step):
        w = moving[None, :, :] - fixed[start : start + step, None, :]  # [p, q, 3]
        wu = w @ u
        disc = wu * wu - np.einsum("pqk,pqk->pq", w, w) + contact * contact
        roots = np.where(disc >= 0.0, -wu + np.sqrt(np.clip(disc, 0.0, None)), -np.inf)
        best = max(best, float(roots.max()))
    if not np.isfinite(best):
        raise ValueError("the clouds never touch along this direction (empty cloud?)")
    return best


def plan_collision(
    clouds: list[np.ndarray],
    *,
    collision_time: float,
    acceleration,
    contact: float,
    domain_lower,
    domain_upper,
    ground_height: float | None,
    rng: np.random.Generator,
    attempts: int = 200,
) -> Layout:
    """Plan start centroids and launch velocities for 2 or 3 objects (``clouds``: particle
    positions [N_k, 3] relative to each centroid, m) to touch at ``collision_time`` (s).

    Raises ValueError when no draw keeps every flight inside the domain and above the table.
    """
    k = len(clouds)
    if k not in (2, 3):
        raise ValueError(f"plan_collision handles 2 or 3 objects, got {k}")
    radii = np.array([np.linalg.norm(c, axis=1).max() for c in clouds])
    for _ in range(attempts):
        layout = _draw(clouds, radii, collision_time, acceleration, contact, rng)
        if _flight_ok(layout, radii, acceleration, domain_lower, domain_upper, ground_height):
            if _apart_at_start(layout, clouds, contact):
                return layout
    raise ValueError(
        f"no collision layout with collision_time={collision_time:.3f} s keeps {k} objects "
        f"(bounding radii {np.round(radii, 3).tolist()} m) inside the domain "
        f"{list(domain_lower)}..{list(domain_upper)}; choose an earlier collision_frame"
    )


def _draw(clouds, radii, t_c, acceleration, contact, rng) -> Layout:
    k = len(clouds)
    point = np.array(
        [*rng.uniform(-COLLISION_XY, COLLISION_XY, size=2), rng.uniform(*COLLISION_HEIGHT)]
    )
    base = rng.uniform(0.0, 2.0 * np.pi)
    angles = base + 2.0 * np.pi * np.arange(k) / k + rng.uniform(-0.25, 0.25, size=k)
    starts = np.empty((k, 3))
    for i, ang in enumerate(angles):
        reach = radii[i] + rng.uniform(*LAUNCH_GAP)
        starts[i] = point + reach * np.array([np.cos(ang), np.sin(ang), 0.0])
        starts[i, 2] += rng.uniform(*LAUNCH_RISE)
    targets = np.empty((k, 3))
    # objects 1 and 2: head-on along the line through their starts, touching at t_c
    u = starts[1] - starts[0]
    u /= np.linalg.norm(u)
    d = first_contact_distance(clouds[0], clouds[1], u, contact)
    targets[0] = point - 0.5 * d * u
    targets[1] = point + 0.5 * d * u
    if k == 3:
        # object 3 flies at the pair's midpoint along the line from its start
        pair = np.concatenate([clouds[0] + targets[0] - point, clouds[1] + targets[1] - point])
        u3 = starts[2] - 0.5 * (starts[0] + starts[1])
        u3 /= np.linalg.norm(u3)
        targets[2] = point + first_contact_distance(pair, clouds[2], u3, contact) * u3
    velocities = np.stack(
        [launch_velocity(s, g, t_c, acceleration) for s, g in zip(starts, targets)]
    )
    return Layout(starts, velocities, targets, t_c, point)


def _flight_ok(layout, radii, acceleration, lower, upper, ground) -> bool:
    """Bounding spheres stay MARGIN inside the walls and above the table until t_c."""
    lo = np.asarray(lower, dtype=np.float64) + MARGIN
    hi = np.asarray(upper, dtype=np.float64) - MARGIN
    floor = max(lo[2], (ground if ground is not None else -np.inf) + MARGIN)
    for t in np.linspace(0.0, layout.collision_time, 25):
        c = layout.centroid_at(t, acceleration)
        if np.any(c[:, :2] - radii[:, None] < lo[:2]) or np.any(c[:, :2] + radii[:, None] > hi[:2]):
            return False
        if np.any(c[:, 2] - radii < floor) or np.any(c[:, 2] + radii > hi[2]):
            return False
    return True


def _apart_at_start(layout, clouds, contact) -> bool:
    """No two objects touch at t = 0."""
    placed = [c + x0 for c, x0 in zip(clouds, layout.starts)]
    for i in range(len(placed)):
        for j in range(i + 1, len(placed)):
            gap = cKDTree(placed[j]).query(placed[i])[0].min()
            if gap <= 2.0 * contact:
                return False
    return True
