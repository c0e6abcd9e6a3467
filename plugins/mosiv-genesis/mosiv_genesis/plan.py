"""Everything a Genesis scene decides before the engine starts, in plain numpy (no Genesis import):
shapes, material parameters, the mid-air collision layout, cameras and colours.

The ``synth`` source has richer versions of these (ten procedural shapes, exact first-contact
layout); plugins do not import each other, so this module keeps a deliberately small set.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from mosiv_framework.scene.protocol import launch_velocity

# the simulation box (m) as scene.json declares it; the table is the plane z = 0
DOMAIN_LOWER = (-0.4, -0.4, 0.0)
DOMAIN_UPPER = (0.4, 0.4, 0.6)
GROUND_HEIGHT = 0.0
DECLARED_GRAVITY = (0.0, 0.0, -9.8)
SIZE_LIMITS = (0.08, 0.15)  # largest extent of an object (m), paper section 4.1
# collision point 0.22-0.32 m above the table near its centre, approached over 0.12-0.2 m
COLLISION_HEIGHT = (0.22, 0.32)
COLLISION_XY = 0.04
LAUNCH_GAP = (0.12, 0.2)
LAUNCH_RISE = (-0.04, 0.1)
MARGIN = 0.02  # clearance kept to the walls at launch (m)
# cameras: Fibonacci spiral over elevations 12-70 deg, 1.15 m from the look-at point
LOOK_AT = (0.0, 0.0, 0.15)
CAMERA_DISTANCE = 1.15
FOV_DEG = 45.0  # Genesis' fov is vertical; the images are square, so it is the horizontal one too

# (relative extents x, y, z, trimesh primitive) per shape, scaled to the drawn size
SHAPES: dict[str, tuple[tuple[float, float, float], str]] = {
    "egg": ((0.75, 0.75, 1.0), "sphere"),
    "apple": ((1.0, 1.0, 0.9), "sphere"),
    "potato": ((1.0, 0.7, 0.55), "sphere"),
    "barrel": ((0.8, 0.8, 1.0), "cylinder"),
    "cushion": ((1.0, 1.0, 0.45), "box"),
    "bread": ((1.0, 0.55, 0.45), "capsule"),
}
SHAPE_NAMES = tuple(SHAPES)
COLORS = {  # one realistic sRGB colour per shape
    "egg": (0.9, 0.8, 0.68),
    "apple": (0.75, 0.12, 0.1),
    "potato": (0.74, 0.6, 0.38),
    "barrel": (0.55, 0.35, 0.18),
    "cushion": (0.3, 0.42, 0.75),
    "bread": (0.8, 0.55, 0.25),
}
BACKGROUNDS = ((0.62, 0.7, 0.8), (0.75, 0.72, 0.66), (0.55, 0.58, 0.6), (0.66, 0.74, 0.66))

# Parameter ranges, paper appendix: E 4.75e4-5.25e4 Pa, Poisson 0.2-0.3, density 800-1200.
# Yield stress and friction angle as in mosiv-synth (plasticine dents at 1-2 m/s impacts but
# carries its own weight; dry sand 25-40 deg); snow's clamps from the paper's snow row.
COMMON = {"E": (4.75e4, 5.25e4), "nu": (0.2, 0.3), "rho": (800.0, 1200.0)}
EXTRA = {
    "elastic": {},
    "plasticine": {"yield_stress": (2.0e3, 5.0e3)},
    "sand": {"friction_angle": (25.0, 40.0)},
    "newtonian": {},
    "snow": {"yield_lower": (2.5e-2, 4.5e-2), "yield_higher": (4.5e-3, 7.5e-3)},
}
GENESIS_FAMILIES = tuple(EXTRA)

# The wide preset (log-uniform where marked): two decades of Young's modulus, 1e4 Pa (soft gel)
# to 1e6 Pa (rubber); Poisson ratio 0.15 (foam) to 0.4 (nearly incompressible); density 500
# (wood, foam) to 2000 kg/m^3 (wet clay), as mosiv-synth's wide preset. Yield stress 1-30 kPa:
# the soft end slumps under its own weight (~1-3 kPa at the base), the hard end yields only
# in the stiffer draws' impacts. Sand 20 deg (glass beads) to 45 deg (crushed rock). Snow's
# clamps over a factor ~2-3 around the paper's. Genesis' Liquid has no viscosity parameter: its
# viscosity is mu times the substep (scene_format_params), so the E decades span it too.
WIDE_COMMON = {"E": (1.0e4, 1.0e6), "nu": (0.15, 0.4), "rho": (500.0, 2000.0)}
WIDE_EXTRA = {
    "elastic": {},
    "plasticine": {"yield_stress": (1.0e3, 3.0e4)},
    "sand": {"friction_angle": (20.0, 45.0)},
    "newtonian": {},
    "snow": {"yield_lower": (1.5e-2, 5.0e-2), "yield_higher": (3.0e-3, 1.0e-2)},
}
WIDE_LOG = ("E", "rho", "yield_stress")  # drawn log-uniformly in the wide preset
RANGE_PRESETS = ("paper", "wide")
# Genesis' MPM is explicit: a P-wave must cross less than half a cell per substep,
# sqrt((lambda + 2 mu) / rho) dt / dx < 0.5; substeps are raised to reach CFL_TARGET below it
CFL_BOUND = 0.5
CFL_TARGET = 0.45
# Genesis warns above its own step hint dt <= 0.02 s / grid_density (cells/m); substeps keep
# to it as well (140 substeps at 24 fps on 64 cells/m do)
GENESIS_DT_HINT = 0.02


def make_mesh(name: str, size: float, rotation: np.ndarray):
    """Watertight trimesh of shape ``name``, largest extent ``size`` (m), rotated, centred."""
    import trimesh

    extents, kind = SHAPES[name]
    if kind == "sphere":
        mesh = trimesh.creation.icosphere(subdivisions=3, radius=0.5)
    elif kind == "cylinder":
        mesh = trimesh.creation.cylinder(radius=0.5, height=1.0, sections=32)
    elif kind == "box":
        mesh = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    else:  # capsule along x: a rounded loaf
        mesh = trimesh.creation.capsule(height=0.5, radius=0.25, count=(16, 16))
        mesh.apply_transform(trimesh.transformations.rotation_matrix(math.pi / 2, (0, 1, 0)))
    mesh.apply_scale(np.asarray(extents) / mesh.extents)
    mesh.apply_scale(size / max(mesh.extents))
    mesh.vertices = mesh.vertices @ rotation.T
    mesh.vertices -= mesh.center_mass
    return mesh


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    """Uniform random rotation matrix (QR of a Gaussian matrix, signs fixed, det +1)."""
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def preset_ranges(family: str, preset: str = "paper") -> dict[str, tuple[float, float]]:
    """(lower, upper) per Genesis parameter of ``family`` in ``preset`` ("paper" or "wide")."""
    if preset == "wide":
        return {**WIDE_COMMON, **WIDE_EXTRA[family]}
    return {**COMMON, **EXTRA[family]}


def sample_params(family: str, rng: np.random.Generator, preset: str = "paper") -> dict[str, float]:
    """Genesis material parameters of one object: uniform in each paper range; in the wide
    preset log-uniform for the parameters of ``WIDE_LOG``."""
    out = {}
    for name, (lo, hi) in preset_ranges(family, preset).items():
        if preset == "wide" and name in WIDE_LOG:
            out[name] = float(math.exp(rng.uniform(math.log(lo), math.log(hi))))
        else:
            out[name] = float(rng.uniform(lo, hi))
    return out


def range_table(preset: str) -> dict:
    """The preset's ranges as gt/params.json records them: family -> name -> bounds."""
    return {
        fam: {
            n: {"lower": lo, "upper": hi, "log": preset == "wide" and n in WIDE_LOG}
            for n, (lo, hi) in preset_ranges(fam, preset).items()
        }
        for fam in GENESIS_FAMILIES
    }


