"""``mosiv run``: scene -> reconstruct -> lift -> identify -> evaluate, each stage resumable.

Before anything is written the run checks its output folder (a new or empty folder, or a run
folder: ``mosiv_framework.pipeline.rundir``), generates the scene if the recipe says how,
validates the scene and the recipe's stiffness caps against it. Only then does it write
recipe.yaml and run.json; a run that fails before any stage finished takes them back.

Every stage's result is saved in the run folder with a fingerprint of the recipe sections it
depends on (and of the stages before it) and a digest of the scene's files; a rerun skips
stages whose fingerprint and digest match and recomputes the rest.
"""

from __future__ import annotations

import logging
import shutil
import time
from collections.abc import Mapping
from dataclasses import dataclass, replace
from pathlib import Path

import torch
from omegaconf import DictConfig, OmegaConf

from mosiv_framework.errors import ConfigError, SceneFormatError
from mosiv_framework.pipeline.contact import simulator_section
from mosiv_framework.pipeline.evaluate import evaluate_run
from mosiv_framework.pipeline.formats import recipe_header
from mosiv_framework.pipeline.identification import check_terms_supported, identify_stage
from mosiv_framework.pipeline.memory import stage_peak
from mosiv_framework.pipeline.params import ParameterVector
from mosiv_framework.pipeline.rundir import (
    OutputFolder,
    RunDir,
    RunRecord,
    earlier_scene_digest,
    fingerprint,
    scene_digest,
)
from mosiv_framework.recipes import check_stiffness
from mosiv_framework.recipes.cell_size import KEY as CELL_SIZE
from mosiv_framework.recipes.cell_size import resolve_cell_size
from mosiv_framework.registry import get_registry
from mosiv_framework.scene import read_scene, require_valid_scene
from mosiv_framework.types import ParticleSet

log = logging.getLogger(__name__)

STAGES = ("reconstruct", "lift", "identify", "evaluate")


def component(section) -> tuple[str, dict]:
    """A recipe component section as (name, the options its factory takes)."""
    options = dict(section)
    return options.pop("name"), options


def _occupied(path: Path) -> bool:
    """Whether something other than an empty folder is at ``path`` (a link counts)."""
    if not path.exists():
        return path.is_symlink()
    try:
        return not path.is_dir() or any(path.iterdir())
    except OSError:
        return True


def generate_scene(scene_section) -> bool:
    """Generate the scene with ``scene.source`` when ``scene.generate`` is "if-missing" and
    ``scene.path`` is missing or an empty folder; returns whether it did. Without "if-missing"
    a missing scene is a ConfigError naming scene.path and how to generate one: a mistyped
    path must not quietly become a synthetic scene."""
    path = Path(scene_section.path)
    if (path / "scene.json").is_file() or _occupied(path):
        # a scene, or files that are not one (scene.json missing or broken): validation names
        # what is wrong; a scene is never generated over the user's files
        return False
    generate = getattr(scene_section, "generate", None) or "never"
    if generate == "if-missing" and scene_section.source is not None:
        name, options = component(scene_section.source)
        log.info("generating scene with %r into %s", name, path)
        # written beside the scene and moved into place once complete: a generation that
        # dies part-way (a crashed engine, a lost machine) leaves no half scene that a later
        # run would take for the user's files
        partial = path.with_name(f".{path.name}.partial")
        if partial.exists():
            shutil.rmtree(partial)  # left by an interrupted generation of this scene
        get_registry().create("scene_source", name, options).generate(partial)
        if path.exists():
            path.rmdir()  # an empty folder (checked above)
        partial.rename(path)
        return True
    what = "holds no scene.json" if path.exists() else "does not exist"
    if scene_section.source is not None:
        how = (
            f"to generate a scene there with scene.source ({scene_section.source.get('name')}), "
            "set scene.generate=if-missing"
        )
    else:
        how = (
            "give the folder of a mosiv-scene/1 scene (`mosiv data synth` and `mosiv data "
            "import` write one), or name a scene.source and set scene.generate=if-missing"
        )
    raise ConfigError(f"scene.path {str(path)!r} {what}; {how}")


