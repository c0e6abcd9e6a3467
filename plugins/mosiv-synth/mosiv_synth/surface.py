"""Object surfaces from simulation particles: particle volume fraction -> marching cubes.

Independent of any Gaussian model on purpose (the reconstruction must not be handed its own
appearance model). Each particle spreads its rest volume s^3 over a voxel grid of size h = s/2
by trilinear (cloud-in-cell) weights; dividing by h^3 gives the solid volume fraction, ~1 inside
a body and 0 outside. A Gaussian blur of standard deviation s/2 removes the lattice's
period-s ripple (attenuated by exp(-2 pi^2 sigma^2 / s^2) < 1 %), and the 0.5 iso-surface of the
result is the body's boundary: a symmetric blur of a step crosses one half at the step.

Where particles have spread out (a splash, a thin puddle, scattered sand) the volume fraction
falls below one half everywhere and such a body would vanish or break into a lattice of
threads. So the field is the larger of the fraction and a distance ramp that crosses one half at
distance PARTICLE_RADIUS * s from the nearest particle: every particle stays visible as at least
a ball of diameter s (the parcel of material it stands for), while on dense bodies the ramp
lies inside the fraction's surface and changes nothing.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

ISO_LEVEL = 0.5
PARTICLE_RADIUS = 0.5  # in particle spacings: balls of this radius around adjacent particles touch
_PAD = 4  # voxels of empty margin: the blur's 3-sigma reach (2 voxels) plus one for marching cubes


@dataclass
class Surface:
    """A triangle mesh: vertices [V, 3] (m), faces [F, 3] (int), unit outward normals [V, 3]."""

    vertices: np.ndarray
    faces: np.ndarray
    normals: np.ndarray


def volume_fraction(points: np.ndarray, spacing: float) -> tuple[np.ndarray, np.ndarray, float]:
    """Blurred solid volume fraction of particles of rest volume spacing^3.

    Returns (field [X, Y, Z], origin [3] m of voxel (0, 0, 0), voxel size h m).
    """
    from scipy.ndimage import gaussian_filter

    h = 0.5 * spacing
    origin = points.min(axis=0) - _PAD * h
    shape = np.ceil((points.max(axis=0) - origin) / h).astype(int) + _PAD + 1
    g = (points - origin) / h
    base = np.floor(g).astype(np.int64)
    frac = g - base
    field = np.zeros(int(np.prod(shape)), dtype=np.float64)
    weight0 = spacing**3 / h**3  # a particle's volume in voxels
    for corner in range(8):
        offs = np.array([(corner >> 2) & 1, (corner >> 1) & 1, corner & 1])
        w = np.prod(np.where(offs == 1, frac, 1.0 - frac), axis=1) * weight0
        idx = base + offs
        flat = (idx[:, 0] * shape[1] + idx[:, 1]) * shape[2] + idx[:, 2]
        field += np.bincount(flat, weights=w, minlength=field.size)
    field = gaussian_filter(field.reshape(shape), sigma=0.5 * spacing / h, mode="constant")
    return np.maximum(field, _particle_balls(points, origin, shape, h, spacing)), origin, h


def _particle_balls(points, origin, shape, h: float, spacing: float) -> np.ndarray:
    """Ramp 0.5 + (R - d) / (2 h), d = distance to the nearest particle, R = PARTICLE_RADIUS s:
    one half on the sphere of radius R around each particle, 0 a voxel further out."""
    from scipy.spatial import cKDTree

    radius = PARTICLE_RADIUS * spacing
    axes = [origin[d] + h * np.arange(shape[d]) for d in range(3)]
    centres = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    dist, _ = cKDTree(points).query(centres, distance_upper_bound=radius + 2.0 * h)
    dist = np.where(np.isfinite(dist), dist, radius + 2.0 * h)
    return np.clip(0.5 + (radius - dist) / (2.0 * h), 0.0, 1.0).reshape(shape)


def particle_surface(points: np.ndarray, spacing: float) -> Surface:
    """The closed surface around particles ``points`` [N, 3] (m) of lattice ``spacing`` (m)."""
    from skimage.measure import marching_cubes

    field, origin, h = volume_fraction(np.asarray(points, dtype=np.float64), spacing)
    if len(points) == 0:
        return Surface(np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64), np.zeros((0, 3)))
    verts, faces, normals, _ = marching_cubes(field, level=ISO_LEVEL, spacing=(h, h, h))
    return Surface(
        np.ascontiguousarray(verts + origin),
        np.ascontiguousarray(faces, dtype=np.int64),
        np.ascontiguousarray(normals, dtype=np.float64),
    )
