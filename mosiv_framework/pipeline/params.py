"""Building simulation parameters and the optimiser's view of them.

The optimiser works on a vector of unconstrained leaves: initial velocities in m/s, and every
identified physical parameter through its ParamSpec's normalised coordinate in [0, 1] (log space
for stiffnesses and viscosities), so one learning rate suits parameters that differ by orders of
magnitude and bounds always hold.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from dataclasses import dataclass, field

import numpy as np
import torch

from mosiv_framework.laws import get_law
from mosiv_framework.laws.base import ParamSpec
from mosiv_framework.registry import get_registry
from mosiv_framework.types import ObjectParams, SimulationParams, World

log = logging.getLogger(__name__)

GROUND_FRICTION = ParamSpec(
    "ground_friction", "1", 0.0, 2.0, 0.3, description="table Coulomb coefficient"
)

#: Scaling every object's density and stiffness by one factor leaves the motion unchanged
#: (stress, weight and friction all scale alike), so one density fixes that gauge: the first
#: object's rho stays at its given value and the other objects' densities are identified
#: relative to it (their ratios decide how momentum is exchanged in a collision).
GAUGE_PARAM = "rho"


def initial_velocity_from_points(
    points: dict[int, torch.Tensor],
    *,
    fps: float,
    gravity: tuple[float, float, float],
    frames: int = 2,
    time_step: float = 0.0,
) -> dict[int, torch.Tensor]:
    """v0 per object from a least-squares ballistic fit of its centroid over ``frames`` frames.

    The centre of mass of a body in free flight moves as c(t) = c0 + v0 t + g t^2 / 2 whatever it
    does internally (rotation, vibration), so over the frames before any contact
    c(t) - g t^2 / 2 is a straight line in t whose slope is v0 (m/s). With ``frames=2`` this is
    v0 = (c(1) - c(0)) / dt - g dt / 2.

    ``time_step`` (s): the step h of the simulator that will roll v0 out. Symplectic Euler (v +=
    g h, then x += v h, as both MPM backends step) moves a free centroid by v0 t + g h^2 n (n + 1)
    / 2 after n steps, i.e. c0 + (v0 + g h / 2) t + g t^2 / 2: the line's slope is v0 + g h / 2,
    so g h / 2 is taken off. Without it, the velocities handed to that simulator are off by
    g h / 2 (3.4 mm/s at 24 fps and 60 substeps), which identification did not fully remove and
    a diagnosis then took for a gravity change (in every control scene of the diagnosis suite).
    """
    g = torch.tensor(gravity, dtype=torch.float64)
    out = {}
    for k, pts in points.items():
        n = max(2, min(int(frames), pts.shape[0]))
        t = torch.arange(n, dtype=torch.float64) / fps
        c = pts[:n].to(torch.float64).mean(dim=1) - 0.5 * t[:, None] ** 2 * g
        # slope of the least-squares line through (t_i, c_i): cov(t, c) / var(t)
        tc = t - t.mean()
        slope = (tc[:, None] * (c - c.mean(dim=0))).sum(0) / (tc**2).sum()
        out[k] = (slope - 0.5 * time_step * g).to(torch.float32)
    return out


#: how far apart (in point spacings) two bodies, or a body and the ground, may be while a
#: departure from the gravity parabola counts as their contact: an MPM engine's contact acts
#: across its kernel's support, about two cells of about 1.5 spacings on each side (Genesis
#: holds touching bodies sampled 1 cm apart 1.6-3.9 cm apart)
NEAR_SPACINGS = 5.0


def free_flight_frames(
    points: dict[int, torch.Tensor], world: World, *, gap: float, ballistic_tolerance: float = 0.0
) -> int:
    """How many leading frames show every object in free flight (at least 2).

    An object is free at a frame while its points stay more than ``gap`` (m) from every other
    object's points and from the ground plane; the count stops at the first frame where any
    object is not. With ``ballistic_tolerance`` > 0 an object is also not free from the frame
    its centroid leaves the gravity parabola through its earlier centroids
    (``ballistic_departure``) once it is within ``NEAR_SPACINGS`` point spacings of another
    object or the ground: a recording's contact can act before its surfaces meet, farther
    apart than the gap of a fine simulator grid, and a departure far from everything is a
    body force (wind, drag) that the diagnosis reads from these frames, not a contact.
    Frames after that depend on material parameters, which the velocity phase does not know
    yet.
    """
    from scipy.spatial import cKDTree

    ids = sorted(points)
    n_frames = min(p.shape[0] for p in points.values())
    near = dict.fromkeys(ids, gap)
    departs = dict.fromkeys(ids, n_frames)
    if ballistic_tolerance > 0 and n_frames > 0:
        for k in ids:
            spacing = point_spacing(points[k][0])
            near[k] = max(gap, NEAR_SPACINGS * spacing)
            departs[k] = ballistic_departure(points[k], world, ballistic_tolerance * spacing)
    for f in range(n_frames):
        clouds = {k: points[k][f].detach().cpu().double().numpy() for k in ids}
        closest = {k: math.inf for k in ids}  # to another object or the ground
        for i, a in enumerate(ids):
            if world.ground_height is not None:
                closest[a] = min(closest[a], clouds[a][:, 2].min() - world.ground_height)
            for b in ids[i + 1 :]:
                dist, _ = cKDTree(clouds[b]).query(clouds[a], k=1)
                closest[a] = min(closest[a], float(dist.min()))
                closest[b] = min(closest[b], float(dist.min()))
        if any(closest[k] < gap for k in ids):
            return max(2, f)
        if any(f >= departs[k] and closest[k] < near[k] for k in ids):
            return max(2, f)
    return max(2, n_frames)


def point_spacing(points: torch.Tensor) -> float:
    """The median distance (m) from each of ``points`` ([N, 3]) to its nearest neighbour; 0
    for fewer than two points."""
    from scipy.spatial import cKDTree

    cloud = points.detach().cpu().double().numpy()
    if cloud.shape[0] < 2:
        return 0.0
    dist, _ = cKDTree(cloud).query(cloud, k=2)
    return float(np.median(dist[:, 1]))


def ballistic_departure(points: torch.Tensor, world: World, threshold: float) -> int:
    """The first frame whose centroid of ``points`` ([F, N, 3]) leaves the gravity parabola
    through the centroids of the frames before it by more than ``threshold`` (m) and by more
    than four times that fit's own RMS residual (a noisy reconstruction's jitter), and whose
    next frame does too; F if none.

    In free flight a body's centroid follows c(t) = c0 + v0 t + g t^2 / 2 exactly, whatever
    the body does inside (spinning, wobbling: internal forces sum to zero); a contact pushes
    it off, and the push stays in every later frame, where a jittery centroid's does not.
    """
    centroids = points.detach().cpu().double().mean(dim=1).numpy()
    t = np.arange(len(centroids)) / world.fps
    falling = centroids - 0.5 * np.asarray(world.gravity, dtype=float) * t[:, None] ** 2
    for f in range(2, len(centroids)):
        basis = np.stack([np.ones(f), t[:f]], axis=1)  # c0 + v0 t per axis
        coef, *_ = np.linalg.lstsq(basis, falling[:f], rcond=None)
        fit_rms = float(np.sqrt(np.mean(np.sum((basis @ coef - falling[:f]) ** 2, axis=1))))
        bound = max(threshold, 4.0 * fit_rms)
        ahead = range(f, min(f + 2, len(centroids)))  # the last frame: its own residual decides
        misses = [np.linalg.norm(coef[0] + coef[1] * t[g] - falling[g]) for g in ahead]
        if all(m > bound for m in misses):
            return f
    return len(centroids)


def stiffness_ceilings(
    families: dict[int, str],
    values: dict[int, dict[str, float]],
    *,
    dx: float,
    dt: float,
    cfl: float,
) -> dict[int, dict[str, float]]:
    """Per object, the largest stiffness an explicit MPM step of ``dt`` (s) on cells of ``dx``
    (m) can follow: the P-wave speed sqrt(M / rho) must stay below ``cfl * dx / dt``.

    Density and nu are taken at the given values (law defaults where absent), so these are
    bounds for the start; ``ParameterVector.keep_stable`` holds the same limit at the values
    the optimiser reaches. The optimiser then cannot step into stiffnesses the simulator
    would diverge on, which otherwise costs a back-off per excursion.
    """
    m_per_rho = (cfl * dx / dt) ** 2  # the largest P-wave modulus per unit density
    out: dict[int, dict[str, float]] = {}
    for k, family in families.items():
        vals = {**get_law(family).defaults(), **values.get(k, {})}
        factors = p_wave_factors(family, vals)
        out[k] = {name: vals["rho"] * m_per_rho / f for name, f in factors.items()}
    return out


def wave_speed_limit(cfl: float, world: World, grid, substeps) -> float | None:
    """The P-wave speed (m/s) an explicit step can follow: ``cfl`` cells of ``world.extent /
    grid`` per substep of ``1 / (world.fps * substeps)``; None without a positive cfl, grid
    and substep count (a simulator without a grid, or no cap asked for)."""
    if not (cfl > 0 and isinstance(grid, int) and grid > 0):
        return None
    if not (isinstance(substeps, int) and substeps > 0):
        return None
    return cfl * (world.extent / grid) * world.fps * substeps


def p_wave_factors(family: str, values: dict[str, float]) -> dict[str, float]:
    """How much each stiffness (Pa) of ``family``'s law adds to the P-wave modulus M = rho c^2
    per pascal, at the Poisson ratio in ``values`` (0.25 where the law has none):
    (1 - nu) / ((1 + nu)(1 - 2 nu)) for E, 1 for a bulk modulus K, 4/3 for a shear modulus G.
    A higher nu gives a larger M for the same E, so E's cap falls with nu."""
    factors = {}
    for spec in get_law(family).all_params:
        if spec.name == "E":
            nu = values.get("nu", 0.25)
            factors["E"] = (1 - nu) / ((1 + nu) * (1 - 2 * nu))
        elif spec.name == "bulk_modulus":
            factors["bulk_modulus"] = 1.0
        elif spec.name == "shear_modulus":
            factors["shear_modulus"] = 4.0 / 3.0
    return factors


