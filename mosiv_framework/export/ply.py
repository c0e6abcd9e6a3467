"""PLY files of particles and of 3D Gaussians in the layout splatting tools read.

Particles: one vertex per particle with ``x y z`` (m), ``vx vy vz`` (m/s) and ``object_id``.

Gaussians: the layout of the reference 3D Gaussian splatting implementation (Kerbl et al. 2023),
which SuperSplat, the antimatter15 and gsplat web viewers and Polycam read:
``x y z nx ny nz f_dc_0..2 f_rest_0..44 opacity scale_0..2 rot_0..3``, all float32, where

- ``f_dc`` is the degree-0 spherical-harmonic coefficient: a viewer shows the colour
  ``0.5 + SH_C0 * f_dc``, so ``f_dc = (rgb - 0.5) / SH_C0``;
- ``f_rest`` (degrees 1..3, view-dependent colour) are zeros: MOSIV's Gaussians have one colour.
  All 45 are written because the reference loader expects degree 3;
- ``opacity`` is the logit of the opacity in (0, 1) (viewers apply a sigmoid);
- ``scale_i`` is the log of the standard deviation (m) along each axis (viewers apply exp);
  MOSIV's Gaussians are isotropic, so the three are equal;
- ``rot`` is a unit quaternion ``w x y z`` (identity here: an isotropic Gaussian has no axes);
- ``nx ny nz`` are unused normals, zero.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

#: the degree-0 real spherical harmonic, 1 / (2 sqrt(pi))
SH_C0 = 0.28209479177387814
#: f_rest coefficients of spherical harmonics up to degree 3 (3 colours x 15)
N_SH_REST = 45
#: opacities are clipped to [EPS, 1 - EPS] before the logit so it stays finite
OPACITY_EPS = 1e-6
PARTICLE_PROPERTIES = ("x", "y", "z", "vx", "vy", "vz", "object_id")
GAUSSIAN_PROPERTIES = (
    ("x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2")
    + tuple(f"f_rest_{i}" for i in range(N_SH_REST))
    + ("opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3")
)


def rgb_to_sh_dc(rgb: np.ndarray) -> np.ndarray:
    """Colours in [0, 1] -> degree-0 SH coefficients, as 3DGS viewers decode them."""
    return (np.asarray(rgb, dtype=np.float64) - 0.5) / SH_C0


def sh_dc_to_rgb(f_dc: np.ndarray) -> np.ndarray:
    return 0.5 + SH_C0 * np.asarray(f_dc, dtype=np.float64)


def opacity_to_logit(opacity: np.ndarray) -> np.ndarray:
    a = np.clip(np.asarray(opacity, dtype=np.float64), OPACITY_EPS, 1.0 - OPACITY_EPS)
    return np.log(a) - np.log1p(-a)


def logit_to_opacity(logit: np.ndarray) -> np.ndarray:
    return 1.0 / (1.0 + np.exp(-np.asarray(logit, dtype=np.float64)))


def _write(path: Path, names: tuple[str, ...], columns: list[np.ndarray], dtypes: list) -> Path:
    from plyfile import PlyData, PlyElement

    n = len(columns[0])
    vertex = np.empty(n, dtype=list(zip(names, dtypes)))
    for name, column in zip(names, columns):
        vertex[name] = column
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    PlyData([PlyElement.describe(vertex, "vertex")], text=False).write(str(path))
    return path


def write_particles_ply(
    path: Path, positions: np.ndarray, velocities: np.ndarray, object_ids: np.ndarray
) -> Path:
    """One vertex per particle: positions [N, 3] m, velocities [N, 3] m/s, object_ids [N]."""
    p = np.asarray(positions, dtype=np.float32)
    v = np.asarray(velocities, dtype=np.float32)
    columns = [p[:, 0], p[:, 1], p[:, 2], v[:, 0], v[:, 1], v[:, 2]]
    columns.append(np.asarray(object_ids, dtype=np.int32))
    return _write(path, PARTICLE_PROPERTIES, columns, ["f4"] * 6 + ["i4"])


def write_gaussians_ply(
    path: Path,
    means: np.ndarray,
    radii: np.ndarray,
    colors: np.ndarray,
    opacities: np.ndarray,
) -> Path:
    """Isotropic Gaussians (means [G, 3] m, radii [G] standard deviations in m, colors [G, 3]
    in [0, 1], opacities [G] in [0, 1]) in the 3DGS layout (``GAUSSIAN_PROPERTIES``)."""
    means = np.asarray(means, dtype=np.float64)
    g = means.shape[0]
    radii = np.asarray(radii, dtype=np.float64).reshape(g)
    if not np.all(radii > 0):
        raise ValueError("Gaussian radii must be > 0 (their log is stored)")
    f_dc = rgb_to_sh_dc(np.asarray(colors).reshape(g, 3))
    zeros = np.zeros(g)
    log_scale = np.log(radii)
    columns = [means[:, 0], means[:, 1], means[:, 2], zeros, zeros, zeros]
    columns += [f_dc[:, 0], f_dc[:, 1], f_dc[:, 2]] + [zeros] * N_SH_REST
    columns += [opacity_to_logit(np.asarray(opacities).reshape(g))]
    columns += [log_scale, log_scale, log_scale, np.ones(g), zeros, zeros, zeros]
    return _write(path, GAUSSIAN_PROPERTIES, columns, ["f4"] * len(GAUSSIAN_PROPERTIES))


def read_gaussians_ply(path: Path) -> dict[str, np.ndarray]:
    """A 3DGS-layout PLY back in MOSIV's conventions: ``means`` [G, 3], ``scales`` [G, 3] (m),
    ``colors`` [G, 3] (the degree-0 colour), ``opacities`` [G], ``rotations`` [G, 4] (wxyz)."""
    from plyfile import PlyData

    v = PlyData.read(str(path))["vertex"].data

    def stack(*names: str) -> np.ndarray:
        return np.stack([np.asarray(v[n], dtype=np.float64) for n in names], axis=1)

    return {
        "means": stack("x", "y", "z"),
        "scales": np.exp(stack("scale_0", "scale_1", "scale_2")),
        "colors": sh_dc_to_rgb(stack("f_dc_0", "f_dc_1", "f_dc_2")),
        "opacities": logit_to_opacity(np.asarray(v["opacity"], dtype=np.float64)),
        "rotations": stack("rot_0", "rot_1", "rot_2", "rot_3"),
    }
