"""The ``synth`` SceneSource: plan a scene, simulate it, render it, write it (mosiv-scene/1).

1. plan (``plan_scene``): shapes, sizes and rotations, particles inside each mesh, material
   parameters, a mid-air collision layout (``layout.plan_collision``), concealed effects,
   cameras on the hemisphere and the scene's look; everything derives from ``seed``;
2. simulate with the simulator registered under ``options.simulator``; concealed body forces
   become its PhysicsTerms, a concealed ground friction replaces the table's coefficient;
3. render every frame from every camera (``surface`` + ``render``) and write rgb, masks,
   gt/points.npz, gt/params.json and, only when something is concealed, gt/effects.json.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from importlib import metadata
from pathlib import Path

import numpy as np
import torch

from mosiv_framework.conceal import TERM_KINDS, Effect, parse_conceal
from mosiv_framework.errors import ConfigError
from mosiv_framework.interfaces import SceneSource
from mosiv_framework.laws import get_law
from mosiv_framework.scene.cameras import Camera
from mosiv_framework.scene.check import GT_PARAM_NAMES
from mosiv_framework.scene.io import SceneObject, SceneWriter
from mosiv_framework.scene.protocol import hemisphere_cameras
from mosiv_framework.types import ObjectParams, ParticleSet, SimulationParams, World
from mosiv_synth.layout import Layout, plan_collision
from mosiv_synth.materials import MATERIAL_RANGES, RANGE_PRESETS, draw, range_table, sample_params
from mosiv_synth.options import SynthOptions
from mosiv_synth.render import Style, backdrop, draw_style, render_view
from mosiv_synth.sampling import random_rotation, sample_inside
from mosiv_synth.shapes import SHAPE_NAMES, make_shape
from mosiv_synth.stability import required_substeps, stability_numbers
from mosiv_synth.surface import particle_surface

# The simulation box (m): the table (z = 0) spans it; 0.8 m across gives room for launches
# 0.2-0.3 m from the collision point and for drifting after it; 0.6 m is well above any apex.
DOMAIN_LOWER = (-0.4, -0.4, 0.0)
DOMAIN_UPPER = (0.4, 0.4, 0.6)
GROUND_HEIGHT = 0.0
DECLARED_GRAVITY = (0.0, 0.0, -9.8)


@dataclass
class ScenePlan:
    """Everything decided before simulating: per object (ids 1..K, list order) its shape,
    family, particles at frame 0 (m), true parameters and launch velocity; plus layout,
    ground friction (nominal and used), concealed effects, cameras and style."""

    name: str
    shapes: list[str]
    materials: list[str]
    sizes: list[float]
    rotations: list[np.ndarray]
    particles: list[np.ndarray]
    params: list[dict[str, float]]
    layout: Layout
    collision_frame: int
    ground_friction_nominal: float
    ground_friction: float
    effects: list[Effect]
    cameras: list[Camera]
    style: Style
    #: scene material -> the law that simulates it where not its own (SynthOptions.laws)
    laws: dict[str, str] = field(default_factory=dict)

    @property
    def world(self) -> World:
        """The world as scene.json declares it (concealed effects are not part of it)."""
        return World(DOMAIN_LOWER, DOMAIN_UPPER, DECLARED_GRAVITY, GROUND_HEIGHT)


def true_acceleration(effects: list[Effect]) -> np.ndarray:
    """Uniform acceleration (m/s^2) of free flight in the generating simulation: the declared
    or concealed gravity plus any concealed wind (drag is velocity-dependent, left out)."""
    kinds = {e.kind: e for e in effects}
    g = np.array(
        kinds["gravity"].params["acceleration"] if "gravity" in kinds else DECLARED_GRAVITY
    )
    if "wind" in kinds:
        g = g + np.array(kinds["wind"].params["acceleration"])
    return g


def plan_scene(opts: SynthOptions) -> ScenePlan:
    """Draw every random choice of the scene from ``opts.seed``."""
    rng = np.random.default_rng(opts.seed)
    k = opts.n_objects
    shapes = opts.shapes or [str(s) for s in rng.choice(SHAPE_NAMES, size=k, replace=False)]
    families = tuple(MATERIAL_RANGES)
    materials = opts.materials or [str(m) for m in rng.choice(families, size=k, replace=False)]
    sizes, rotations, clouds, params = [], [], [], []
    for shape, family in zip(shapes, materials):
        mesh = make_shape(shape, rng)
        rot = random_rotation(rng)
        mesh.vertices = mesh.vertices @ rot.T
        points = sample_inside(mesh, opts.particle_spacing, offset=rng.uniform(0.0, 1.0, size=3))
        sizes.append(float(np.max(mesh.extents)))
        rotations.append(rot)
        clouds.append(points - points.mean(axis=0))
        params.append(sample_params(family, rng, opts.ranges))
    effects = parse_conceal(opts.conceal)
    for effect in effects:
        if effect.kind == "object_friction":  # the truth, so gt/params.json records it
            for p in params:
                p["friction"] = float(effect.params["coefficient"])
    frame = opts.collision_frame or _auto_collision_frame(opts, rng)
    layout = plan_collision(
        clouds,
        collision_time=frame / opts.fps,
        acceleration=true_acceleration(effects),
        contact=opts.particle_spacing,
        domain_lower=DOMAIN_LOWER,
        domain_upper=DOMAIN_UPPER,
        ground_height=GROUND_HEIGHT,
        rng=rng,
    )
    nominal = draw(rng, RANGE_PRESETS[opts.ranges][1])
    used = next((e.params["coefficient"] for e in effects if e.kind == "ground_friction"), nominal)
    cameras = hemisphere_cameras(
        opts.n_cameras, resolution=opts.resolution, azimuth0=float(rng.uniform(0, 2 * np.pi))
    )
    return ScenePlan(
        name=opts.scene_name or f"{'-'.join(materials)}-{opts.seed:04d}",
        shapes=list(shapes),
        materials=list(materials),
        sizes=sizes,
        rotations=rotations,
        particles=[c + x0 for c, x0 in zip(clouds, layout.starts)],
        params=params,
        layout=layout,
        collision_frame=int(frame),
        ground_friction_nominal=nominal,
        ground_friction=float(used),
        effects=effects,
        cameras=cameras,
        style=draw_style(list(shapes), rng, ground_height=GROUND_HEIGHT),
        laws=dict(opts.laws),
    )


def _auto_collision_frame(opts: SynthOptions, rng: np.random.Generator) -> int:
    # inside the first half of the observed frames, so identification sees the collision, the
    # fall and the landing (paper protocol: 15 of 30 frames observed)
    # clips shorter than 3 frames (previews, projection tests) end before any collision: the
    # planned one then lies just after the clip, at frame 2
    lo = max(2, opts.observed_frames // 3)
    hi = max(lo, min(opts.observed_frames // 2, opts.n_frames - 1))
    return int(rng.integers(lo, hi + 1))


def simulate(plan: ScenePlan, opts: SynthOptions) -> np.ndarray:
    """Positions [n_frames, N, 3] (m) of all particles (objects in order) from the simulator
    registered as ``opts.simulator``, with the concealed effects switched on."""
    from mosiv_framework.registry import get_registry

    try:
        sim = get_registry().create("simulator", opts.simulator, simulator_options(plan, opts))
    except ConfigError as exc:  # name the scene's options, not the identification's simulator
        raise ConfigError(
            f"generating the scene with simulator {opts.simulator!r} "
            f"(scene.source.simulator / simulator_options): {exc}"
        ) from exc
    unsupported = sorted(set(simulated_materials(plan)[0]) - set(sim.supported_laws))
    if unsupported:
        raise ConfigError(
            f"simulator {opts.simulator!r} does not implement material(s) {unsupported}; "
            f"it supports {sorted(sim.supported_laws)}"
        )
    world = plan.world
    terms: dict[str, dict[str, torch.Tensor]] = {}
    for effect in plan.effects:
        if effect.kind not in TERM_KINDS:
            continue  # friction and plasticity act through SimulationParams (see below)
        if effect.kind == "gravity" and "gravity" not in sim.supported_terms:
            # replacing the world's gravity is the same physics for a backend without the term
            world = dataclasses.replace(world, gravity=effect.params["acceleration"])
            continue
        if effect.kind not in sim.supported_terms:
            raise ConfigError(
                f"simulator {opts.simulator!r} cannot conceal {effect.kind!r}: it implements "
                f"the physics terms {sorted(sim.supported_terms)}"
            )
        terms[effect.kind] = {
            n: torch.tensor(v, dtype=torch.float32) for n, v in effect.params.items()
        }
    particles, params = _simulation_inputs(plan, opts.particle_spacing, terms)
    with torch.no_grad():
        traj = sim.rollout(
            particles,
            params,
            world=dataclasses.replace(world, fps=opts.fps),
            frames=opts.n_frames - 1,
        )
    return traj.positions.detach().cpu().numpy().astype(np.float32)


def simulator_options(plan: ScenePlan, opts: SynthOptions) -> dict:
    """The simulator options the scene is generated with: the requested ones, and for the wide
    preset at least the substeps ``stability.required_substeps`` asks for its draws."""
    options = dict(opts.simulator_options)
    if opts.ranges == "paper":  # stable at the protocol's settings; scenes reproduce as given
        return options
    dx, substeps = _grid_and_substeps(opts)
    families, values = simulated_materials(plan)
    options["substeps"] = required_substeps(
        families, values, dx=dx, fps=opts.fps, requested=substeps
    )
    return options


def _grid_and_substeps(opts: SynthOptions, options: dict | None = None) -> tuple[float, int]:
    """Grid cell (m) and substeps of the simulator ``opts`` name, from ``options`` (default:
    the requested ones) or the simulator's defaults (its grid counts cells along the domain's
    longest side, as ``mosiv_framework.simulation.MPMOptions`` defines)."""
    from mosiv_framework.registry import get_registry

    options = dict(opts.simulator_options) if options is None else options
    schema = get_registry().get("simulator", opts.simulator).options
    defaults = {f.name: f.default for f in dataclasses.fields(schema)} if schema else {}
    grid = int(options.get("grid", defaults.get("grid", 64)))
    substeps = int(options.get("substeps", defaults.get("substeps", 100)))
    extent = max(u - lo for lo, u in zip(DOMAIN_LOWER, DOMAIN_UPPER))
    return extent / grid, substeps


def stability_record(plan: ScenePlan, opts: SynthOptions) -> dict:
    """Grid cell, substeps and the CFL and viscous numbers the scene was simulated with."""
    dx, substeps = _grid_and_substeps(opts, simulator_options(plan, opts))
    families, values = simulated_materials(plan)
    numbers = stability_numbers(families, values, dx=dx, dt=1.0 / (opts.fps * substeps))
    return {"dx_m": dx, "substeps": substeps, **numbers}


def simulated_materials(plan: ScenePlan) -> tuple[list[str], list[dict[str, float]]]:
    """Family and parameters each object is simulated with: the declared ones, except that a
    concealed ``plasticity`` turns every declared elastic body into plasticine (same E, nu)
    yielding at the concealed stress, and that ``plan.laws`` names the law simulating a
    material (another stress with the same parameters)."""
    plastic = next((e for e in plan.effects if e.kind == "plasticity"), None)
    families, values = [], []
    for fam, p in zip(plan.materials, plan.params):
        if plastic is not None and fam == "elastic":
            fam, p = "plasticine", {**p, "yield_stress": float(plastic.params["yield_stress"])}
        families.append(plan.laws.get(fam, fam))
        values.append(dict(p))
    return families, values


def _simulation_inputs(
    plan: ScenePlan, spacing: float, terms
) -> tuple[ParticleSet, SimulationParams]:
    ids = np.concatenate([np.full(len(p), k) for k, p in enumerate(plan.particles, start=1)])
    positions = torch.tensor(np.concatenate(plan.particles), dtype=torch.float32)
    families, values = simulated_materials(plan)
    particles = ParticleSet(
        positions,
        torch.full((len(ids),), spacing**3, dtype=torch.float32),
        torch.tensor(ids, dtype=torch.long),
        {k: m for k, m in enumerate(families, start=1)},
    )
    objects = {
        k: ObjectParams(fam, {n: torch.tensor(v, dtype=torch.float32) for n, v in p.items()})
        for k, (fam, p) in enumerate(zip(families, values), start=1)
    }
    velocity = {
        k: torch.tensor(v, dtype=torch.float32)
        for k, v in enumerate(plan.layout.velocities, start=1)
    }
    params = SimulationParams(
        objects, velocity, torch.tensor(plan.ground_friction, dtype=torch.float32), terms
    )
    return particles, params


def gt_params_document(plan: ScenePlan, opts: SynthOptions) -> dict:
    """gt/params.json: scene-format names under ``params``, the law's own complete set under
    each object's ``generator_params``, scene-wide generator settings at the top."""
    try:
        version = metadata.version("mosiv-synth")
    except metadata.PackageNotFoundError:
        version = "unknown"
    objects = []
    for k, (shape, fam, p) in enumerate(zip(plan.shapes, plan.materials, plan.params), start=1):
        get_law(fam).validate(p)
        objects.append(
            {
                "id": k,
                "name": shape,
                "material": fam,
                "params": {n: v for n, v in p.items() if n in GT_PARAM_NAMES},
                "generator_params": dict(p),
                "initial_velocity": [float(x) for x in plan.layout.velocities[k - 1]],
                "initial_centroid": [float(x) for x in plan.layout.starts[k - 1]],
                "size_m": plan.sizes[k - 1],
                "rotation": plan.rotations[k - 1].tolist(),
                "n_particles": len(plan.particles[k - 1]),
                "albedo_linear_rgb": list(plan.style.object_colors[k]),
            }
        )
    return {
        "generator": f"mosiv-synth {version} (simulator {opts.simulator})",
        "generator_params": {
            **({"laws": dict(plan.laws)} if plan.laws else {}),
            "ground_friction": plan.ground_friction,
            "ground_friction_nominal": plan.ground_friction_nominal,
            "simulator": opts.simulator,
            "simulator_options": simulator_options(plan, opts),
            "stability": stability_record(plan, opts),
            "particle_spacing": opts.particle_spacing,
            "particle_volume": opts.particle_spacing**3,
            "collision_frame": plan.collision_frame,
            "collision_time_s": plan.layout.collision_time,
            "collision_point": plan.layout.collision_point.tolist(),
            "seed": opts.seed,
        },
        "ranges": opts.ranges,
        "range_table": range_table(opts.ranges),
        "objects": objects,
    }


