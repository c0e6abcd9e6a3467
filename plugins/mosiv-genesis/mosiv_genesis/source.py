"""The ``genesis`` SceneSource: the paper's benchmark protocol run by the Genesis engine.

1. plan in numpy (``plan``): shapes, parameters, collision layout, cameras, colours;
2. build a Genesis scene: MPM bodies (Elastic, ElastoPlastic with von Mises, Liquid, Sand,
   Snow) from the object meshes, a rigid table plane, concealed effects as Genesis force fields
   or as its gravity, one pinhole camera per view (rasteriser: RGB + entity segmentation);
3. aim each object from its sampled particles (launch velocity under the true acceleration),
   step one frame at a time and record particles, RGB and masks through the core SceneWriter.
"""

from __future__ import annotations

import tempfile
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path

import numpy as np

from mosiv_framework.conceal import parse_conceal
from mosiv_framework.conceal_fields import field_acceleration
from mosiv_framework.errors import ConfigError
from mosiv_framework.interfaces import SceneSource
from mosiv_framework.scene.cameras import Camera
from mosiv_framework.scene.io import SceneObject, SceneWriter
from mosiv_framework.scene.protocol import hemisphere_directions, launch_velocity
from mosiv_genesis import plan as P
from mosiv_genesis.options import GENESIS_KINDS, GenesisOptions

# Genesis keeps MPM particles inside its grid box shrunk by this many cells on every side; the
# box is grown by as much so that this boundary is the declared domain: its floor is the table,
# which stops the normal motion. The rigid plane drawn there is coupled to the MPM grid too and
# adds Coulomb friction (its coup_friction, 0.1 by default) on the nodes at or below it: MOSIV's
# ground with ground_friction 0.1 (docs/PHYSICS.md, Ground friction)
MPM_BOUNDARY_CELLS = 3
# Genesis' MPM solves every body on one grid: bodies that touch share grid velocities (no
# friction coefficient between them; elastic bodies can still spring apart); gt/params.json says so, for identification
CONTACT_MODE = "single_grid"


def _genesis(backend: str):
    """Import and initialise Genesis once per process (``gs.init`` may run only once)."""
    try:
        import genesis as gs
    except ImportError as exc:
        raise ConfigError(
            "scene source 'genesis' needs the Genesis engine: pip install 'mosiv-genesis[engine]' "
            f"(genesis-world); import failed: {exc}"
        ) from exc
    if not getattr(gs, "_initialized", False):
        gs.init(
            backend=gs.cpu if backend == "cpu" else gs.gpu, precision="32", logging_level="warning"
        )
    return gs


def _material(gs, family: str, p: dict[str, float]):
    mpm = gs.materials.MPM
    common = {"E": p["E"], "nu": p["nu"], "rho": p["rho"], "sampler": "regular"}
    if family == "elastic":
        return mpm.Elastic(**common)
    if family == "plasticine":
        return mpm.ElastoPlastic(
            **common, use_von_mises=True, von_mises_yield_stress=p["yield_stress"]
        )
    if family == "sand":
        return mpm.Sand(**common, friction_angle=p["friction_angle"])
    if family == "newtonian":
        return mpm.Liquid(**common, viscous=True)
    return mpm.Snow(**common, yield_lower=p["yield_lower"], yield_higher=p["yield_higher"])


def _vis_mode(requested: str, family: str) -> str:
    """Genesis skins the object mesh ("visual") only onto solids; granular and liquid bodies
    have no rest shape to skin, so they are drawn as their particles instead."""
    if requested == "visual" and family in ("sand", "newtonian"):
        return "particle"
    return requested


def _camera_record(cam, cid: str, resolution: int) -> Camera:
    """A scene-format camera from what Genesis renders with: its OpenCV extrinsics, re-
    orthonormalised in float64 (Genesis returns float32), and its pinhole intrinsics."""
    ext = np.asarray(cam.extrinsics, dtype=np.float64)
    u, _, vt = np.linalg.svd(ext[:3, :3])
    ext[:3, :3] = u @ vt
    k = np.asarray(cam.intrinsics, dtype=np.float64)
    return Camera(
        id=cid, width=resolution, height=resolution,
        fx=float(k[0, 0]), fy=float(k[1, 1]), cx=float(k[0, 2]), cy=float(k[1, 2]),
        world_to_camera=ext,
    )  # fmt: skip


@dataclass
class _Plan:
    """Everything decided in numpy before Genesis is touched (see ``_plan``)."""

    name: str
    shapes: list[str]
    families: list[str]
    meshes: list
    params: list[dict[str, float]]
    frame_c: int  # the frame at which the objects meet
    effects: list
    gravity: np.ndarray  # the true gravity (a concealed "gravity" effect replaces the declared)
    wind: np.ndarray | float
    layout: P.Layout
    substeps: int  # MPM substeps per frame, raised from the requested ones for stiff draws


