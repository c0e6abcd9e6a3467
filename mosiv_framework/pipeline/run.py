"""``mosiv run``: scene -> reconstruct -> lift -> identify -> evaluate, each stage resumable.

Every stage's result is saved in the run folder with a fingerprint of the recipe sections it
depends on (and of the stages before it); a rerun skips stages whose fingerprint matches and
recomputes the rest.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import torch
from omegaconf import DictConfig, OmegaConf

from mosiv_framework.errors import ConfigError
from mosiv_framework.pipeline.evaluate import evaluate_run
from mosiv_framework.pipeline.formats import recipe_header
from mosiv_framework.pipeline.identification import check_terms_supported, identify_stage
from mosiv_framework.pipeline.params import ParameterVector
from mosiv_framework.pipeline.rundir import RunDir, fingerprint
from mosiv_framework.registry import get_registry
from mosiv_framework.scene import read_scene

log = logging.getLogger(__name__)


def component(section) -> tuple[str, dict]:
    """A recipe component section as (name, the options its factory takes)."""
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
        name, options = component(scene_section.source)
        log.info("generating scene with %r into %s", name, path)
        get_registry().create("scene_source", name, options).generate(path)
    return read_scene(path)


def run_pipeline(recipe: DictConfig, *, run_dir: Path) -> dict:
    """Run every stage of ``recipe`` into ``run_dir``; returns the metrics."""
    t_start = time.perf_counter()
    rd = RunDir(run_dir)
    plain = OmegaConf.to_container(recipe, resolve=True)
    rd.write_bytes("recipe.yaml", recipe_header() + OmegaConf.to_yaml(recipe).encode())
    scene = ensure_scene(recipe.scene, rd)
    log.info(
        "scene %r: %d objects, %d cameras, %d frames (%d observed)",
        scene.name,
        len(scene.objects),
        len(scene.cameras),
        scene.n_frames,
        scene.observed_frames,
    )
    key = fingerprint(plain["scene"]["path"], plain["reconstructor"])
    reconstruction = reconstruct_stage(recipe, scene, rd, key)
    key = fingerprint(key, plain["lifter"])
    particles = lift_stage(recipe, scene, reconstruction, rd, key)

    simulator, sim_options = build_simulator(recipe.simulator)
    check_terms_supported(plain.get("physics_terms") or {}, simulator, recipe.simulator.name)
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

    key = fingerprint(key, plain["evaluate"])
    stages = dict(scene=scene, particles=particles, reconstruction=reconstruction)
    metrics = evaluate_stage(recipe, stages, identified, simulator, rd, key, started=t_start)
    log.info(
        "done: observed cd %.3g mm^2%s; results in %s",
        metrics["observed"]["cd_mm2"],
        f", future cd {metrics['future']['cd_mm2']:.3g} mm^2" if metrics["future"] else "",
        rd.root,
    )
    return metrics


def reconstruct_stage(recipe, scene, rd: RunDir, key: str):
    """Stage I: the recipe's reconstructor fitted to the scene (reconstruction.pt)."""
    if rd.stage_done("reconstruct", key):
        return rd.load_torch("reconstruction.pt")
    name, options = component(recipe.reconstructor)
    log.info("reconstructing with %r", name)
    reconstructor = get_registry().create("reconstructor", name, options)
    reconstruction = reconstructor.fit(scene, run_dir=rd.root)
    rd.save_torch("reconstruction.pt", reconstruction)
    rd.mark_done("reconstruct", key)
    return reconstruction


def lift_stage(recipe, scene, reconstruction, rd: RunDir, key: str):
    """Stage II: the reconstruction lifted to simulation particles (particles.pt)."""
    if rd.stage_done("lift", key):
        return rd.load_torch("particles.pt")
    name, options = component(recipe.lifter)
    log.info("lifting with %r", name)
    particles = get_registry().create("lifter", name, options).lift(reconstruction, scene)
    rd.save_torch("particles.pt", particles)
    rd.mark_done("lift", key, particles=len(particles))
    return particles


def build_simulator(section):
    """The recipe's simulator and its options. A deterministic simulator on a GPU also makes
    torch deterministic: the losses' gathers scatter their gradients on the GPU too, in a fixed
    order then, so an identification repeats bit for bit (cuBLAS products already do)."""
    name, options = component(section)
    simulator = get_registry().create("simulator", name, options)
    if simulator.deterministic and torch.device(simulator.torch_device).type == "cuda":
        torch.use_deterministic_algorithms(True, warn_only=True)
    return simulator, options


def simulator_refiner(section):
    """A function ``factor -> (substeps, simulator)`` building the recipe's simulator with
    ``factor`` times its substeps; None when its options name no integer ``substeps``."""
    name, options = component(section)
    base = options.get("substeps")
    if not isinstance(base, int) or isinstance(base, bool):
        return None

    def refined(factor: int):
        substeps = base * factor
        return substeps, get_registry().create("simulator", name, {**options, "substeps": substeps})

    return refined


def evaluate_stage(recipe, stages: dict, identified, simulator, rd: RunDir, key: str, *, started):
    """Evaluation over observed and future frames (metrics.json, plots, videos).

    A resumed run, such as a suite entry run again after its diagnosis was cut short, keeps its
    metrics, plots and videos rather than rolling out again."""
    if rd.stage_done("evaluate", key) and rd.path("metrics.json").is_file():
        return rd.load_json("metrics.json")
    log.info("evaluating over observed and future frames")
    metrics = evaluate_run(
        recipe=recipe,
        **stages,
        identified=identified,
        simulator=simulator,
        run_dir=rd,
        started=started,
        refine=simulator_refiner(recipe.simulator),
    )
    rd.mark_done("evaluate", key)
    return metrics
