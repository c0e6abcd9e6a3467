"""Surface meshes of particle objects: a smoothed density grid cut by marching cubes.

Each particle stands for its rest volume ``V_p``. Splatting ``V_p`` into a grid of cell ``h``
(trilinear weights, divided by ``h^3``) and blurring with a Gaussian of standard deviation
``sigma`` gives a density that is about 1 inside the body and 0 outside: the indicator of the
volume the particles fill, smoothed. Its 0.5 level set lies on a flat face of that volume exactly
(the blur of a step is symmetric about the step), so marching cubes at 0.5 recovers the body's
surface and its volume ``sum V_p`` up to the rounding of edges and a shift of curved faces of
order ``sigma^2 / radius`` inward.

``sigma`` is ``SIGMA_PER_SPACING`` times the particle spacing ``s = median(V_p)^(1/3)``: small
enough to keep edges sharp, large enough that the density of a particle lattice does not ripple
down to 0.5 between particles (for a lattice of spacing s the ripple is about
``2 exp(-2 pi^2 sigma^2 / s^2)``: 4% at 0.45 s; at 0.3 s, 33%, and rotated lattices measured
opened hundreds of bubbles inside a ball). Measured on rotated, shifted lattice balls at 0.45 s:
the mesh encloses 95% of ``sum V_p`` for a radius of 3.3 spacings and 98% for 6.7 spacings, the
loss being the rounding of the staircase's edges, which shrinks relative to the volume as the
body grows.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mosiv_framework.export.axes import rotate, srgb_to_linear

#: blur of the density as a multiple of the particle spacing
SIGMA_PER_SPACING = 0.45
#: grid cells per particle spacing
CELLS_PER_SPACING = 3
#: the density level of the surface (half of the inside density 1)
LEVEL = 0.5


def particle_spacing(volumes: np.ndarray) -> float:
    """The typical spacing (m) of particles with rest volumes ``volumes`` (m^3)."""
    return float(np.median(np.asarray(volumes, dtype=np.float64))) ** (1.0 / 3.0)


def density_grid(
    points: np.ndarray, volumes: np.ndarray, *, spacing: float
) -> tuple[np.ndarray, np.ndarray, float]:
    """(density [X, Y, Z], origin [3] m of cell (0, 0, 0), cell size h m) of the particles."""
    from scipy.ndimage import gaussian_filter

    points = np.asarray(points, dtype=np.float64)
    h = spacing / CELLS_PER_SPACING
    sigma = SIGMA_PER_SPACING * spacing
    pad = 4.0 * sigma + spacing  # room for the blur's tail on every side
    origin = points.min(axis=0) - pad
    shape = np.ceil((points.max(axis=0) + pad - origin) / h).astype(int) + 2
    grid = np.zeros(shape)
    rel = (points - origin) / h
    base = np.floor(rel).astype(int)
    frac = rel - base
    mass = np.asarray(volumes, dtype=np.float64) / h**3
    for corner in np.ndindex(2, 2, 2):  # trilinear deposit onto the 8 surrounding nodes
        offset = np.array(corner)
        w = np.prod(np.where(offset == 1, frac, 1.0 - frac), axis=1)
        idx = base + offset
        np.add.at(grid, (idx[:, 0], idx[:, 1], idx[:, 2]), w * mass)
    return gaussian_filter(grid, sigma / h, mode="constant"), origin, h


def object_mesh(points: np.ndarray, volumes: np.ndarray, *, spacing: float | None = None):
    """A closed ``trimesh.Trimesh`` around particles (points [N, 3] m, rest volumes [N] m^3)."""
    import trimesh
    from skimage.measure import marching_cubes

    spacing = particle_spacing(volumes) if spacing is None else spacing
    density, origin, h = density_grid(points, volumes, spacing=spacing)
    if density.max() <= LEVEL:  # too few particles to fill any cell above the level
        return trimesh.Trimesh()
    verts, faces, _, _ = marching_cubes(density, level=LEVEL, spacing=(h, h, h))
    # skimage orients faces for a dark-inside field; density is high inside, so flip to make
    # normals point out (and the signed volume positive)
    mesh = trimesh.Trimesh(vertices=verts + origin, faces=faces[:, ::-1], process=True)
    return mesh


def write_frame_glb(path: Path, meshes: dict[int, object], colors: dict[int, np.ndarray]) -> Path:
    """One glTF binary: a mesh node ``object_<k>`` per object id k, coloured ``colors[k]``
    (sRGB in [0, 1]). glTF fixes +y up and linear vertex colours: MOSIV's z-up vertices are
    turned into that world (``axes.ROTATIONS["y"]``) and the colours made linear."""
    import trimesh

    scene = trimesh.Scene()
    for k in sorted(meshes):
        mesh = meshes[k].copy()
        if len(mesh.vertices):
            mesh.vertices = rotate(mesh.vertices, "y")  # a rotation: faces keep their winding
        if len(mesh.faces):
            linear = srgb_to_linear(colors[k])
            rgba = np.append(np.round(linear * 255), 255).astype(np.uint8)
            mesh.visual = trimesh.visual.ColorVisuals(
                mesh, face_colors=np.tile(rgba, (len(mesh.faces), 1))
            )
        scene.add_geometry(mesh, node_name=f"object_{k}", geom_name=f"object_{k}")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(scene.export(file_type="glb"))
    return path