class SynthSource(SceneSource):
    """Generates one benchmark scene per ``generate`` call from its options."""

    def __init__(self, options: SynthOptions) -> None:
        self.options = options

    def declared(self) -> tuple[World, list[str] | None]:
        """The World and object families scene.json will declare, known without generating
        (recipe validation checks the simulator's stiffness cap against them); families None
        when they are drawn at random."""
        world = World(DOMAIN_LOWER, DOMAIN_UPPER, DECLARED_GRAVITY, GROUND_HEIGHT, self.options.fps)
        return world, list(self.options.materials) or None

    def generate(self, out_dir: Path) -> Path:
        """Plan, simulate, render and write the scene into ``out_dir`` (must be empty or new)."""
        from tqdm import tqdm

        out_dir = Path(out_dir)
        if out_dir.exists() and any(out_dir.iterdir()):
            raise ConfigError(
                f"output folder {str(out_dir)!r} is not empty; give a new or empty folder"
            )
        opts = self.options
        plan = plan_scene(opts)
        positions = simulate(plan, opts)
        bounds = np.cumsum([0] + [len(p) for p in plan.particles])
        per_object = {
            k: positions[:, bounds[k - 1] : bounds[k]] for k in range(1, len(plan.particles) + 1)
        }
        world = plan.world
        writer = SceneWriter(
            out_dir,
            name=plan.name,
            fps=opts.fps,
            n_frames=opts.n_frames,
            observed_frames=opts.observed_frames,
            objects=[
                SceneObject(k, s, m)
                for k, (s, m) in enumerate(zip(plan.shapes, plan.materials), start=1)
            ],
            cameras=plan.cameras,
            domain_lower=world.domain_lower,
            domain_upper=world.domain_upper,
            gravity=world.gravity,
            ground_height=world.ground_height,
        )
        bar = tqdm(
            total=opts.n_frames * len(plan.cameras),
            desc=f"rendering {plan.name}",
            unit="view",
            disable=not opts.progress,
        )
        backs = {cam.id: backdrop(cam, plan.style) for cam in plan.cameras}
        for t in range(opts.n_frames):
            surfaces = {
                k: particle_surface(pts[t].astype(np.float64), opts.particle_spacing)
                for k, pts in per_object.items()
            }
            for cam in plan.cameras:
                rgb, mask = render_view(cam, surfaces, plan.style, back=backs[cam.id])
                writer.write_frame(cam.id, t, rgb=rgb, mask=mask)
                bar.update(1)
        bar.close()
        writer.write_gt(
            points=per_object,
            params=gt_params_document(plan, opts),
            effects=[e.to_json() for e in plan.effects] if plan.effects else None,
        )
        return writer.finish()
