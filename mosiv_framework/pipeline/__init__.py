"""``mosiv run``: scene -> reconstruct -> lift -> identify -> evaluate, each stage resumable.

Every stage's result is saved in the run folder with a fingerprint of the recipe sections it
depends on; a rerun skips stages whose fingerprint matches and recomputes the rest.
"""

from __future__ import annotations

import resource
import time
from dataclasses import replace
from pathlib import Path

import torch
from omegaconf import DictConfig, OmegaConf

from mosiv_framework.errors import ConfigError, SimulationDiverged
from mosiv_framework.losses import WeightedSum
from mosiv_framework.pipeline.appearance import can_render, rollout_images
from mosiv_framework.pipeline.evaluate import (
    parameter_errors,
    plot_centroids,
    plot_history,
    plot_parameters,
    score,
)
from mosiv_framework.pipeline.identify import identify
from mosiv_framework.pipeline.library import library_params, pick_prototypes
from mosiv_framework.pipeline.params import (
    GROUND_FRICTION,
    ParameterVector,
    free_flight_frames,
    initial_velocity_from_points,
    stiffness_ceilings,
)
from mosiv_framework.pipeline.rundir import RunDir, fingerprint
from mosiv_framework.pipeline.silhouettes import SILHOUETTE_LOSSES, SilhouetteObjective
from mosiv_framework.pipeline.video import pick_camera, save_rollout_npz, write_comparison_video
from mosiv_framework.recipes.terms import identified_terms, term_tensors
from mosiv_framework.registry import get_registry
from mosiv_framework.scene import read_scene


def _say(message: str) -> None:
    print(f"[mosiv] {message}", flush=True)


def _component(section) -> tuple[str, dict]:
    options = dict(section)
    return options.pop("name"), options


def ensure_scene(scene_section, run_dir: RunDir):
    """Read the scene, generating it first with ``scene.source`` when the folder is missing."""
    path = Path(scene_section.path)
    if not (path / "scene.json").is_file():
        if scene_section.source is None:
            raise ConfigError(
                f"scene.path {str(path)!r} holds no scene.json and the recipe names no "
                f"scene.source to generate one"
            )
        name, options = _component(scene_section.source)
        _say(f"generating scene with {name!r} into {path}")
        get_registry().create("scene_source", name, options).generate(path)
    return read_scene(path)


def run_pipeline(recipe: DictConfig, *, run_dir: Path) -> dict:
    """Run every stage of ``recipe`` into ``run_dir``; returns the metrics."""
    t_start = time.perf_counter()
    rd = RunDir(run_dir)
    plain = OmegaConf.to_container(recipe, resolve=True)
    rd.write_bytes("recipe.yaml", OmegaConf.to_yaml(recipe).encode())
    registry = get_registry()
    scene = ensure_scene(recipe.scene, rd)
    _say(
        f"scene {scene.name!r}: {len(scene.objects)} objects, {len(scene.cameras)} cameras, "
        f"{scene.n_frames} frames ({scene.observed_frames} observed)"
    )

    # Stage I: reconstruction
    key = fingerprint(plain["scene"]["path"], plain["reconstructor"])
    if rd.stage_done("reconstruct", key):
        reconstruction = rd.load_torch("reconstruction.pt")
    else:
        name, options = _component(recipe.reconstructor)
        _say(f"reconstructing with {name!r}")
        reconstruction = registry.create("reconstructor", name, options).fit(scene, run_dir=rd.root)
        rd.save_torch("reconstruction.pt", reconstruction)
        rd.mark_done("reconstruct", key)

    # Stage II: lifting
    key = fingerprint(key, plain["lifter"])
    if rd.stage_done("lift", key):
        particles = rd.load_torch("particles.pt")
    else:
        name, options = _component(recipe.lifter)
        _say(f"lifting with {name!r}")
        particles = registry.create("lifter", name, options).lift(reconstruction, scene)
        rd.save_torch("particles.pt", particles)
        rd.mark_done("lift", key, particles=len(particles))

    # Stage III: identification
    sim_name, sim_options = _component(recipe.simulator)
    simulator = registry.create("simulator", sim_name, sim_options)
    if simulator.deterministic and torch.device(simulator.torch_device).type == "cuda":
        # the losses' gathers scatter their gradients on the GPU too: in a fixed order now,
        # so an identification repeats bit for bit (cuBLAS products already do)
        torch.use_deterministic_algorithms(True, warn_only=True)
    check_terms_supported(plain.get("physics_terms") or {}, simulator, sim_name)
    key = fingerprint(key, plain["simulator"], plain["losses"], plain["identify"])
    if plain.get("physics_terms"):  # only then, so runs made without terms keep their key
        key = fingerprint(key, plain["physics_terms"])
    if rd.stage_done("identify", key):
        identified = ParameterVector.from_json(rd.load_json("identified.json"))
    else:
        identified = identify_stage(
            recipe, scene, particles, reconstruction, simulator, sim_options, rd, key
        )
        rd.mark_done("identify", key)

    # Evaluation (a resumed run, such as a suite entry run again after its diagnosis was cut
    # short, keeps its metrics, plots and videos rather than rolling out again)
    key = fingerprint(key, plain["evaluate"])
    if rd.stage_done("evaluate", key) and rd.path("metrics.json").is_file():
        metrics = rd.load_json("metrics.json")
    else:
        _say("evaluating over observed and future frames")
        metrics = evaluate_run(
            recipe=recipe,
            scene=scene,
            particles=particles,
            reconstruction=reconstruction,
            identified=identified,
            simulator=simulator,
            run_dir=rd,
            started=t_start,
            refine=simulator_refiner(recipe.simulator),
        )
        rd.mark_done("evaluate", key)
    _say(
        f"done: observed cd {metrics['observed']['cd_mm2']:.3g} mm^2"
        + (f", future cd {metrics['future']['cd_mm2']:.3g} mm^2" if metrics["future"] else "")
        + f"; results in {rd.root}"
    )
    return metrics