def p_wave_speed(p: dict[str, float]) -> float:
    """sqrt((lambda + 2 mu) / rho) (m/s) of Genesis parameters E, nu, rho (every family)."""
    e, nu = p["E"], p["nu"]
    return math.sqrt(e * (1.0 - nu) / ((1.0 + nu) * (1.0 - 2.0 * nu)) / p["rho"])


def cfl_number(params: list[dict[str, float]], *, grid_density: float, dt: float) -> float:
    """The largest P-wave CFL number c dt / dx over the objects (dx = 1 / grid_density m)."""
    return max(p_wave_speed(p) for p in params) * dt * grid_density


def required_substeps(
    params: list[dict[str, float]], *, grid_density: float, fps: float, requested: int
) -> int:
    """The fewest substeps per frame, at least ``requested``, whose CFL number stays below
    ``CFL_TARGET`` for every object and whose step keeps to Genesis' hint ``GENESIS_DT_HINT``."""
    need = cfl_number(params, grid_density=grid_density, dt=1.0 / fps) / CFL_TARGET
    hint = grid_density / (GENESIS_DT_HINT * fps)
    return max(int(requested), math.ceil(need), math.ceil(hint - 1e-9))


def scene_format_params(family: str, p: dict[str, float], *, substep_dt: float) -> dict[str, float]:
    """The mosiv-scene/1 names that mean the same thing in Genesis' model.

    Genesis' viscous Liquid resets F to J^(1/3) I every substep and takes the fixed-corotated
    stress 2 mu (F - R) F^T + lam J (J - 1) I of the next substep's F = J^(1/3) (I + dt C). To
    first order in dt C and J - 1 that is 2 mu dt D + (lam + 2 mu / 3)(J - 1) I (D the strain
    rate, the symmetric part of C): a Newtonian fluid of viscosity mu dt (``substep_dt``, the
    engine's substep in s) and bulk modulus lam + 2 mu / 3 = E / (3 (1 - 2 nu)), which is what
    MOSIV's newtonian law has at J = 1 (docs/PHYSICS.md, Genesis's laws). E and nu stay
    generator_params.
    """
    if family == "newtonian":
        e, nu = p["E"], p["nu"]
        mu = e / (2.0 * (1.0 + nu))
        return {
            "rho": p["rho"],
            "bulk_modulus": e / (3.0 * (1.0 - 2.0 * nu)),
            "viscosity": mu * substep_dt,
        }
    keep = ("E", "nu", "rho", "yield_stress", "friction_angle")
    return {k: v for k, v in p.items() if k in keep}


