"""``mosiv run``: scene -> reconstruct -> lift -> identify -> evaluate, each stage resumable.

Every stage's result is saved in the run folder with a fingerprint of the recipe sections it
depends on; a rerun skips stages whose fingerprint matches and recomputes the rest.
"""

from __future__ import annotations

import resource
import time
from pathlib import Path

import torch
from omegaconf import DictConfig, OmegaConf

from mosiv_framework.errors import ConfigError, StageNotAvailable
from mosiv_framework.losses import WeightedSum
from mosiv_framework.pipeline.evaluate import parameter_errors, plot_centroids, plot_history, score
from mosiv_framework.pipeline.identify import identify
from mosiv_framework.pipeline.params import ParameterVector, initial_velocity_from_points
from mosiv_framework.pipeline.rundir import RunDir, fingerprint
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
    world = scene.world
    key = fingerprint(key, plain["simulator"], plain["losses"], plain["identify"])
    if rd.stage_done("identify", key):
        identified = ParameterVector.from_json(rd.load_json("identified.json"))
        history = rd.load_json("identify/history.json")
    else:
        terms = {}
        for loss_name, options in plain["losses"].items():
            if loss_name in ("silhouette", "scene-silhouette") and options.get("weight", 1.0) > 0:
                raise StageNotAvailable(
                    f"losses.{loss_name} needs silhouettes of simulated states, which need particles "
                    f"carrying appearance (the Gaussian lifter, mosiv-lift); set "
                    f"losses.{loss_name}.weight=0 or use a lifter that binds Gaussians"
                )
            terms[loss_name] = registry.create("loss", loss_name, options)
        objective = WeightedSum(terms)
        v0 = initial_velocity_from_points(
            reconstruction.points, fps=scene.fps, gravity=scene.gravity
        )
        vector = ParameterVector.create(
            particles.materials,
            v0,
            ground_friction=None if world.ground_height is None else 0.3,
            identify_friction=recipe.identify.identify_friction,
            identify_ground_friction=recipe.identify.identify_ground_friction,
        )
        _say(
            f"identifying {len(vector.normalized)} parameters and {len(v0)} initial velocities "
            f"with {sim_name!r}"
        )
        vector, history = identify(
            simulator=simulator,
            particles=particles,
            world=world,
            targets=reconstruction.points,
            observed_frames=scene.observed_frames,
            objective=objective,
            vector=vector,
            section=recipe.identify,
            run_dir=rd,
            config_hash=key,
        )
        rd.save_json("identify/history.json", history)
        rd.save_json("identified.json", vector.to_json())
        plot_history(history, rd.path("identify/loss.png"))
        identified = vector.physical()
        rd.mark_done("identify", key)
        identified = identified.detached()

    # Evaluation
    _say("evaluating over observed and future frames")
    with torch.no_grad():
        traj = simulator.rollout(particles, identified, world=world, frames=scene.n_frames - 1)
    reference = scene.gt_points() if scene.has_gt else reconstruction.points
    blocks = score(
        traj,
        reference,
        observed_frames=scene.observed_frames,
        n_samples=recipe.evaluate.emd_samples,
        seed=recipe.evaluate.seed,
    )
    metrics = {
        "observed": blocks["observed"],
        "future": blocks["future"],
        "reference": "gt/points.npz" if scene.has_gt else "reconstruction",
        "params": rd.load_json("identified.json"),
        "param_error": parameter_errors(identified, scene.gt_params()) if scene.has_gt else None,
        "time_s": time.perf_counter() - t_start,
        "peak_memory_gb": _peak_memory_gb(),
    }
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
    _say(
        f"done: observed cd {metrics['observed']['cd_mm2']:.3g} mm^2"
        + (f", future cd {metrics['future']['cd_mm2']:.3g} mm^2" if metrics["future"] else "")
        + f"; results in {rd.root}"
    )
    return metrics


def _peak_memory_gb() -> float:
    """Peak GPU memory if CUDA was used, else the process's peak resident memory."""
    if torch.cuda.is_available() and torch.cuda.max_memory_allocated() > 0:
        return torch.cuda.max_memory_allocated() / 2**30
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20  # ru_maxrss is KiB on Linux
