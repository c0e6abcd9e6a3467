"""The ten benchmark geometries of the paper (section 4.1), built procedurally with trimesh.

Every shape is a closed, consistently wound triangle mesh with z up, centred on its volume
centroid and scaled so that its largest bounding-box side is the requested size (m). Two
constructions keep them watertight by design:
- a surface of revolution (``trimesh.creation.revolve``) of a profile that starts and ends on
  the axis (pawn, apple, cream, barrel, mushroom);
- a star-shaped deformation of an icosphere (each vertex moved along its direction), optionally
  followed by a smooth bijective bend (egg, bread, potato, cushion, banana).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

#: shape name -> (smallest, largest) size in m drawn for it; all inside the protocol's 0.08-0.15
SIZE_RANGES: dict[str, tuple[float, float]] = {
    "egg": (0.08, 0.10),
    "pawn": (0.10, 0.13),
    "apple": (0.09, 0.11),
    "bread": (0.12, 0.15),
    "cream": (0.09, 0.12),
    "barrel": (0.10, 0.12),
    "potato": (0.10, 0.13),
    "cushion": (0.12, 0.15),
    "banana": (0.13, 0.15),
    "mushroom": (0.09, 0.12),
}
SHAPE_NAMES: tuple[str, ...] = tuple(SIZE_RANGES)
SIZE_LIMITS = (0.08, 0.15)

_SECTIONS = 48  # angular segments of surfaces of revolution
_SUBDIVISIONS = 4  # icosphere subdivisions for star-shaped bodies (2562 vertices)


def _revolve(profile: list[tuple[float, float]]):
    """Surface of revolution about z of a (radius, z) profile running bottom (r=0) to top (r=0)."""
    import trimesh

    return trimesh.creation.revolve(np.asarray(profile, dtype=np.float64), sections=_SECTIONS)


def _star(radius: Callable[[np.ndarray], np.ndarray]):
    """Icosphere whose vertex with unit direction u is moved to radius(u) * u."""
    import trimesh

    sphere = trimesh.creation.icosphere(subdivisions=_SUBDIVISIONS)
    u = sphere.vertices / np.linalg.norm(sphere.vertices, axis=1, keepdims=True)
    return trimesh.Trimesh(vertices=u * radius(u)[:, None], faces=sphere.faces, process=False)


def _superellipsoid(u: np.ndarray, axes, exponent: float) -> np.ndarray:
    """Radius along u of |x/a|^n + |y/b|^n + |z/c|^n = 1."""
    a = np.asarray(axes, dtype=np.float64)
    return np.sum(np.abs(u / a) ** exponent, axis=1) ** (-1.0 / exponent)


def _egg(rng: np.random.Generator):
    # prolate ellipsoid whose girth shrinks towards the top: the classic egg asymmetry
    taper = rng.uniform(0.12, 0.2)

    def radius(u):
        return _superellipsoid(u, (0.75, 0.75, 1.0), 2.0) * (1.0 - taper * u[:, 2] * (u[:, 2] > 0))

    return _star(radius)


def _bread(rng: np.random.Generator):
    # a loaf: a boxy superellipsoid, longer than wide, domed on top and flat below
    length = rng.uniform(1.6, 1.9)

    def radius(u):
        r = _superellipsoid(u, (length, 1.0, 0.75), 3.0)
        return r * np.where(u[:, 2] < 0, 0.8, 1.0)

    return _star(radius)


def _potato(rng: np.random.Generator):
    # ellipsoid with smooth random lumps: a sum of a few low-frequency cosine bumps
    axes = (rng.uniform(1.3, 1.6), 1.0, rng.uniform(0.75, 0.9))
    dirs = rng.normal(size=(6, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    amps = rng.uniform(0.03, 0.07, size=6)

    def radius(u):
        lumps = 1.0 + (amps * np.clip(u @ dirs.T, 0.0, None) ** 3).sum(axis=1)
        return _superellipsoid(u, axes, 2.0) * lumps

    return _star(radius)


def _cushion(rng: np.random.Generator):
    # a square pillow: rounded square in plan, thickness falling off towards the edges
    thickness = rng.uniform(0.3, 0.38)

    def radius(u):
        plan = _superellipsoid(u, (1.0, 1.0, 1.0), 4.0)
        edge = np.maximum(np.abs(u[:, 0]), np.abs(u[:, 1])) * plan
        squash = np.where(np.abs(u[:, 2]) > 1e-9, thickness * (1.0 - 0.5 * edge**2), 1.0)
        # radius where the ray meets the thinner of the plan square and the puffy top/bottom
        return np.minimum(plan, squash / np.maximum(np.abs(u[:, 2]), 1e-9))

    return _star(radius)


def _banana(rng: np.random.Generator):
    # a slender spindle along x, tapered ends, bent along an arc of radius R (a bijective map)
    mesh = _star(lambda u: _superellipsoid(u, (1.0, 0.2, 0.2), 2.0))
    v = mesh.vertices.copy()
    v[:, 1:] *= (1.0 - 0.35 * np.abs(v[:, 0:1])) / 1.0  # thinner tips
    bend = rng.uniform(1.3, 1.8)  # arc radius in units of the half length
    angle = v[:, 0] / bend
    rr = bend - v[:, 2]  # bend centre above the fruit, so the ends curve upwards
    mesh.vertices = np.stack([rr * np.sin(angle), v[:, 1], bend - rr * np.cos(angle)], axis=1)
    return mesh


def _pawn(rng: np.random.Generator):
    head = rng.uniform(0.2, 0.24)
    profile = [(0.0, 0.0), (0.42, 0.0), (0.42, 0.08), (0.33, 0.14), (0.2, 0.2), (0.13, 0.45)]
    profile += [(0.26, 0.52), (0.26, 0.56), (0.12, 0.6)]
    # the head: a circle of radius `head` resting on the collar
    centre = 0.6 + head * 0.85
    for t in np.linspace(-0.55 * np.pi, 0.5 * np.pi, 12)[1:]:
        profile.append((head * np.cos(t), centre + head * np.sin(t)))
    profile[-1] = (0.0, centre + head)
    return _revolve(profile)


def _apple(rng: np.random.Generator):
    # sphere-like profile with dimples at both poles (cardioid-flavoured radius)
    flat = rng.uniform(0.85, 0.95)
    ts = np.linspace(-0.5 * np.pi, 0.5 * np.pi, 24)
    profile = [(0.0, -flat + 0.12)]
    for t in ts[1:-1]:
        r = np.cos(t) * (1.0 + 0.1 * np.sin(t))
        z = flat * np.sin(t)
        profile.append((r, z))
    profile.append((0.0, flat - 0.15))
    return _revolve(profile)


def _cream(rng: np.random.Generator):
    # a soft-serve dollop: three stacked, shrinking bulges ending in a tip
    profile = [(0.0, 0.0)]
    z, r = 0.0, 1.0
    for _ in range(3):
        h = 0.45 * r
        for t in np.linspace(-0.5 * np.pi, 0.5 * np.pi, 7)[:-1]:
            profile.append((r * (0.75 + 0.25 * np.cos(t)), z + h * (1.0 + np.sin(t)) / 2.0))
        z += h
        r *= rng.uniform(0.62, 0.7)
    profile += [(0.5 * r, z + 0.15), (0.0, z + 0.45)]
    return _revolve(profile)


def _barrel(rng: np.random.Generator):
    bulge = rng.uniform(0.1, 0.16)
    zs = np.linspace(0.0, 1.3, 11)
    profile = [(0.0, 0.0)]
    profile += [(0.5 + bulge * (1.0 - ((z - 0.65) / 0.65) ** 2), z) for z in zs]
    profile.append((0.0, 1.3))
    return _revolve(profile)


def _mushroom(rng: np.random.Generator):
    stem = rng.uniform(0.17, 0.22)
    cap = rng.uniform(0.55, 0.65)
    profile = [(0.0, 0.0), (stem * 1.15, 0.0), (stem, 0.45), (cap * 0.85, 0.5), (cap, 0.58)]
    for t in np.linspace(0.0, 0.5 * np.pi, 9)[1:-1]:
        profile.append((cap * np.cos(t), 0.58 + 0.45 * np.sin(t)))
    profile.append((0.0, 1.03))
    return _revolve(profile)


_BUILDERS = {
    "egg": _egg,
    "pawn": _pawn,
    "apple": _apple,
    "bread": _bread,
    "cream": _cream,
    "barrel": _barrel,
    "potato": _potato,
    "cushion": _cushion,
    "banana": _banana,
    "mushroom": _mushroom,
}


def make_shape(name: str, rng: np.random.Generator, *, size: float | None = None):
    """The trimesh.Trimesh of shape ``name``: watertight, centred on its volume centroid, its
    largest bounding-box side ``size`` m (drawn from ``SIZE_RANGES[name]`` when None)."""
    if name not in _BUILDERS:
        raise ValueError(f"unknown shape {name!r}; valid shapes: {', '.join(SHAPE_NAMES)}")
    if size is None:
        size = float(rng.uniform(*SIZE_RANGES[name]))
    if not SIZE_LIMITS[0] <= size <= SIZE_LIMITS[1]:
        raise ValueError(f"size={size} m of {name!r} is outside the protocol's {SIZE_LIMITS} m")
    mesh = _BUILDERS[name](rng)
    mesh.merge_vertices()
    if mesh.volume < 0:  # profile direction decides the winding of a revolve
        mesh.invert()
    mesh.apply_scale(size / float(np.max(mesh.extents)))
    mesh.apply_translation(-mesh.center_mass)
    if not mesh.is_watertight:
        raise RuntimeError(f"shape {name!r} came out non-watertight; this is a bug of shapes.py")
    return mesh