def check_terms_supported(section: dict, simulator, sim_name: str) -> None:
    """Raise ConfigError if the recipe switches on a physics term the simulator lacks."""
    supported = set(getattr(simulator, "supported_terms", frozenset()))
    missing = sorted(set(section) - supported)
    if missing:
        raise ConfigError(
            f"physics_terms {missing}: simulator {sim_name!r} does not implement them; it "
            f"implements {sorted(supported) or 'no physics terms'}"
        )


def build_objective(losses: dict, registry) -> WeightedSum:
    """The recipe's weighted loss terms (terms of weight 0 are left out)."""
    terms = {
        name: registry.create("loss", name, options)
        for name, options in losses.items()
        if float(options.get("weight", 1.0)) > 0
    }
    if not terms:
        raise ConfigError(f"every loss weight in losses={losses} is 0; nothing to minimise")
    return WeightedSum(terms)


def identify_stage(recipe, scene, particles, reconstruction, simulator, sim_options, rd, key):
    """Velocities, then parameters (gradient) or prototypes (library); writes identified.json,
    identify/history.json and the identification plots. Returns detached SimulationParams."""
    section = recipe.identify
    world = scene.world
    plain = OmegaConf.to_container(recipe, resolve=True)
    objective = build_objective(plain["losses"], get_registry())
    if any(name in SILHOUETTE_LOSSES for name in objective.terms):
        # the recorded masks are area-averaged down to the comparison size
        size = min(section.silhouette_size, max(max(c.width, c.height) for c in scene.cameras))
        objective = SilhouetteObjective(objective, scene=scene, particles=particles, size=size)
    targets = reconstruction.points
    # roll out where the simulator computes, so trajectories and every loss stay on its
    # device (on a GPU the losses on CPU copies took three quarters of an iteration)
    sim_particles = particles.to(simulator.torch_device)
    physics_terms = plain.get("physics_terms") or {}
    vector, free = start_vector(recipe, scene, particles.materials, targets, sim_options)
    if physics_terms:
        _say(
            "physics terms on: "
            + ", ".join(
                f"{n} ({'identified' if n in identified_terms(physics_terms) else 'fixed'})"
                for n in physics_terms
            )
        )
    velocity_frames = min(free, scene.observed_frames)
    _say(
        f"{free} free-flight frame(s) before contact: initial velocities from their centroids"
        + ("" if section.velocity_window == "free" else "; velocity phase fits every frame")
    )
    library = section.method == "library"
    _say(
        f"identifying {len(vector.velocity)} initial velocities and "
        + (
            "a prototype per object (library baseline)"
            if library
            else f"{len(vector.normalized)} parameters"
        )
        + f" with {recipe.simulator.name!r}"
    )
    vector, history = identify(
        simulator=simulator,
        particles=sim_particles,
        world=world,
        targets=targets,
        observed_frames=scene.observed_frames,
        objective=objective,
        vector=vector,
        section=_velocity_only(section) if library else section,
        run_dir=rd,
        config_hash=key,
        velocity_frames=velocity_frames if section.velocity_window == "free" else None,
    )
    identified_json = vector.to_json()
    stopped = [
        {"phase": h["phase"], "iteration": h["iteration"], "reason": h["stopped_early"]}
        for h in history
        if "stopped_early" in h
    ]
    if stopped:  # the run goes on from the best iterate, but says the fit was cut short
        identified_json["stopped_early"] = stopped
        for s in stopped:
            _say(f"identification {s['phase']} phase stopped early at iteration {s['iteration']}")
    if library:
        choice, tried = pick_prototypes(
            simulator=simulator,
            particles=sim_particles,
            world=world,
            targets=targets,
            observed_frames=scene.observed_frames,
            objective=objective,
            velocities=vector.velocity,
            ground_friction=float(vector.physical().ground_friction),
            terms=vector.physical().terms,
            scope=section.library_scope,
            sweeps=section.library_sweeps,
        )
        params = library_params(
            choice,
            vector.velocity,
            ground_friction=identified_json["ground_friction"],
            terms=vector.physical().terms,
        )
        for k, proto in choice.items():
            entry = identified_json["objects"][str(k)]
            entry["family"] = proto.family
            entry["params"] = {n: float(v) for n, v in sorted(params.objects[k].values.items())}
        identified_json["library"] = {str(k): p.name for k, p in choice.items()}
        rd.save_json("identify/library.json", tried)
        _say("library choice: " + ", ".join(f"object {k}: {p.name}" for k, p in choice.items()))
    rd.save_json("identify/history.json", history)
    rd.save_json("identified.json", identified_json)
    plot_history(history, rd.path("identify/loss.png"))
    plot_parameters(history, rd.path("identify/parameters.png"))
    return ParameterVector.from_json(identified_json)