def support(points: np.ndarray, direction: np.ndarray) -> float:
    """How far a centred shape reaches along ``direction``: max over points of p . d (m)."""
    return float(np.max(points @ direction))


@dataclass
class Layout:
    """Per object: start centroid [K, 3] (m), centroid target at the collision time [K, 3]."""

    starts: np.ndarray
    targets: np.ndarray
    collision_point: np.ndarray


def plan_layout(
    shapes: list[np.ndarray],
    *,
    radii: list[float],
    collision_time: float,
    acceleration,
    rng: np.random.Generator,
) -> Layout:
    """Start and target centroids so the objects meet head-on at a collision point.

    Objects 1 and 2 approach along a random horizontal direction u and are planned to touch at
    the collision point (their targets sit one support distance to either side of it); object
    3 comes in along the perpendicular direction. Each planned flight (``collision_time`` s
    under ``acceleration`` m/s^2, bounding spheres of ``radii`` m) must stay inside the domain.
    Launch velocities follow from ``launch_velocity`` once the engine has placed the particles.
    """
    times = np.linspace(0.0, collision_time, 16)
    lo, hi = np.asarray(DOMAIN_LOWER), np.asarray(DOMAIN_UPPER)
    for _ in range(200):
        p = np.array(
            [*rng.uniform(-COLLISION_XY, COLLISION_XY, size=2), rng.uniform(*COLLISION_HEIGHT)]
        )
        theta = rng.uniform(0.0, 2.0 * math.pi)
        u = np.array([math.cos(theta), math.sin(theta), 0.0])
        w = np.array([-u[1], u[0], 0.0])
        targets = [p - support(shapes[0], u) * u, p + support(shapes[1], -u) * u]
        dirs = [-u, u]
        if len(shapes) == 3:
            reach = max(support(s, w) for s in shapes[:2])
            targets.append(p + (reach + support(shapes[2], -w)) * w)
            dirs.append(w)
        starts = [
            t + rng.uniform(*LAUNCH_GAP) * d + np.array([0.0, 0.0, rng.uniform(*LAUNCH_RISE)])
            for t, d in zip(targets, dirs)
        ]
        inside = True
        for start, target, r in zip(starts, targets, radii):
            v0 = launch_velocity(start, target, collision_time, acceleration)
            path = (
                start + v0 * times[:, None] + 0.5 * np.asarray(acceleration) * times[:, None] ** 2
            )
            inside &= bool(np.all(path - r - MARGIN >= lo) and np.all(path + r + MARGIN <= hi))
        if inside:
            return Layout(np.array(starts), np.array(targets), p)
    raise RuntimeError("no collision layout fits the domain; objects are too large")