def ensure_scene(scene_section, run_dir: RunDir | None = None):
    """Read the scene, generating it first with ``scene.source`` when the folder is missing and
    ``scene.generate`` is "if-missing" (ConfigError for a missing scene otherwise)."""
    generate_scene(scene_section)
    return read_scene(Path(scene_section.path))


def needs_ground_truth(plain: dict) -> bool | None:
    """True when a component reads the scene's ground truth (the oracle reconstructor, the
    gt-points lifter): the scene must then hold valid gt/; None lets the check decide."""
    reads_gt = plain["reconstructor"]["name"] == "oracle" or plain["lifter"]["name"] == "gt-points"
    return True if reads_gt else None


def no_ground_truth_message(plain: dict, path: Path) -> str:
    """Why a recipe that reads gt/ cannot run on a scene without it, and what runs instead."""
    readers = [
        f"{kind} {plain[kind]['name']!r}"
        for kind, name in (("reconstructor", "oracle"), ("lifter", "gt-points"))
        if plain[kind]["name"] == name
    ]
    return (
        f"{path}: no ground truth (gt/), as in every recording; this recipe's "
        f"{' and '.join(readers)} read the scene's ground truth instead of its videos. "
        "Run a recipe that reconstructs from the videos: recipes/video_quickstart.yaml (small, "
        "CPU) or recipes/video_paper.yaml (paper size, GPU), e.g. `mosiv run "
        f"recipes/video_quickstart.yaml scene.path={path}`"
    )


def prepare_scene(recipe: DictConfig, plain: dict):
    """The scene, generated if needed and validated in full, and the warnings of the recipe's
    stiffness caps in it (an impossible cap raises ConfigError). A ``simulator.cell_size``
    becomes the grid it gives in the scene's domain, in ``recipe`` and ``plain`` alike
    (``mosiv_framework.recipes.cell_size``). Nothing of the run is written yet, so a scene or
    recipe the run cannot use leaves no run folder behind."""
    generate_scene(recipe.scene)
    path = Path(plain["scene"]["path"])
    need_gt = needs_ground_truth(plain)
    gt = path / "gt"
    if need_gt and not (gt.exists() or gt.is_symlink()):  # a gt/ file: validation names it
        raise SceneFormatError(no_ground_truth_message(plain, path))
    require_valid_scene(path, need_ground_truth=need_gt)
    scene = read_scene(path)
    if resolve_cell_size(recipe, scene.world.extent) is not None:
        plain["simulator"] = OmegaConf.to_container(recipe.simulator, resolve=True)
    warnings = check_stiffness(plain, world=scene.world, families=scene.materials)
    for warning in warnings:
        log.warning("%s", warning)
    return scene, warnings


def stage_keys(plain: dict, *, earlier: bool = False) -> dict[str, str]:
    """Each stage's configuration fingerprint, chained: a stage's key covers the stages
    before it. ``earlier``: the keys markers recorded before the scene entered by its content,
    when the first key held the scene's path."""
    # not the scene's path: its content is the stage's input (``scene_digest``), so a run
    # folder and its scene copied elsewhere resume there
    key = fingerprint(*([plain["scene"]["path"]] if earlier else []), plain["reconstructor"])
    keys = {"reconstruct": key}
    keys["lift"] = key = fingerprint(key, plain["lifter"])
    key = fingerprint(key, plain["simulator"], plain["losses"], _identify_key(plain["identify"]))
    if plain.get("physics_terms"):  # only then, so runs made without terms keep their key
        key = fingerprint(key, plain["physics_terms"])
    keys["identify"] = key
    keys["evaluate"] = fingerprint(key, plain["evaluate"])
    return keys