def start_vector(
    recipe, scene, families: dict[int, str], targets: dict[int, torch.Tensor], sim_options: dict
) -> tuple[ParameterVector, int]:
    """Where identification starts: initial velocities from a ballistic fit of the targets'
    centroids over the frames before any contact, every law parameter at its default (capped by
    ``identify.stiffness_cfl``), the recipe's physics terms on. Returns the vector and the
    number of leading free-flight frames. ``mosiv diagnose`` re-identifies from here too."""
    section = recipe.identify
    world = scene.world
    grid, substeps = sim_options.get("grid"), sim_options.get("substeps")
    dx = world.extent / grid if isinstance(grid, int) and grid > 0 else None
    gap = section.contact_gap or (2.0 * dx if dx else 0.02)
    free = free_flight_frames(targets, world, gap=gap)
    # the simulator's step, where its options name one (substeps per frame)
    step = 1.0 / (scene.fps * substeps) if isinstance(substeps, int) and substeps > 0 else 0.0
    v0 = initial_velocity_from_points(
        targets, fps=scene.fps, gravity=scene.gravity, frames=free, time_step=step
    )
    ceilings = None
    if section.stiffness_cfl > 0 and dx and isinstance(substeps, int) and substeps > 0:
        ceilings = stiffness_ceilings(
            families,
            {},
            dx=dx,
            dt=1.0 / (scene.fps * substeps),
            cfl=section.stiffness_cfl,
        )
    plain = OmegaConf.to_container(recipe, resolve=True)
    physics_terms = plain.get("physics_terms") or {}
    vector = ParameterVector.create(
        families,
        v0,
        ground_friction=None if world.ground_height is None else GROUND_FRICTION.default,
        identify_friction=section.identify_friction,
        identify_ground_friction=section.identify_ground_friction,
        ceilings=ceilings,
        terms=term_tensors(physics_terms),
        identify_terms=identified_terms(physics_terms),
    )
    return vector, free


def _velocity_only(section):
    """The identify section with the parameter phase switched off (library baseline)."""
    copy = OmegaConf.create(OmegaConf.to_container(section, resolve=True))
    copy.param_iterations = 0
    return copy


#: how many times evaluation may double the simulator's substeps after a divergence
EVALUATION_REFINEMENTS = 2


def simulator_refiner(section):
    """A function ``factor -> (substeps, simulator)`` building the recipe's simulator with
    ``factor`` times its substeps; None when its options name no integer ``substeps``."""
    name, options = _component(section)
    base = options.get("substeps")
    if not isinstance(base, int) or isinstance(base, bool):
        return None

    def refined(factor: int):
        substeps = base * factor
        return substeps, get_registry().create("simulator", name, {**options, "substeps": substeps})

    return refined