def _capped(spec: ParamSpec, cap: float | None) -> ParamSpec:
    """``spec`` with its upper bound lowered to ``cap`` (never below its lower bound)."""
    if cap is None or not math.isfinite(cap) or cap >= spec.upper:
        return spec
    upper = max(cap, spec.lower * (1 + 1e-6))
    return dataclasses.replace(spec, upper=upper, default=min(spec.default, upper))


@dataclass
class ParameterVector:
    """The identified quantities of a scene as optimisable leaves.

    ``velocity`` leaves are m/s; ``normalized`` leaves are ParamSpec coordinates in [0, 1],
    keyed ``objK.NAME``, ``ground_friction`` or ``term.TERM.NAME`` (physics-term parameters,
    [3] leaves for vector parameters). ``fixed_terms`` holds the physics-term parameters that
    are switched on but not identified (SI values).
    """

    families: dict[int, str]
    fixed: dict[int, dict[str, float]]
    velocity: dict[int, torch.Tensor]
    normalized: dict[str, torch.Tensor]
    specs: dict[str, ParamSpec] = field(default_factory=dict)
    fixed_terms: dict[str, dict[str, torch.Tensor]] = field(default_factory=dict)
    #: the simulator's stability limit on P-wave speeds (m/s; ``cfl * dx / dt``), which
    #: ``keep_stable`` holds at the current densities and Poisson ratios; None: no limit
    wave_speed_limit: float | None = None

    @classmethod
    def create(
        cls,
        families: dict[int, str],
        velocities: dict[int, torch.Tensor],
        *,
        values: dict[int, dict[str, float]] | None = None,
        ground_friction: float | None = GROUND_FRICTION.default,
        identify: tuple[str, ...] | None = None,
        identify_friction: bool = True,
        identify_ground_friction: bool = True,
        ceilings: dict[int, dict[str, float]] | None = None,
        terms: dict[str, dict[str, torch.Tensor]] | None = None,
        identify_terms: tuple[str, ...] = (),
        wave_speed_limit: float | None = None,
    ) -> ParameterVector:
        """Leaves for every parameter of every object's law (from ``values`` or defaults).

        ``identify`` restricts which parameter names are optimised (default: all but the
        first object's density, see GAUGE_PARAM); the rest are kept fixed at their value.
        ``ceilings`` lowers upper bounds per object and parameter (see ``stiffness_ceilings``);
        a start value above its ceiling starts at the ceiling. ``wave_speed_limit`` (m/s) is
        the limit those ceilings come from, for ``keep_stable``.
        ``terms`` switches physics terms on (term name -> parameter name -> SI value, as in
        SimulationParams.terms); those named in ``identify_terms`` get leaves in the term's
        normalised space (within its ParamSpec bounds), the others stay fixed.
        """
        values = values or {}
        fixed: dict[int, dict[str, float]] = {}
        normalized: dict[str, torch.Tensor] = {}
        specs: dict[str, ParamSpec] = {}
        gauge_object = min(families)
        for k, family in families.items():
            law = get_law(family)
            start = {**law.defaults(), **values.get(k, {})}
            law.validate(start, where=f"object {k}: ")
            fixed[k] = {}
            for spec in law.all_params:
                if identify is None:
                    free = not (spec.name == GAUGE_PARAM and k == gauge_object)
                else:
                    free = spec.name in identify
                if spec.name == "friction" and (not identify_friction or len(families) < 2):
                    free = False  # inter-object friction only matters with two or more bodies
                if free:
                    key = f"obj{k}.{spec.name}"
                    spec = _capped(spec, (ceilings or {}).get(k, {}).get(spec.name))
                    specs[key] = spec
                    value = min(float(start[spec.name]), spec.upper)
                    normalized[key] = spec.to_normalized(torch.tensor(value))
                else:
                    fixed[k][spec.name] = float(start[spec.name])
        if ground_friction is not None:
            if identify_ground_friction:
                specs["ground_friction"] = GROUND_FRICTION
                normalized["ground_friction"] = GROUND_FRICTION.to_normalized(
                    torch.tensor(float(ground_friction))
                )
            else:
                fixed[0] = {"ground_friction": float(ground_friction)}
        fixed_terms: dict[str, dict[str, torch.Tensor]] = {}
        unknown = sorted(set(identify_terms) - set(terms or {}))
        if unknown:
            raise ValueError(
                f"identify_terms {unknown} are not among the terms {sorted(terms or {})}"
            )
        for name, term_values in (terms or {}).items():
            term_specs = term_param_specs(name)
            for pname, value in term_values.items():
                value = torch.as_tensor(value, dtype=torch.float32).detach().clone()
                if name in identify_terms:
                    key = f"term.{name}.{pname}"
                    specs[key] = term_specs[pname]
                    normalized[key] = term_specs[pname].to_normalized(value)
                else:
                    fixed_terms.setdefault(name, {})[pname] = value
        velocity = {k: v.detach().clone().to(torch.float32) for k, v in velocities.items()}
        for leaf in [*velocity.values(), *normalized.values()]:
            leaf.requires_grad_(True)
        vector = cls(
            dict(families), fixed, velocity, normalized, specs, fixed_terms, wave_speed_limit
        )
        vector.keep_stable()  # a start past the limit starts at it
        return vector

    def keep_stable(self) -> list[str]:
        """Lower the identified stiffnesses of every object whose P-wave speed, at its current
        density and Poisson ratio, exceeds ``wave_speed_limit``, so that it runs at the limit;
        returns the keys lowered (a stiffness already at its lower bound cannot go further
        and is not reported).

        The ceilings of ``create`` hold at the start's density and Poisson ratio only, and
        each stiffness alone. As the optimiser raises an elastic body's nu (or lowers its
        density) at a capped E, its P-wave speed grows past the limit: at nu = 0.41 instead of
        the default 0.25 by a factor 1.4, which the observed frames may survive and a longer
        prediction does not. A law with two moduli (bulk and shear) sums them into one P-wave
        modulus: both identified ones are scaled by the same factor.
        """
        if self.wave_speed_limit is None:
            return []
        lowered = []
        with torch.no_grad():
            for k, obj in self.physical().objects.items():
                values = {n: float(v) for n, v in obj.values.items() if v.numel() == 1}
                values = {**get_law(obj.family).defaults(), **values}
                factors = p_wave_factors(obj.family, values)
                parts = {name: values[name] * f for name, f in factors.items()}
                limit = values["rho"] * self.wave_speed_limit**2
                free = {n: m for n, m in parts.items() if f"obj{k}.{n}" in self.normalized}
                excess = sum(parts.values()) - limit
                if not free or excess <= 1e-5 * limit:
                    continue
                if excess >= sum(free.values()):  # the fixed stiffnesses alone are past it
                    log.warning(
                        "object %d: its fixed stiffnesses alone exceed the simulator's stability "
                        "limit (P-wave speed %.3g m/s); raise simulator.substeps",
                        k,
                        self.wave_speed_limit,
                    )
                    continue
                scale = (1.0 - excess / sum(free.values())) * (1 - 1e-5)
                for name in free:
                    key = f"obj{k}.{name}"
                    u = self.specs[key].to_normalized(torch.tensor(values[name] * scale))
                    before = self.normalized[key].clone()
                    self.normalized[key].copy_(u.clamp(0.0, 1.0))
                    if not torch.equal(before, self.normalized[key]):
                        lowered.append(key)
        return lowered

    def move_to_centre(self) -> None:
        """Move every identified object parameter and the ground friction to the centre of its
        law's bounds: the geometric centre sqrt(lower * upper) for scale parameters (E of
        1e3-1e7 Pa starts at 1e5), the midpoint for the others; where a stiffness ceiling lowered
        the upper bound below that centre, the start is the ceiling. A start that knows nothing
        of the data or of any generator's ranges (the law defaults sit at the centre of the
        synthetic generator's paper ranges). Physics-term leaves keep their start."""
        with torch.no_grad():
            for key, u in self.normalized.items():
                if key.startswith("term."):
                    continue
                if key == "ground_friction":
                    law_spec = GROUND_FRICTION
                else:
                    owner, name = key.split(".", 1)
                    law_spec = get_law(self.families[int(owner[3:])]).param(name)
                centre = centre_value(law_spec)
                u.copy_(self.specs[key].to_normalized(torch.tensor(centre)).clamp(0.0, 1.0))
        self.keep_stable()  # the centre's density can be below the one the ceilings assumed

    def set_ground_friction(self, value: float) -> None:
        """The ground's coefficient set to ``value`` (clamped to its bounds), whether it is
        identified or held fixed; a vector without a ground is left alone."""
        value = min(GROUND_FRICTION.upper, max(GROUND_FRICTION.lower, float(value)))
        with torch.no_grad():
            if "ground_friction" in self.normalized:
                u = GROUND_FRICTION.to_normalized(torch.tensor(value))
                self.normalized["ground_friction"].copy_(u.clamp(0.0, 1.0))
            elif 0 in self.fixed and "ground_friction" in self.fixed[0]:
                self.fixed[0]["ground_friction"] = value

    def physical(self) -> SimulationParams:
        """The SimulationParams these leaves stand for (differentiable w.r.t. the leaves)."""
        objects = {}
        for k, family in self.families.items():
            vals = {n: torch.tensor(v, dtype=torch.float32) for n, v in self.fixed[k].items()}
            for key, u in self.normalized.items():
                if key.startswith(f"obj{k}."):
                    vals[key.split(".", 1)[1]] = (
                        self.specs[key].from_normalized(u).to(torch.float32)
                    )
            objects[k] = ObjectParams(family, vals)
        if "ground_friction" in self.normalized:
            gf = GROUND_FRICTION.from_normalized(self.normalized["ground_friction"])
        else:
            gf = torch.tensor(self.fixed.get(0, {}).get("ground_friction", GROUND_FRICTION.default))
        terms = {name: dict(values) for name, values in self.fixed_terms.items()}
        for key, u in self.normalized.items():
            if key.startswith("term."):
                _, name, pname = key.split(".", 2)
                terms.setdefault(name, {})[pname] = self.specs[key].from_normalized(u).float()
        return SimulationParams(objects, dict(self.velocity), gf.to(torch.float32), terms)

    def to_json(self) -> dict:
        """Plain numbers: per object family, parameter values and initial velocity; the ground
        friction; and, when terms are switched on, their values (lists for vectors)."""
        params = self.physical().detached()
        out = {
            "objects": {
                str(k): {
                    "family": p.family,
                    "params": {n: float(v.detach()) for n, v in sorted(p.values.items())},
                    "initial_velocity": [float(x) for x in params.initial_velocity[k].detach()],
                }
                for k, p in params.objects.items()
            },
            "ground_friction": float(torch.as_tensor(params.ground_friction).detach()),
        }
        if params.terms:
            out["terms"] = terms_json(params.terms)
        return out

    @staticmethod
    def from_json(data: dict) -> SimulationParams:
        objects, v0 = {}, {}
        for k, obj in data["objects"].items():
            objects[int(k)] = ObjectParams(
                obj["family"], {n: torch.tensor(float(v)) for n, v in obj["params"].items()}
            )
            v0[int(k)] = torch.tensor(obj["initial_velocity"], dtype=torch.float32)
        terms = {
            name: {p: torch.tensor(v, dtype=torch.float32) for p, v in values.items()}
            for name, values in data.get("terms", {}).items()
        }
        return SimulationParams(objects, v0, torch.tensor(float(data["ground_friction"])), terms)


def centre_value(spec: ParamSpec) -> float:
    """The centre of ``spec``'s bounds: geometric for log-scale parameters, else arithmetic."""
    if spec.log_scale:
        return math.sqrt(spec.lower * spec.upper)
    return 0.5 * (spec.lower + spec.upper)


def term_param_specs(name: str) -> dict[str, ParamSpec]:
    """Parameter name -> ParamSpec of the registered physics term ``name``."""
    term = get_registry().create("physics_term", name, {})
    return {spec.name: spec for spec in term.params}


def terms_json(terms: dict[str, dict[str, torch.Tensor]]) -> dict:
    """SimulationParams.terms as plain numbers: floats for scalars, lists for vectors."""
    return {
        name: {p: v.detach().cpu().tolist() for p, v in sorted(values.items())}
        for name, values in sorted(terms.items())
    }