def _plan(opts: GenesisOptions, rng: np.random.Generator) -> _Plan:
    """Shapes, materials, sizes, parameters, collision frame, effects and layout, drawn from
    ``rng`` in a fixed order (the same seed gives the same scene)."""
    k = opts.n_objects
    shapes = opts.shapes or [str(s) for s in rng.choice(P.SHAPE_NAMES, k, replace=False)]
    families = opts.materials or [str(m) for m in rng.choice(P.GENESIS_FAMILIES, k)]
    sizes = rng.uniform(*P.SIZE_LIMITS, size=k)
    meshes = [P.make_mesh(s, float(z), P.random_rotation(rng)) for s, z in zip(shapes, sizes)]
    params = [P.sample_params(f, rng, opts.ranges) for f in families]
    frame_c = opts.collision_frame or int(
        rng.integers(max(2, opts.observed_frames // 3), max(3, opts.observed_frames // 2) + 1)
    )
    effects = parse_conceal(opts.conceal, kinds=GENESIS_KINDS)
    gravity = np.array(
        next(
            (e.params["acceleration"] for e in effects if e.kind == "gravity"),
            P.DECLARED_GRAVITY,
        )
    )
    wind = next((np.array(e.params["acceleration"]) for e in effects if e.kind == "wind"), 0.0)
    layout = P.plan_layout(
        [m.vertices for m in meshes],
        radii=[float(np.max(np.linalg.norm(m.vertices, axis=1))) for m in meshes],
        collision_time=frame_c / opts.fps,
        acceleration=gravity + wind,
        rng=rng,
    )
    name = opts.scene_name or f"{'-'.join(families)}-{opts.seed:04d}"
    substeps = P.required_substeps(
        params, grid_density=opts.grid_density, fps=opts.fps, requested=opts.substeps
    )
    return _Plan(
        name, shapes, families, meshes, params, frame_c, effects, gravity, wind, layout, substeps
    )


class GenesisSource(SceneSource):
    """Generates one scene per ``generate`` call with the Genesis engine."""

    def __init__(self, options: GenesisOptions) -> None:
        self.options = options

    def generate(self, out_dir: Path) -> Path:
        out_dir = Path(out_dir)
        if out_dir.exists() and any(out_dir.iterdir()):
            raise ConfigError(f"output folder {str(out_dir)!r} is not empty; give a new one")
        opts = self.options
        gs = _genesis(opts.backend)
        rng = np.random.default_rng(opts.seed)
        plan = _plan(opts, rng)
        scene = _empty_scene(gs, opts, plan, rng)
        with tempfile.TemporaryDirectory() as tmp:
            entities = _add_objects(gs, scene, opts, plan, Path(tmp))
            _add_force_fields(gs, scene, plan.effects)
            gcams = _add_cameras(scene, opts, rng)
            scene.build()
        cameras = [_camera_record(c, f"cam_{i:02d}", opts.resolution) for i, c in enumerate(gcams)]
        starts, velocities = _aim(entities, opts, plan)
        writer = SceneWriter(
            out_dir, name=plan.name, fps=opts.fps, n_frames=opts.n_frames,
            observed_frames=opts.observed_frames,
            objects=[
                SceneObject(i, s, f) for i, (s, f) in enumerate(zip(plan.shapes, plan.families), 1)
            ],
            cameras=cameras, domain_lower=P.DOMAIN_LOWER, domain_upper=P.DOMAIN_UPPER,
            gravity=P.DECLARED_GRAVITY, ground_height=P.GROUND_HEIGHT,
        )  # fmt: skip
        points = _record(scene, entities, list(zip(cameras, gcams)), writer, opts, plan.name)
        writer.write_gt(
            points={i: np.stack(p) for i, p in points.items()},
            params=_gt_document(plan, starts, velocities, opts),
            effects=[e.to_json() for e in plan.effects] if plan.effects else None,
        )
        return writer.finish()


def _empty_scene(gs, opts: GenesisOptions, plan: _Plan, rng: np.random.Generator):
    """The Genesis scene with its MPM box (grown by ``MPM_BOUNDARY_CELLS``), the plan's
    substeps and gravity, a background colour drawn from ``rng``, and the table plane."""
    pad = MPM_BOUNDARY_CELLS / opts.grid_density  # m
    scene = gs.Scene(
        sim_options=gs.options.SimOptions(
            dt=1.0 / opts.fps, substeps=plan.substeps, gravity=tuple(plan.gravity)
        ),
        mpm_options=gs.options.MPMOptions(
            lower_bound=tuple(np.array(P.DOMAIN_LOWER) - pad),
            upper_bound=tuple(np.array(P.DOMAIN_UPPER) + pad),
            grid_density=opts.grid_density,
            particle_size=opts.particle_size,
        ),
        vis_options=gs.options.VisOptions(
            segmentation_level="entity",
            show_world_frame=False,
            background_color=P.BACKGROUNDS[int(rng.integers(len(P.BACKGROUNDS)))],
        ),
        show_viewer=False,
        renderer=gs.renderers.Rasterizer(),
    )
    scene.add_entity(gs.morphs.Plane(pos=(0.0, 0.0, P.GROUND_HEIGHT)))
    return scene


def _add_objects(gs, scene, opts: GenesisOptions, plan: _Plan, tmp: Path) -> list:
    """One MPM entity per object from its mesh (exported to ``tmp``, which must outlive
    ``scene.build``) at its planned start."""
    entities = []
    for i, (mesh, start) in enumerate(zip(plan.meshes, plan.layout.starts), start=1):
        path = tmp / f"object_{i}.obj"
        mesh.export(path)
        family = plan.families[i - 1]
        entities.append(
            scene.add_entity(
                material=_material(gs, family, plan.params[i - 1]),
                morph=gs.morphs.Mesh(file=str(path), scale=1.0, pos=tuple(start)),
                surface=gs.surfaces.Default(
                    color=P.COLORS[plan.shapes[i - 1]],
                    vis_mode=_vis_mode(opts.vis_mode, family),
                ),
            )
        )
    return entities


def _add_force_fields(gs, scene, effects) -> None:
    """Concealed wind, drag and the out-of-library fields as Genesis force fields (gravity acts
    through SimOptions); the fields' settings are those ``conceal_fields`` writes as the truth."""
    for e in effects:
        if e.kind == "wind":
            a = np.array(e.params["acceleration"])
            field = gs.force_fields.Constant(
                direction=tuple(a / max(np.linalg.norm(a), 1e-12)),
                strength=float(np.linalg.norm(a)),
            )
        elif e.kind in ("linear_drag", "quadratic_drag"):
            kw = "linear" if e.kind == "linear_drag" else "quadratic"
            field = gs.force_fields.Drag(**{kw: e.params["coefficient"]})
        elif e.kind == "vortex":  # Genesis' vortex turns about +z whatever its direction
            field = gs.force_fields.Vortex(
                direction=(0.0, 0.0, 1.0),
                center=tuple(float(x) for x in e.params["center"]),
                strength_perpendicular=float(e.params["strength"]),
                strength_radial=float(e.params["radial"]),
                falloff_pow=0.0,
                damping=0.0,
            )
        elif e.kind == "attractor":  # Point pushes away at positive strength
            field = gs.force_fields.Point(
                strength=-float(e.params["strength"]),
                position=tuple(float(x) for x in e.params["position"]),
                falloff_pow=0.0,
                flow=0.0,
            )
        else:
            continue
        scene.add_force_field(field)
        field.activate()


def _add_cameras(scene, opts: GenesisOptions, rng: np.random.Generator) -> list:
    """``n_cameras`` cameras on a hemisphere around the look-at point, the first azimuth drawn
    from ``rng``."""
    azimuth0 = float(rng.uniform(0.0, 2.0 * np.pi))
    target = np.asarray(P.LOOK_AT)
    return [
        scene.add_camera(
            res=(opts.resolution, opts.resolution),
            pos=tuple(target + P.CAMERA_DISTANCE * d),
            lookat=P.LOOK_AT,
            up=(0.0, 0.0, 1.0),
            fov=P.FOV_DEG,
            GUI=False,
        )
        for d in hemisphere_directions(opts.n_cameras, azimuth0=azimuth0)
    ]


def _aim(entities, opts: GenesisOptions, plan: _Plan):
    """Launch each object from where Genesis actually sampled its particles so that it reaches
    its planned target at the collision frame; returns (start centroids, velocities).

    Under gravity and wind (drag slows both bodies alike and is left out) the flight is
    ballistic; an out-of-library field bends it, and the launch is then shot through the whole
    true acceleration (``plan.shoot_velocity``)."""
    t_c = plan.frame_c / opts.fps
    starts = [_positions(e).mean(axis=0) for e in entities]
    if all(e.in_library for e in plan.effects):
        acceleration = plan.gravity + plan.wind
        velocities = [
            launch_velocity(s, t, t_c, acceleration) for s, t in zip(starts, plan.layout.targets)
        ]
    else:
        accel = true_acceleration(plan.effects, plan.gravity)
        velocities = [
            P.shoot_velocity(s, t, t_c, accel) for s, t in zip(starts, plan.layout.targets)
        ]
    for entity, v in zip(entities, velocities):
        entity.set_velocity(np.broadcast_to(v, (entity.n_particles, 3)).astype(np.float32))
    return starts, velocities


def true_acceleration(effects, gravity):
    """x'' = f(x, v, t) of a small free body in the recording: ``gravity`` (m/s^2, the true
    one) plus every concealed wind, drag and field."""
    wind = sum((np.array(e.params["acceleration"]) for e in effects if e.kind == "wind"), 0.0)
    lin = sum(e.params["coefficient"] for e in effects if e.kind == "linear_drag")
    quad = sum(e.params["coefficient"] for e in effects if e.kind == "quadratic_drag")
    fields = [e.to_json() for e in effects if not e.in_library]

    def f(x, v, t):
        a = np.asarray(gravity, dtype=np.float64) + wind - lin * v - quad * np.linalg.norm(v) * v
        for field in fields:
            a = a + field_acceleration(field, x, v, t)
        return a

    return f


def _record(scene, entities, cameras, writer, opts: GenesisOptions, name: str) -> dict:
    """Step one frame at a time, writing every (camera, Genesis camera) pair's RGB and mask;
    returns object id -> per-frame particle positions."""
    points: dict[int, list[np.ndarray]] = {i: [] for i in range(1, opts.n_objects + 1)}
    for t in range(opts.n_frames):
        if t > 0:
            scene.step()
        for i, entity in enumerate(entities, start=1):
            points[i].append(_positions(entity))
        lut = _mask_lut(scene, entities)
        for cam, gcam in cameras:
            rgb, _, seg, _ = gcam.render(rgb=True, segmentation=True)
            mask = lut[np.clip(np.asarray(seg, dtype=np.int64), 0, len(lut) - 1)]
            writer.write_frame(cam.id, t, rgb=np.asarray(rgb, dtype=np.uint8), mask=mask)
        if opts.progress:
            print(f"genesis {name}: frame {t + 1}/{opts.n_frames}", flush=True)
    return points


def _positions(entity) -> np.ndarray:
    """[N, 3] float32 particle positions (m) of one MPM entity now."""
    pos = entity.get_particles_pos()
    pos = pos.detach().cpu().numpy() if hasattr(pos, "detach") else np.asarray(pos)
    return pos.reshape(-1, 3).astype(np.float32)


def _mask_lut(scene, entities) -> np.ndarray:
    """Segmentation index -> object id (0 for background, table and anything else)."""
    idx_to_key = scene.segmentation_idx_dict
    ids = {e.idx: i for i, e in enumerate(entities, start=1)}
    lut = np.zeros(max(idx_to_key) + 1, dtype=np.uint8)
    for seg_idx, key in idx_to_key.items():
        lut[seg_idx] = ids.get(key, 0)
    return lut


def _gt_document(plan: _Plan, starts, velocities, opts: GenesisOptions) -> dict:
    """gt/params.json: scene-format parameters per object, Genesis' own under
    ``generator_params``; the grid, substeps, contact mode and ranges the engine ran with."""
    try:
        version = metadata.version("genesis-world")
    except metadata.PackageNotFoundError:
        version = "unknown"
    shapes, families, params = plan.shapes, plan.families, plan.params
    dt = 1.0 / (opts.fps * plan.substeps)
    return {
        "generator": f"mosiv-genesis (Genesis {version}, MPM, {opts.backend})",
        "generator_params": {
            "substeps": plan.substeps,
            "substeps_requested": opts.substeps,
            "cfl": P.cfl_number(params, grid_density=opts.grid_density, dt=dt),
            "grid_density": opts.grid_density,
            "grid_cell_m": 1.0 / opts.grid_density,
            "contact": CONTACT_MODE,
            "particle_size": opts.particle_size,
            "collision_frame": plan.frame_c,
            "collision_point": plan.layout.collision_point.tolist(),
            "seed": opts.seed,
        },
        "ranges": opts.ranges,
        "range_table": P.range_table(opts.ranges),
        "objects": [
            {
                "id": i,
                "name": shapes[i - 1],
                "material": fam,
                "params": P.scene_format_params(fam, p, substep_dt=dt),
                "generator_params": dict(p),
                "initial_velocity": [float(x) for x in velocities[i - 1]],
                "initial_centroid": [float(x) for x in starts[i - 1]],
            }
            for i, (fam, p) in enumerate(zip(families, params), start=1)
        ],
    }