def _identify_key(section: dict) -> dict:
    """What of the identify section its stage key covers: with ``law_choice: fixed`` the law
    alternatives are never tried, so neither they nor the choice enter the key, and a
    ``global_polish`` or ``holdout_frames`` of 0 and a ``ground_friction_start`` of "start"
    are left out too (runs made before those existed keep their keys)."""
    for key in ("global_polish", "holdout_frames"):
        if not section.get(key, 0):
            section = {k: v for k, v in section.items() if k != key}
    if section.get("ground_friction_start", "start") == "start":
        section = {k: v for k, v in section.items() if k != "ground_friction_start"}
    if section.get("law_choice", "fixed") != "fixed":
        return section
    return {k: v for k, v in section.items() if k not in ("law_choice", "law_alternatives")}


@dataclass
class Progress:
    """Where the stages record themselves: the run folder, run.json, each stage's key and the
    digest of the scene every stage reads."""

    rd: RunDir
    record: RunRecord
    keys: dict[str, str]
    digest: str

    def done(self, stage: str) -> bool:
        """Whether ``stage`` finished with this configuration on this scene."""
        finished = self.rd.stage_done(stage, self.keys[stage], self.digest)
        if finished:
            self.record.stage_done(stage)
        return finished

    def mark(self, stage: str, **info) -> None:
        self.rd.mark_done(stage, self.keys[stage], self.digest, **info)
        self.record.stage_done(stage)

    def _earlier_markers(self) -> dict[str, dict]:
        """Each stage before evaluation: what its marker records ({} where it has none)."""
        markers = {}
        for stage in STAGES[:-1]:
            marker = f"stages/{stage}.json"
            found = self.rd.path(marker).is_file()
            markers[stage] = self.rd.load_json(marker) if found else {}
        return markers

    def stage_times(self) -> dict[str, float | None]:
        """Seconds each finished stage before evaluation took when it ran (a resumed stage
        keeps the time of the run that made it; None where its marker predates the timing)."""
        return {stage: info.get("time_s") for stage, info in self._earlier_markers().items()}

    def stage_peaks(self) -> dict[str, dict | None]:
        """The peak memory each finished stage before evaluation recorded when it ran
        (``memory.stage_peak``; None where its marker predates the record)."""
        keys = ("peak_memory_gb", "memory")
        return {
            stage: {k: info[k] for k in keys if k in info} or None
            for stage, info in self._earlier_markers().items()
        }

    def carry_earlier_markers(self, plain: dict, scene_root: Path) -> None:
        """Markers written before the scene entered by its content (keys holding the scene's
        path, the scene digested by file times) still describe this run when the scene is
        where and as it was: rewrite them in the current form instead of rerunning."""
        earlier_keys, earlier_digest = stage_keys(plain, earlier=True), None
        carried = []
        for stage in STAGES:
            # a new run has no markers: nothing to carry, and no earlier digest to compute
            if not self.rd.path(f"stages/{stage}.json").is_file():
                continue
            if self.rd.stage_state(stage, self.keys[stage], self.digest) != "missing":
                continue
            earlier_digest = earlier_digest or earlier_scene_digest(scene_root)
            if self.rd.stage_done(stage, earlier_keys[stage], earlier_digest):
                self.rd.rekey_marker(stage, self.keys[stage], self.digest)
                carried.append(stage)
        if carried:
            log.info("stage markers of an earlier MOSIV carried over: %s", ", ".join(carried))

    def announce_changes(self) -> None:
        """Say so when the scene changed under finished stages, and where the run restarts."""
        states = {s: self.rd.stage_state(s, self.keys[s], self.digest) for s in STAGES}
        if "changed" in states.values():
            first = next(s for s in STAGES if states[s] != "done")
            log.info("scene changed since the last run: rerunning from %s", first)


