"""Simulation particles inside a closed triangle mesh, and random rotations.

Particles sit at the cell centres of a regular lattice of spacing ``s`` (m) aligned with the
world axes; a centre is kept when a vertical ray from it crosses the mesh an odd number of times
(vectorised per lattice column, so no ray-acceleration library is needed). Each kept
particle carries the cell volume s^3 (m^3) as its rest volume, so the total particle volume
converges to the mesh volume as s -> 0.
"""

from __future__ import annotations

import numpy as np


def inside_mask(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Boolean [P]: which ``points`` [P, 3] lie inside a closed mesh (ray parity along +z).

    Points are grouped into vertical columns (same x, y); each column's line is intersected
    once with every triangle (2D barycentric test in the xy projection), and a point is inside
    when an odd number of crossings lies above it. Crossings at the same height (the line
    through a shared edge or vertex) are counted once.
    """
    p = np.asarray(points, dtype=np.float64)
    xy, column = np.unique(p[:, :2], axis=0, return_inverse=True)
    tri = np.asarray(vertices, dtype=np.float64)[np.asarray(faces)]  # [F, 3, 3]
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    # barycentric coordinates of each column (x, y) in each triangle's xy projection
    e1, e2 = b[:, :2] - a[:, :2], c[:, :2] - a[:, :2]
    det = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]  # [F]; 0 for vertical triangles
    ok = np.abs(det) > 1e-18
    rel = xy[:, None, :] - a[None, :, :2]  # [C, F, 2]
    safe = np.where(ok, det, 1.0)
    w1 = (rel[..., 0] * e2[:, 1] - rel[..., 1] * e2[:, 0]) / safe
    w2 = (e1[:, 0] * rel[..., 1] - e1[:, 1] * rel[..., 0]) / safe
    hit = ok & (w1 >= 0) & (w2 >= 0) & (w1 + w2 <= 1)
    z = a[:, 2] + w1 * (b[:, 2] - a[:, 2]) + w2 * (c[:, 2] - a[:, 2])
    z = np.sort(np.where(hit, z, np.inf), axis=1)
    z = z[:, : max(1, int(np.isfinite(z).sum(axis=1).max()))]
    dup = np.zeros_like(z, dtype=bool)
    with np.errstate(invalid="ignore"):  # inf - inf between two missing crossings
        dup[:, 1:] = np.abs(np.diff(z, axis=1)) < 1e-12
    z[dup] = np.inf
    above = (z[column] > p[:, 2:3]) & np.isfinite(z[column])
    return above.sum(axis=1) % 2 == 1


def sample_inside(mesh, spacing: float, *, offset: np.ndarray | None = None) -> np.ndarray:
    """Lattice cell centres (spacing m) inside ``mesh`` (a closed trimesh.Trimesh): [N, 3] m.

    ``offset`` (in cells, each in [0, 1)) shifts the lattice so different seeds sample different
    sub-cell positions; default 0.5 (lattice symmetric about the origin).
    """
    lo, hi = mesh.bounds
    shift = np.full(3, 0.5) if offset is None else np.asarray(offset, dtype=np.float64)
    first = np.floor(lo / spacing - shift) + shift  # lattice coordinate of the first centre <= lo
    axes = [
        (np.arange(first[d], hi[d] / spacing + 1.0) * spacing) for d in range(3)
    ]  # centres at (i + shift) * spacing covering [lo, hi]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    inside = inside_mask(grid, mesh.vertices, mesh.faces)
    points = grid[inside]
    if points.shape[0] < 8:
        raise ValueError(
            f"only {points.shape[0]} particles fit inside a mesh of extents "
            f"{np.round(mesh.extents, 3).tolist()} m at particle_spacing={spacing} m; "
            "use a smaller spacing"
        )
    return points


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    """A uniformly distributed rotation matrix [3, 3] (unit quaternion from 4 normals)."""
    q = rng.normal(size=4)
    w, x, y, z = q / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )
