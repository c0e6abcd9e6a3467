"""The identification stage around ``identify``: the objective and the starting vector from the
recipe, the library baseline's prototype choice, and what the stage writes (identified.json,
identify/history.json, identify/library.json and the identification plots)."""

from __future__ import annotations

import logging

import torch
from omegaconf import OmegaConf

from mosiv_framework.errors import ConfigError
from mosiv_framework.losses import WeightedSum
from mosiv_framework.pipeline import formats
from mosiv_framework.pipeline.contact import (
    contact_json,
    contact_modes,
    law_sets,
    recorded_close_call,
)
from mosiv_framework.pipeline.evaluate import plot_history, plot_parameters
from mosiv_framework.pipeline.identify import identify
from mosiv_framework.pipeline.landing import landing_friction
from mosiv_framework.pipeline.library import library_params, pick_prototypes
from mosiv_framework.pipeline.params import (
    GROUND_FRICTION,
    ParameterVector,
    free_flight_frames,
    initial_velocity_from_points,
    stiffness_ceilings,
    wave_speed_limit,
)
from mosiv_framework.pipeline.silhouettes import SILHOUETTE_LOSSES, SilhouetteObjective
from mosiv_framework.pipeline.uncertainty import attach_intervals
from mosiv_framework.recipes.terms import identified_terms, term_tensors
from mosiv_framework.registry import get_registry

log = logging.getLogger(__name__)


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


def stage_objective(recipe, scene, particles):
    """The recipe's objective; with a silhouette loss, wrapped to render the particles against
    the recorded masks, area-averaged down to ``identify.silhouette_size``."""
    losses = OmegaConf.to_container(recipe, resolve=True)["losses"]
    objective = build_objective(losses, get_registry())
    if any(name in SILHOUETTE_LOSSES for name in objective.terms):
        largest = max(max(c.width, c.height) for c in scene.cameras)
        size = min(recipe.identify.silhouette_size, largest)
        objective = SilhouetteObjective(objective, scene=scene, particles=particles, size=size)
    return objective


def identify_stage(
    recipe, scene, particles, reconstruction, simulator, sim_options, rd, key, *, warnings=()
):
    """Velocities, then parameters (gradient) or prototypes (library); writes identified.json,
    identify/history.json and the identification plots. Returns detached SimulationParams.

    ``warnings``: what the recipe's settings cap (``check_stiffness``), stored under
    ``warnings`` in identified.json so the results say how they were limited, with a contact
    choice that was a close call (``contact.recorded_close_call``). identified.json's
    ``contact`` says which contact between objects the parameters were identified with (chosen
    from the data with ``identify.contact: auto``, see ``mosiv_framework.pipeline.contact``)."""
    section = recipe.identify
    objective = stage_objective(recipe, scene, particles)
    targets = reconstruction.points
    # roll out where the simulator computes, so trajectories and every loss stay on its
    # device (on a GPU the losses on CPU copies took three quarters of an iteration)
    sim_particles = particles.to(simulator.torch_device)
    vector, free = start_vector(recipe, scene, particles.materials, targets, sim_options)
    library = section.method == "library"
    _announce(recipe, vector, free, library)
    modes = None
    if section.contact == "auto" or section.law_choice == "auto":
        sets = None
        if section.law_choice == "auto":
            sets = law_sets(scene.materials, section.laws, section.law_alternatives)
        modes = contact_modes(
            recipe.simulator,
            simulator,
            margin=section.contact_margin,
            tie_iterations=section.contact_tie_iterations,
            every_mode=section.contact == "auto",
            law_sets=sets,
        )
    vector, history = identify(
        simulator=simulator,
        particles=sim_particles,
        world=scene.world,
        targets=targets,
        observed_frames=scene.observed_frames,
        objective=objective,
        vector=vector,
        section=_velocity_only(section) if library else section,
        run_dir=rd,
        config_hash=key,
        velocity_frames=min(free, scene.observed_frames)
        if section.velocity_window == "free"
        else None,
        contact=modes,
    )
    identified_json = vector.to_json()
    contact = contact_json(history, recipe.simulator)
    if contact is not None:
        identified_json["contact"] = contact
        if modes is not None:  # the library baseline picks with the chosen contact too
            simulator = modes.simulators[contact["mode"]]
    warnings = list(warnings)
    close = recorded_close_call(modes, contact) if modes is not None and contact else None
    warnings += [close] if close else []
    if warnings:
        identified_json["warnings"] = warnings
    _note_stopped_early(history, identified_json)
    attach_intervals(history, identified_json)
    if library:
        fit = dict(simulator=simulator, particles=sim_particles, objective=objective)
        _choose_prototypes(section, scene, targets, vector, identified_json, rd, **fit)
    rd.save_json("identify/history.json", formats.stamped_entries(formats.HISTORY, history))
    rd.save_json("identified.json", formats.stamped(formats.IDENTIFIED, identified_json))
    plot_history(history, rd.path("identify/loss.png"))
    plot_parameters(history, rd.path("identify/parameters.png"))
    return ParameterVector.from_json(identified_json)


def _announce(recipe, vector: ParameterVector, free: int, library: bool) -> None:
    """Say what identification is about to fit."""
    physics_terms = OmegaConf.to_container(recipe, resolve=True).get("physics_terms") or {}
    if physics_terms:
        identified = identified_terms(physics_terms)
        log.info(
            "physics terms on: %s",
            ", ".join(
                f"{n} ({'identified' if n in identified else 'fixed'})" for n in physics_terms
            ),
        )
    log.info(
        "%d free-flight frame(s) before contact: initial velocities from their centroids%s",
        free,
        "" if recipe.identify.velocity_window == "free" else "; velocity phase fits every frame",
    )
    what = (
        "a prototype per object (library baseline)"
        if library
        else f"{len(vector.normalized)} parameters"
    )
    log.info(
        "identifying %d initial velocities and %s with %r",
        len(vector.velocity),
        what,
        recipe.simulator.name,
    )