def run_pipeline(recipe: DictConfig, *, run_dir: Path, force: bool = False) -> dict:
    """Run every stage of ``recipe`` into ``run_dir``; returns the metrics.

    Args:
        recipe: the validated recipe.
        run_dir: the run folder (``output.dir``): new, empty, or a run folder to resume.
        force: with ``output.resume=false``, remove the previous run's files there first
            (only the files a run writes; anything else in the folder is kept).
    Raises:
        OutputError: the folder is not the run's to write, or holds a run and
            ``output.resume=false`` without ``force``.
    """
    t_start = time.perf_counter()
    plain = OmegaConf.to_container(recipe, resolve=True)
    folder = OutputFolder(run_dir, scene_path=plain["scene"]["path"])
    resume = bool((plain.get("output") or {}).get("resume", True))
    if not resume and not force:
        folder.start_afresh(force=False)  # refuses a folder holding a run; removes nothing
    if resume and force:
        log.warning("--force has no effect with output.resume=true: the run resumes")
    try:
        scene, warnings = prepare_scene(recipe, plain)
        removed = folder.start_afresh(force=True) if not resume else []
        if removed:
            log.info("output.resume=false: removed the previous run's %s", ", ".join(removed))
        progress = open_run(recipe, plain, folder, scene)
        metrics = run_stages(recipe, plain, scene, progress, warnings, started=t_start)
    except BaseException:
        folder.undo()
        raise
    log.info(
        "done: observed cd %.3g mm^2%s; results in %s",
        metrics["observed"]["cd_mm2"],
        f", future cd {metrics['future']['cd_mm2']:.3g} mm^2" if metrics["future"] else "",
        progress.rd.root,
    )
    return metrics


def open_run(recipe: DictConfig, plain: dict, folder: OutputFolder, scene) -> Progress:
    """Write recipe.yaml and run.json into the run folder; the stages' progress."""
    rd = RunDir(folder.root)
    if folder.kind == "earlier run":
        log.info("%s: a run folder made before run.json existed; adding run.json", rd.root)
    rd.write_bytes("recipe.yaml", recipe_header() + OmegaConf.to_yaml(recipe).encode())
    digest = scene_digest(scene.root)
    record = RunRecord(
        rd,
        folder.record,
        recipe=fingerprint(plain),
        scene=str(plain["scene"]["path"]),
        digest=digest,
    )
    record.save()
    progress = Progress(rd, record, stage_keys(plain), digest)
    progress.carry_earlier_markers(plain, Path(scene.root))
    return progress


def run_stages(recipe, plain, scene, progress: Progress, warnings, *, started) -> dict:
    """The four stages, each resumed when its marker matches; returns the metrics."""
    log.info(
        "scene %r: %d objects, %d cameras, %d frames (%d observed)",
        scene.name,
        len(scene.objects),
        len(scene.cameras),
        scene.n_frames,
        scene.observed_frames,
    )
    progress.announce_changes()
    rd = progress.rd
    reconstruction = reconstruct_stage(recipe, scene, progress)
    particles = lift_stage(recipe, scene, reconstruction, progress)

    simulator, sim_options = build_simulator(recipe.simulator)
    check_terms_supported(plain.get("physics_terms") or {}, simulator, recipe.simulator.name)
    if progress.done("identify"):
        identified = ParameterVector.from_json(rd.load_json("identified.json"))
    else:
        # the checkpoint of an interrupted identification resumes only on the same scene
        checkpoint_key = fingerprint(progress.keys["identify"], progress.digest)
        t_identify = time.perf_counter()
        identified = identify_stage(
            recipe,
            scene,
            with_identified_laws(particles, recipe.identify.laws),
            reconstruction,
            simulator,
            sim_options,
            rd,
            checkpoint_key,
            warnings=warnings,
        )
        elapsed = round(time.perf_counter() - t_identify, 3)
        progress.mark("identify", time_s=elapsed, **stage_peak(simulator))

    # evaluation rolls out with the contact identification used (identify.contact: auto
    # may have chosen another than the recipe's simulator.contact)
    section = simulator_section(recipe.simulator, rd.load_json("identified.json"))
    if section != recipe.simulator:
        simulator, _ = build_simulator(section)
    stages = dict(scene=scene, particles=particles, reconstruction=reconstruction)
    simulators = (simulator, simulator_refiner(section))
    return evaluate_stage(recipe, stages, identified, simulators, progress, started=started)


