"""Particles of all objects on one shared grid, with disjoint supports.

Every object's occupied cells are cells of the same grid (side ``cell_size``, aligned with the
scene domain's lower corner), so their particles share one resolution:
1. a cell claimed by several objects goes to the object whose frame-0 Gaussians (its observed
   surface) are nearest to the cell centre (paper section 3.3, "nearest object surface"); with
   Gaussians that fill the volume (seeded from points) this splits an overlap at its bisector;
2. cells whose centre lies outside the simulation domain are dropped;
3. each cell emits ``n^3`` particles on an n x n x n sub-lattice, each with rest volume
   ``cell_size^3 / n^3`` (m^3) and mass ``rho_k`` times that volume (kg);
4. residual interpenetration: wherever particles of two objects lie closer than half a cell
   (possible across a shared cell face when n >= 2), the particle that is nearer to the other
   object's surface than to its own (largest ``d_own - d_other``) is removed, until no pair of
   particles of different objects is closer than half a cell.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from scipy.spatial import cKDTree

from mosiv_lift.density import DensityGrid

Tensor = torch.Tensor

#: relative slack on the half-cell separation: particles exactly half a cell apart (adjacent
#: sub-lattice sites across a face, n = 2) are separated, not interpenetrating
_SEPARATION_SLACK = 1e-6


@dataclass
class Emission:
    """Particles of all objects: positions [N, 3] m (float32), volumes [N] m^3, masses [N] kg,
    object_ids [N] int64; with counts of contested cells and of removed particles."""

    positions: Tensor
    volumes: Tensor
    masses: Tensor
    object_ids: Tensor
    contested_cells: int
    removed_particles: int


def _surface_distance(trees: dict[int, cKDTree], object_id: int, points: np.ndarray) -> np.ndarray:
    return trees[object_id].query(points, k=1)[0]


def resolve_claims(
    cells: dict[int, Tensor], trees: dict[int, cKDTree], *, origin: np.ndarray, cell: float
) -> tuple[dict[int, Tensor], int]:
    """Give every cell (global int64 indices [M_k, 3] per object) to one object; returns the
    cells kept per object and how many cells were contested."""
    ids = sorted(cells)
    all_cells = torch.cat([cells[k] for k in ids])
    owner = torch.cat([torch.full((len(cells[k]),), k, dtype=torch.int64) for k in ids])
    unique, inverse, counts = torch.unique(
        all_cells, dim=0, return_inverse=True, return_counts=True
    )
    contested = counts[inverse] > 1
    keep = ~contested
    if contested.any():
        rows = torch.nonzero(contested).squeeze(1)
        centres = origin + (all_cells[rows].numpy() + 0.5) * cell
        dist = np.full(len(rows), np.inf)
        for k in ids:  # distance of each contested entry to its own claimant's surface
            mine = (owner[rows] == k).numpy()
            if mine.any():
                dist[mine] = _surface_distance(trees, k, centres[mine])
        # per unique cell, the claimant with the smallest distance wins (ties: lower id)
        group = inverse[rows].numpy()
        order = np.lexsort((owner[rows].numpy(), dist, group))
        first = np.ones(len(order), dtype=bool)
        first[1:] = group[order][1:] != group[order][:-1]
        keep[rows[torch.from_numpy(order[first])]] = True
    n_contested = int((counts > 1).sum())
    return {k: all_cells[keep & (owner == k)] for k in ids}, n_contested


def _sub_lattice(n: int) -> np.ndarray:
    """Offsets (in cells) of the n^3 particles of a cell: ((i + 1/2) / n, ...), [n^3, 3]."""
    axis = (np.arange(n) + 0.5) / n
    return np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), axis=-1).reshape(-1, 3)


def separate(
    positions: np.ndarray, object_ids: np.ndarray, trees: dict[int, cKDTree], *, radius: float
) -> np.ndarray:
    """[N] bool of particles to keep so that no two particles of different objects are closer
    than ``radius`` (m)."""
    alive = np.ones(len(positions), dtype=bool)
    ids = sorted(trees)
    while True:
        index = np.nonzero(alive)[0]
        pairs = cKDTree(positions[index]).query_pairs(radius, output_type="ndarray")
        if len(pairs):
            pairs = index[pairs]
            pairs = pairs[object_ids[pairs[:, 0]] != object_ids[pairs[:, 1]]]
        if not len(pairs):
            return alive
        involved = np.unique(pairs)
        # how much nearer each involved particle is to a foreign surface than to its own
        own = np.empty(len(involved))
        other = np.full(len(involved), np.inf)
        for k in ids:
            mine = object_ids[involved] == k
            pts = positions[involved]
            own[mine] = _surface_distance(trees, k, pts[mine])
            if (~mine).any():
                other[~mine] = np.minimum(other[~mine], _surface_distance(trees, k, pts[~mine]))
        score = dict(zip(involved.tolist(), (own - other).tolist()))
        a, b = pairs[:, 0], pairs[:, 1]
        sa = np.array([score[i] for i in a])
        sb = np.array([score[i] for i in b])
        # the more foreign particle of each pair goes (ties: the higher object id)
        lose_a = (sa > sb) | ((sa == sb) & (object_ids[a] > object_ids[b]))
        alive[np.where(lose_a, a, b)] = False


def emit_particles(
    grids: dict[int, DensityGrid],
    surfaces: dict[int, Tensor],
    *,
    domain_lower,
    domain_upper,
    cell: float,
    sub_lattice: int,
    densities: dict[int, float],
) -> Emission:
    """Particles from each object's density grid (all on the same grid of side ``cell`` m).

    ``surfaces`` maps object id -> [G_k, 3] frame-0 Gaussian means (m) used as that object's
    observed surface; ``densities`` object id -> rho (kg/m^3).
    """
    origin = np.asarray(domain_lower, dtype=np.float64)
    upper = np.asarray(domain_upper, dtype=np.float64)
    trees = {k: cKDTree(surfaces[k].detach().double().cpu().numpy()) for k in sorted(grids)}
    cells = {
        k: torch.nonzero(g.occupied) + torch.tensor(g.box.lower, dtype=torch.int64)
        for k, g in grids.items()
    }
    claimed = {k: len(c) for k, c in cells.items()}
    cells, n_contested = resolve_claims(cells, trees, origin=origin, cell=cell)
    offsets = _sub_lattice(sub_lattice)
    volume = cell**3 / len(offsets)
    positions, ids = [], []
    for k in sorted(cells):
        corner = origin + cells[k].numpy() * cell
        inside = np.all((corner + 0.5 * cell >= origin) & (corner + 0.5 * cell <= upper), axis=1)
        corner = corner[inside]
        if not len(corner):
            # say which step emptied it: no density, cells lost to another object's claims
            # (its Gaussians overlap this object's), or cells outside the simulation domain
            raise ValueError(
                f"object {k} has no occupied cell inside the domain after lifting: its density "
                f"grid held {claimed[k]} cells, {claimed[k] - len(cells[k])} went to other "
                f"objects that claimed the same cells, {len(cells[k])} were left of which "
                f"{len(cells[k]) - len(corner)} lie outside the domain {origin.tolist()} - "
                f"{upper.tolist()} m; check its Gaussians (object ids), masks and the lifter's "
                "cell_size"
            )
        pts = (corner[:, None, :] + offsets[None] * cell).reshape(-1, 3)
        positions.append(pts)
        ids.append(np.full(len(pts), k, dtype=np.int64))
    pos = np.concatenate(positions)
    oid = np.concatenate(ids)
    alive = separate(pos, oid, trees, radius=0.5 * cell * (1.0 - _SEPARATION_SLACK))
    pos, oid = pos[alive], oid[alive]
    for k in sorted(cells):
        if not (oid == k).any():
            raise ValueError(
                f"object {k} lost all its particles to its neighbours while separating supports"
            )
    rho = np.array([densities[int(k)] for k in oid])
    volumes = np.full(len(pos), volume)
    return Emission(
        positions=torch.from_numpy(pos).to(torch.float32),
        volumes=torch.from_numpy(volumes).to(torch.float32),
        masses=torch.from_numpy(rho * volumes).to(torch.float32),
        object_ids=torch.from_numpy(oid),
        contested_cells=n_contested,
        removed_particles=int((~alive).sum()),
    )
