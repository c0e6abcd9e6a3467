"""Voxel visual hull of per-camera foregrounds, its 3D connected components, and the painting
of labelled voxels back into each camera.

The grid covers the scene's domain box; each voxel centre is projected once per camera (the
cameras are static), so carving a frame is one gather per camera.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from scipy import ndimage

from mosiv_framework.scene.cameras import Camera


@dataclass(frozen=True)
class VoxelGrid:
    """Cubic voxels of side ``size`` (m) filling the box from ``lower``; ``shape`` voxels per axis."""

    lower: np.ndarray
    size: float
    shape: tuple[int, int, int]

    @classmethod
    def over(cls, domain, voxels: int) -> VoxelGrid:
        """A grid over ``domain`` ((lower), (upper)) with ``voxels`` cells along its longest side."""
        lower, upper = (np.asarray(c, dtype=np.float64) for c in domain)
        size = float((upper - lower).max()) / voxels
        shape = tuple(max(1, int(math.ceil(s / size - 1e-9))) for s in upper - lower)
        return cls(lower, size, shape)

    def centres(self) -> np.ndarray:
        """World coordinates (m) of every voxel centre, [N, 3] in C order of ``shape``."""
        axes = [self.lower[i] + (np.arange(n) + 0.5) * self.size for i, n in enumerate(self.shape)]
        grid = np.meshgrid(*axes, indexing="ij")
        return np.stack([g.ravel() for g in grid], axis=-1)


@dataclass
class CameraTable:
    """Where each voxel centre lands in one camera: flat pixel index (-1 when behind the camera
    or outside the image), depth (m, along the optical axis), continuous (u, v), and the
    half-width (pixels) of the square the voxel covers in the image."""

    camera: Camera
    pixel: np.ndarray
    depth: np.ndarray
    uv: np.ndarray
    half_px: np.ndarray


def project_grid(grid: VoxelGrid, camera: Camera) -> CameraTable:
    """Project every voxel centre of ``grid`` into ``camera`` (``Camera.project``)."""
    uv, depth = camera.project(torch.as_tensor(grid.centres(), dtype=torch.float64))
    uv, depth = uv.numpy(), depth.numpy()
    front = depth > 1e-9
    with np.errstate(invalid="ignore", divide="ignore"):
        col = np.floor(np.where(front, uv[:, 0], -1.0)).astype(np.int64)
        row = np.floor(np.where(front, uv[:, 1], -1.0)).astype(np.int64)
        # half the voxel's bounding-sphere diameter: adjacent voxels' squares then overlap, so
        # a solid hull paints without gaps between voxel centres
        half = 0.5 * math.sqrt(3.0) * grid.size * max(camera.fx, camera.fy) / depth
    inside = front & (col >= 0) & (col < camera.width) & (row >= 0) & (row < camera.height)
    pixel = np.where(inside, row * camera.width + col, -1)
    return CameraTable(camera, pixel, depth.astype(np.float32), uv, np.where(front, half, 0.0))


def carve(
    tables: list[CameraTable], foregrounds: list[np.ndarray], *, view_tolerance: int
) -> np.ndarray:
    """Occupancy of one frame, bool [N]: voxels that every camera seeing them (up to
    ``view_tolerance`` cameras excepted) sees as foreground. A voxel must be seen as
    foreground by at least two cameras (one when only one camera exists); cameras whose
    image the voxel falls outside neither keep nor carve it.

    Args:
        tables: one per camera; foregrounds: bool [H, W] of the same cameras, same order.
    """
    n = tables[0].pixel.shape[0]
    seen = np.zeros(n, dtype=np.int32)
    fg = np.zeros(n, dtype=np.int32)
    for table, mask in zip(tables, foregrounds):
        inside = table.pixel >= 0
        seen += inside
        fg += inside & mask.ravel()[np.where(inside, table.pixel, 0)]
    need = min(2, len(tables))
    return (fg >= need) & (seen - fg <= view_tolerance)


def components(occupied: np.ndarray, shape: tuple[int, int, int], min_voxels: int) -> list:
    """Connected components (26-neighbourhood) of the occupancy, as arrays of flat voxel
    indices, largest first; components of fewer than ``min_voxels`` voxels are dropped."""
    labels, count = ndimage.label(occupied.reshape(shape), structure=np.ones((3, 3, 3)))
    flat = labels.ravel()
    order = np.argsort(flat, kind="stable")
    bounds = np.searchsorted(flat[order], np.arange(1, count + 2))
    parts = [order[bounds[i] : bounds[i + 1]] for i in range(count)]
    parts = [p for p in parts if p.size >= max(1, min_voxels)]
    return sorted(parts, key=lambda p: -p.size)


def _splat(table: CameraTable, voxels: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """Label image [H, W] (0 where no voxel lands): each labelled voxel covers the pixels whose
    centres fall in its square; where several do, the one nearest the camera wins."""
    cam = table.camera
    keep = table.depth[voxels] > 0
    voxels, labels = voxels[keep], labels[keep]
    uv, half = table.uv[voxels], table.half_px[voxels]
    reach = int(math.ceil(float(half.max()))) if half.size else 0
    base_col, base_row = np.floor(uv[:, 0]).astype(np.int64), np.floor(uv[:, 1]).astype(np.int64)
    pix, dep, lab = [], [], []
    for dr in range(-reach, reach + 1):
        for dc in range(-reach, reach + 1):
            col, row = base_col + dc, base_row + dr
            hit = (np.abs(col + 0.5 - uv[:, 0]) <= half) & (np.abs(row + 0.5 - uv[:, 1]) <= half)
            hit &= (col >= 0) & (col < cam.width) & (row >= 0) & (row < cam.height)
            pix.append((row * cam.width + col)[hit])
            dep.append(table.depth[voxels][hit])
            lab.append(labels[hit])
    image = np.zeros(cam.height * cam.width, dtype=np.uint8)
    if pix:
        pix, dep, lab = np.concatenate(pix), np.concatenate(dep), np.concatenate(lab)
        order = np.lexsort((dep, pix))  # by pixel, nearest first within a pixel
        first = np.unique(pix[order], return_index=True)[1]
        image[pix[order][first]] = lab[order][first]
    return image.reshape(cam.height, cam.width)


def paint(
    table: CameraTable, foreground: np.ndarray, voxels: np.ndarray, labels: np.ndarray
) -> np.ndarray:
    """Instance mask of one camera and frame, uint8 [H, W], restricted to its foreground.

    Labelled voxels are splatted (nearest depth wins); foreground pixels no voxel covers take
    the label of the nearest covered pixel, but only inside a 2D foreground region that some
    voxel covers: a region with no hull behind it (something outside the domain, a view-only
    artefact) stays background.
    """
    covered = _splat(table, voxels, labels) * foreground
    if not covered.any():
        return covered
    _, (near_r, near_c) = ndimage.distance_transform_edt(covered == 0, return_indices=True)
    filled = np.where(foreground, covered[near_r, near_c], 0).astype(np.uint8)
    regions, count = ndimage.label(foreground)
    backed = np.zeros(count + 1, dtype=bool)
    backed[np.unique(regions[covered > 0])] = True
    backed[0] = False
    return np.where(backed[regions], filled, 0).astype(np.uint8)
