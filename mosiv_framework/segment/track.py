"""Object identities over time from the hull's 3D connected components.

The first frame fixes the objects: its components (the largest ``n_objects`` when that is
known, splitting merged ones when fewer are found) get ids 1..K in order of increasing world x
of their centroids. Later frames match components to objects by centroid distance (Hungarian,
``scipy.optimize.linear_sum_assignment``). When objects touch they form one component; the
objects left without a component of their own claim the nearest one, and a component claimed
by several objects is split voxel by voxel: each voxel goes to the object whose voxels of the
frame before, translated to follow the object, lie nearest to it (a nearest-neighbour split,
which follows the objects' shapes and sizes where a cut halfway between centroids would not).
"""

from __future__ import annotations

import logging

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.spatial import cKDTree

log = logging.getLogger(__name__)


def _kmeans_split(points: np.ndarray, k: int, iterations: int = 20) -> np.ndarray:
    """Cluster labels 0..k-1 of ``points`` [M, 3]: Lloyd's k-means from farthest-point seeds
    (deterministic). Used only where no earlier frame tells the objects apart."""
    seeds = [points[np.argmax(np.linalg.norm(points - points.mean(0), axis=1))]]
    for _ in range(1, k):
        dist = np.min([np.linalg.norm(points - s, axis=1) for s in seeds], axis=0)
        seeds.append(points[np.argmax(dist)])
    centres = np.array(seeds)
    labels = np.zeros(len(points), dtype=np.int64)
    for _ in range(iterations):
        labels = np.argmin(np.linalg.norm(points[:, None] - centres[None], axis=2), axis=1)
        for j in range(k):
            if np.any(labels == j):
                centres[j] = points[labels == j].mean(0)
    return labels


def first_frame_objects(parts: list, centres: np.ndarray, n_objects: int | None) -> list:
    """The objects of the first frame, as arrays of flat voxel indices ordered by id 1..K.

    Args:
        parts: components (flat voxel indices), largest first; centres: voxel centres [N, 3].
        n_objects: keep the largest this many; split the largest components (k-means) while
            fewer are found. None keeps every component.
    """
    parts = list(parts)
    if n_objects is not None and len(parts) > n_objects:
        # the smaller ones may be stray blobs, or objects the materials do not name: say so
        sizes = [int(p.size) for p in parts]
        log.warning(
            "the first frame shows %d separate objects (%s voxels) but the materials name %d: "
            "the %d largest are kept; give one material per object if the others are objects",
            len(parts), ", ".join(map(str, sizes)), n_objects, n_objects,
        )  # fmt: skip
    elif n_objects is not None and len(parts) < n_objects:
        log.warning(
            "the first frame shows %d separate object(s) but the materials name %d: the "
            "largest are split to make up the count; check the materials if that is wrong",
            len(parts), n_objects,
        )  # fmt: skip
    if n_objects is not None:
        parts = parts[:n_objects]
        while parts and len(parts) < n_objects:
            largest = parts.pop(0)
            if largest.size < 2:
                parts.insert(0, largest)
                break
            labels = _kmeans_split(centres[largest], 2)
            parts.extend([largest[labels == 0], largest[labels == 1]])
            parts.sort(key=lambda p: -p.size)
    return sorted(parts, key=lambda p: float(centres[p, 0].mean()))


def _split_shared(points: np.ndarray, templates: list, iterations: int = 10) -> np.ndarray:
    """Owner (index into ``templates``) of each point of a component several objects share.

    Each object's voxels of the frame before (its template) claim the points nearest to them;
    then each template is translated by the move of its centroid to the centroid of what it
    claimed, and the claim is repeated, so an object that moved by a fair part of its size
    between the frames still gets its own shape back."""
    trees = [cKDTree(t) for t in templates]
    shifts = [np.zeros(3) for _ in templates]
    owner = np.zeros(len(points), dtype=np.int64)
    for _ in range(iterations):
        dist = np.stack([tree.query(points - s)[0] for tree, s in zip(trees, shifts)], axis=1)
        new_owner = np.argmin(dist, axis=1)
        if _ and np.array_equal(new_owner, owner):
            break
        owner = new_owner
        shifts = [
            points[owner == j].mean(0) - t.mean(0) if np.any(owner == j) else s
            for j, (t, s) in enumerate(zip(templates, shifts))
        ]
    return owner


def track_frame(previous: list, parts: list, centres: np.ndarray, max_jump: float | None) -> list:
    """This frame's voxels of each object, in id order (an empty array for an object not seen).

    Args:
        previous: the objects' voxels (flat indices) of the last frame each was seen in.
        parts: this frame's components; centres: voxel centres [N, 3].
        max_jump: largest centroid move (m) between frames for a match; None for no limit.
            A component that no object matches is dropped (the objects are the first
            frame's); an object with no match this frame keeps its last voxels for matching.
    """
    k = len(previous)
    empty = np.zeros(0, dtype=np.int64)
    if not parts or k == 0:
        return [empty] * k
    known = [i for i in range(k) if previous[i].size]
    prev_c = np.array([centres[previous[i]].mean(0) for i in known]).reshape(-1, 3)
    part_c = np.array([centres[p].mean(0) for p in parts])
    cost = np.linalg.norm(prev_c[:, None] - part_c[None], axis=2)
    limit = np.inf if max_jump is None else max_jump
    claims: dict[int, list[int]] = {}
    for r, c in zip(*linear_sum_assignment(cost)):
        if cost[r, c] <= limit:
            claims.setdefault(c, []).append(known[r])
    matched = {obj for objs in claims.values() for obj in objs}
    for r, obj in enumerate(known):
        c = int(np.argmin(cost[r]))
        if obj not in matched and cost[r, c] <= limit and c in claims:
            claims[c].append(obj)  # touching objects: one component holds both
    out = [empty] * k
    for c, objs in claims.items():
        if len(objs) == 1:
            out[objs[0]] = parts[c]
            continue
        owner = _split_shared(centres[parts[c]], [centres[previous[o]] for o in objs])
        for j, obj in enumerate(objs):
            out[obj] = parts[c][owner == j]
    return out


def track(per_frame_parts: list, centres: np.ndarray, n_objects: int | None, max_jump) -> list:
    """Object voxels for every frame: list over frames of lists over ids 1..K. The first frame
    with any component fixes the objects; frames before it have none."""
    start = next((t for t, parts in enumerate(per_frame_parts) if parts), len(per_frame_parts))
    if start == len(per_frame_parts):
        return [[] for _ in per_frame_parts]
    objects = first_frame_objects(per_frame_parts[start], centres, n_objects)
    empty = np.zeros(0, dtype=np.int64)
    history = [[empty] * len(objects) for _ in range(start)] + [objects]
    last = list(objects)
    for parts in per_frame_parts[start + 1 :]:
        now = track_frame(last, parts, centres, max_jump)
        last = [n if n.size else old for n, old in zip(now, last)]
        history.append(now)
    return history