def _evaluation_rollout(simulator, particles, identified, *, world, frames, refine):
    """The identified model rolled over ``frames``; returns (trajectory, simulator, note).

    Identification only ever rolled the observed window. A model that diverges after it (a
    fluid hitting the table faster than the recipe's substeps resolve, session 11's E-F) is
    a time-step problem, not a wrong model, so the rollout is retried with 2x, then 4x the
    substeps, and the note in metrics.json says so; the run is not lost."""
    factor, note = 1, None
    while True:
        try:
            with torch.no_grad():
                traj = simulator.rollout(particles, identified, world=world, frames=frames)
            return traj, simulator, note
        except SimulationDiverged as exc:
            if refine is None or factor >= 2**EVALUATION_REFINEMENTS:
                raise
            factor *= 2
            substeps, simulator = refine(factor)
            note = (
                f"the rollout diverged in object {exc.object_id} at frame {exc.frame}, substep "
                f"{exc.substep} ({exc.reason}); evaluated with {substeps} substeps per frame"
            )
            _say(f"evaluation rollout diverged ({exc.reason}); retrying with {substeps} substeps")


def evaluate_run(
    *,
    recipe,
    scene,
    particles,
    reconstruction,
    identified,
    simulator,
    run_dir,
    started=None,
    refine=None,
) -> dict:
    """Roll ``identified`` over every frame, score it, write metrics.json, plots and videos.

    ``refine`` (see ``simulator_refiner``) lets a diverging rollout retry with more substeps.
    """
    t_start = time.perf_counter() if started is None else started
    rd = run_dir
    world = scene.world
    # the identified families may differ from the lifted ones (library baseline, scope "all")
    particles = replace(particles, materials={k: p.family for k, p in identified.objects.items()})
    traj, simulator, note = _evaluation_rollout(
        simulator, particles, identified, world=world, frames=scene.n_frames - 1, refine=refine
    )
    reference = scene.gt_points() if scene.has_gt else reconstruction.points
    # PSNR/SSIM need images of the prediction: only particles with bound Gaussians (the
    # gaussians lifter) can be rendered against the recorded videos
    images = rollout_images(traj, particles, scene) if can_render(particles) else None
    blocks = score(
        traj,
        reference,
        observed_frames=scene.observed_frames,
        n_samples=recipe.evaluate.emd_samples,
        seed=recipe.evaluate.seed,
        images=images,
    )
    metrics = {
        "observed": blocks["observed"],
        "future": blocks["future"],
        "reference": "gt/points.npz" if scene.has_gt else "reconstruction",
        "params": rd.load_json("identified.json"),
        "param_error": parameter_errors(identified, scene.gt_params()) if scene.has_gt else None,
        "time_s": time.perf_counter() - t_start,
        "peak_memory_gb": _peak_memory_gb(simulator),
    }
    if note is not None:
        metrics["evaluation_note"] = note
    rd.save_json("metrics.json", metrics)
    plot_centroids(
        traj,
        reference,
        fps=scene.fps,
        observed_frames=scene.observed_frames,
        path=rd.path("trajectories.png"),
    )
    rd.save_torch(
        "rollout.pt",
        {"positions": traj.positions.detach().cpu(), "object_ids": traj.object_ids.cpu()},
    )
    save_rollout_npz(traj, rd.path("rollout.npz"))
    if recipe.evaluate.render_videos:
        write_comparison_video(
            traj,
            reference,
            camera=pick_camera(scene, recipe.evaluate.video_camera),
            path=rd.path("videos/prediction_vs_reference.gif"),
            size=recipe.evaluate.video_size,
            fps=recipe.evaluate.video_fps or scene.fps,
            observed_frames=scene.observed_frames,
        )
    return metrics


def _peak_memory_gb(simulator=None) -> float:
    """Peak GPU memory if CUDA was used, else the process's peak resident memory (GiB).

    On CUDA the simulator's own count is included: a backend with its own allocator (Warp's
    pool, Taichi's fields) holds memory that torch's peak does not see."""
    if torch.cuda.is_available() and torch.cuda.max_memory_allocated() > 0:
        backend = simulator.peak_memory_bytes() if simulator is not None else None
        return max(torch.cuda.max_memory_allocated(), backend or 0) / 2**30
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20  # ru_maxrss is KiB on Linux