def fly(start, velocity, duration: float, acceleration, *, steps: int = 64) -> np.ndarray:
    """The position after ``duration`` s of x'' = acceleration(x, v, t) from ``start`` (m) at
    ``velocity`` (m/s), by classical Runge-Kutta in ``steps`` steps."""
    dt = duration / steps
    x, v = np.asarray(start, dtype=np.float64), np.asarray(velocity, dtype=np.float64)
    for i in range(steps):
        t = i * dt
        k1x, k1v = v, acceleration(x, v, t)
        k2x, k2v = v + dt / 2 * k1v, acceleration(x + dt / 2 * k1x, v + dt / 2 * k1v, t + dt / 2)
        k3x, k3v = v + dt / 2 * k2v, acceleration(x + dt / 2 * k2x, v + dt / 2 * k2v, t + dt / 2)
        k4x, k4v = v + dt * k3v, acceleration(x + dt * k3x, v + dt * k3v, t + dt)
        x = x + dt / 6 * (k1x + 2 * k2x + 2 * k3x + k4x)
        v = v + dt / 6 * (k1v + 2 * k2v + 2 * k3v + k4v)
    return x


def shoot_velocity(
    start, target, duration: float, acceleration, *, tol: float = 1e-7, iterations: int = 20
) -> np.ndarray:
    """The launch velocity (m/s) whose flight under x'' = acceleration(x, v, t) reaches
    ``target`` after ``duration`` s: Newton's method on the miss, its Jacobian by finite
    differences, from the ballistic velocity under the acceleration at the start.

    Why: a position-dependent field (a vortex, an attractor) bends the paths so that bodies
    aimed under a constant acceleration would pass each other without colliding.

    Raises RuntimeError if the miss does not fall below ``tol`` (m)."""
    start, target = np.asarray(start, dtype=np.float64), np.asarray(target, dtype=np.float64)
    a0 = acceleration(start, np.zeros(3), 0.0)
    v = launch_velocity(start, target, duration, a0)
    miss = fly(start, v, duration, acceleration) - target
    for _ in range(iterations):
        if np.linalg.norm(miss) < tol:
            return v
        h = 1e-4
        jac = np.stack(
            [
                (fly(start, v + h * e, duration, acceleration) - target - miss) / h
                for e in np.eye(3)
            ],
            axis=1,
        )
        v = v - np.linalg.solve(jac, miss)
        miss = fly(start, v, duration, acceleration) - target
    if np.linalg.norm(miss) < tol:
        return v
    raise RuntimeError(f"no launch velocity reaches the target: misses by {miss} m")