def with_identified_laws(particles: ParticleSet, laws: Mapping[str, str]) -> ParticleSet:
    """``particles`` with each object's material replaced by the law ``identify.laws`` names
    for it (the same particles where it names none)."""
    if not laws:
        return particles
    materials = {k: laws.get(family, family) for k, family in particles.materials.items()}
    for k, family in particles.materials.items():
        if materials[k] != family:
            log.info("object %s (%s) is identified with the law %s", k, family, materials[k])
    return replace(particles, materials=materials)


def reconstruct_stage(recipe, scene, progress: Progress):
    """Stage I: the recipe's reconstructor fitted to the scene (reconstruction.pt)."""
    rd = progress.rd
    if progress.done("reconstruct"):
        return rd.load_torch("reconstruction.pt")
    name, options = component(recipe.reconstructor)
    log.info("reconstructing with %r", name)
    reconstructor = get_registry().create("reconstructor", name, options)
    before = set(p.name for p in rd.root.iterdir())
    t_start = time.perf_counter()
    reconstruction = reconstructor.fit(scene, run_dir=rd.root)
    elapsed = round(time.perf_counter() - t_start, 3)
    # what the reconstructor saved of its own in the run folder is the run's too
    progress.record.add_files(p.name for p in rd.root.iterdir() if p.name not in before)
    rd.save_torch("reconstruction.pt", reconstruction)
    progress.mark("reconstruct", time_s=elapsed, **stage_peak())
    return reconstruction


def lift_stage(recipe, scene, reconstruction, progress: Progress):
    """Stage II: the reconstruction lifted to simulation particles (particles.pt)."""
    rd = progress.rd
    if progress.done("lift"):
        return rd.load_torch("particles.pt")
    name, options = component(recipe.lifter)
    log.info("lifting with %r", name)
    t_start = time.perf_counter()
    particles = get_registry().create("lifter", name, options).lift(reconstruction, scene)
    elapsed = round(time.perf_counter() - t_start, 3)
    rd.save_torch("particles.pt", particles)
    progress.mark("lift", particles=len(particles), time_s=elapsed, **stage_peak())
    return particles


def build_simulator(section):
    """The recipe's simulator and its options. A deterministic simulator on a GPU also makes
    torch deterministic: the losses' gathers scatter their gradients on the GPU too, in a fixed
    order then, so an identification repeats bit for bit (cuBLAS products already do)."""
    name, options = component(section)
    if options.get(CELL_SIZE) is not None:
        raise ConfigError(
            f"simulator.{CELL_SIZE}={options[CELL_SIZE]!r} is a resolution in metres that a run "
            "turns into simulator.grid for its scene (resolve_cell_size) before building the "
            "simulator"
        )
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


def evaluate_stage(recipe, stages: dict, identified, simulators, progress: Progress, *, started):
    """Evaluation over observed and future frames (metrics.json, plots, videos); ``simulators``
    is (the simulator in the contact mode identification used, its ``simulator_refiner``: the
    same with more substeps, for a rollout that diverges).

    A resumed run, such as a suite entry run again after its diagnosis was cut short, keeps its
    metrics, plots and videos rather than rolling out again."""
    rd = progress.rd
    if rd.path("metrics.json").is_file() and progress.done("evaluate"):
        return rd.load_json("metrics.json")
    log.info("evaluating over observed and future frames")
    simulator, refine = simulators
    metrics = evaluate_run(
        recipe=recipe,
        **stages,
        identified=identified,
        simulator=simulator,
        run_dir=rd,
        started=started,
        refine=refine,
        stage_times=progress.stage_times(),
        stage_peaks=progress.stage_peaks(),
    )
    progress.mark("evaluate")
    return metrics