def _note_stopped_early(history: list[dict], identified_json: dict) -> None:
    """Record the phases cut short in identified.json: the run goes on from the best iterate,
    but says the fit was cut short."""
    stopped = [
        {"phase": h["phase"], "iteration": h["iteration"], "reason": h["stopped_early"]}
        for h in history
        if "stopped_early" in h
    ]
    if stopped:
        identified_json["stopped_early"] = stopped
        for s in stopped:
            log.info(
                "identification %s phase stopped early at iteration %d", s["phase"], s["iteration"]
            )


def _choose_prototypes(
    section, scene, targets, vector, identified_json, rd, *, simulator, particles, objective
) -> None:
    """The library baseline: each object's prototype, chosen with the identified velocities
    held, written into ``identified_json``; the combinations tried go to
    identify/library.json."""
    physical = vector.physical()
    choice, tried = pick_prototypes(
        simulator=simulator,
        particles=particles,
        world=scene.world,
        targets=targets,
        observed_frames=scene.observed_frames,
        objective=objective,
        velocities=vector.velocity,
        ground_friction=float(physical.ground_friction.detach()),
        terms=physical.terms,
        scope=section.library_scope,
        sweeps=section.library_sweeps,
    )
    params = library_params(
        choice,
        vector.velocity,
        ground_friction=identified_json["ground_friction"],
        terms=physical.terms,
    )
    for k, proto in choice.items():
        entry = identified_json["objects"][str(k)]
        entry["family"] = proto.family
        entry["params"] = {n: float(v) for n, v in sorted(params.objects[k].values.items())}
    identified_json["library"] = {str(k): p.name for k, p in choice.items()}
    rd.save_json("identify/library.json", formats.stamped_entries(formats.LIBRARY, tried))
    log.info("library choice: %s", ", ".join(f"object {k}: {p.name}" for k, p in choice.items()))


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
    tolerance = float(getattr(section, "ballistic_tolerance", 0.0))
    free = free_flight_frames(targets, world, gap=gap, ballistic_tolerance=tolerance)
    # the simulator's step, where its options name one (substeps per frame)
    step = 1.0 / (scene.fps * substeps) if isinstance(substeps, int) and substeps > 0 else 0.0
    v0 = initial_velocity_from_points(
        targets, fps=scene.fps, gravity=scene.gravity, frames=free, time_step=step
    )
    ceilings = recipe_ceilings(recipe, scene, families, sim_options)
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
        wave_speed_limit=recipe_wave_speed(recipe, scene, sim_options),
    )
    if getattr(section, "start", "defaults") == "centre":
        vector.move_to_centre()  # a data-independent start (identify.start)
    if getattr(section, "ground_friction_start", "start") == "landing":
        # only the frames the parameter phase fits: neither the future nor a held-out tail
        frames = scene.observed_frames - int(getattr(section, "holdout_frames", 0) or 0)
        start_ground_at_landings(vector, targets, world, frames)
    return vector, free


def start_ground_at_landings(vector, targets: dict[int, torch.Tensor], world, frames: int) -> None:
    """The ground's coefficient set to the one the landings within the first ``frames`` target
    frames show (``landing.landing_friction``); where none can be read, to the coefficient's
    default (GROUND_FRICTION.default) rather than the centre of its bounds."""
    frames = min([frames, *(t.shape[0] for t in targets.values())])
    value, found = landing_friction(targets, world, frames)
    if value is None:
        value = GROUND_FRICTION.default
        log.info("no landing to read the ground friction from; it starts at %.3g", value)
    else:
        readings = ", ".join(f"object {x.object_id} frame {x.frame}: {x.ratio:.3g}" for x in found)
        log.info("the ground friction starts at %.3g, read off the landings (%s)", value, readings)
    vector.set_ground_friction(value)


def recipe_ceilings(recipe, scene, families: dict[int, str], sim_options: dict) -> dict | None:
    """The stiffness ceilings identification puts on each object's parameters under the
    recipe's grid, substeps and ``identify.stiffness_cfl`` (``params.stiffness_ceilings``);
    None where the recipe sets none."""
    grid, substeps = sim_options.get("grid"), sim_options.get("substeps")
    dx = scene.world.extent / grid if isinstance(grid, int) and grid > 0 else None
    cfl = recipe.identify.stiffness_cfl
    if not (cfl > 0 and dx and isinstance(substeps, int) and substeps > 0):
        return None
    return stiffness_ceilings(families, {}, dx=dx, dt=1.0 / (scene.fps * substeps), cfl=cfl)


def recipe_wave_speed(recipe, scene, sim_options: dict) -> float | None:
    """The P-wave speed limit (m/s) behind ``recipe_ceilings``: ``identify.stiffness_cfl``
    cells of the recipe's grid per substep; None where the recipe sets no ceiling."""
    return wave_speed_limit(
        recipe.identify.stiffness_cfl,
        scene.world,
        sim_options.get("grid"),
        sim_options.get("substeps"),
    )


def _velocity_only(section):
    """The identify section with the parameter phase switched off (library baseline)."""
    copy = OmegaConf.create(OmegaConf.to_container(section, resolve=True))
    copy.param_iterations = 0
    return copy
