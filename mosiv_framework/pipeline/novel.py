"""Re-evaluating a finished run and simulating novel interactions from it (paper section 3.7).

``load_finished_run`` reads what ``mosiv run`` left in a run folder (recipe, particles,
reconstruction, identified parameters). ``edit_params`` turns command-line edits into new
SimulationParams: swapped materials, changed parameter values, new initial velocities.
``simulate_novel`` rolls the edited model out and writes its rollout, parameters and a video.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, replace
from pathlib import Path

import torch
from omegaconf import DictConfig, OmegaConf

from mosiv_framework.errors import ConfigError
from mosiv_framework.laws import get_law
from mosiv_framework.pipeline.contact import simulator_section
from mosiv_framework.pipeline.formats import PARAMS, stamped
from mosiv_framework.pipeline.params import (
    GROUND_FRICTION,
    ParameterVector,
    term_param_specs,
    terms_json,
)
from mosiv_framework.pipeline.rundir import RunDir
from mosiv_framework.pipeline.video import pick_camera, save_rollout_npz, write_rollout_video
from mosiv_framework.recipes.terms import param_size
from mosiv_framework.registry import get_registry
from mosiv_framework.scene import read_scene
from mosiv_framework.types import ObjectParams, SimulationParams

#: files ``mosiv run`` leaves that re-evaluation and simulation need
REQUIRED = ("recipe.yaml", "particles.pt", "reconstruction.pt", "identified.json")


@dataclass
class FinishedRun:
    run_dir: RunDir
    recipe: DictConfig
    scene: object
    particles: object
    reconstruction: object
    identified: SimulationParams
    #: identified.json as the run wrote it (its ``contact`` says which contact was identified)
    identified_json: dict | None = None

    @property
    def simulator_section(self) -> DictConfig:
        """The recipe's simulator with the contact identification used."""
        return simulator_section(self.recipe.simulator, self.identified_json)

    def simulator(self):
        options = dict(OmegaConf.to_container(self.simulator_section, resolve=True))
        name = options.pop("name")
        return get_registry().create("simulator", name, options)


def load_finished_run(run_dir: str | Path) -> FinishedRun:
    """Everything a finished run folder holds; ConfigError naming what is missing."""
    rd = RunDir(run_dir) if Path(run_dir).is_dir() else None
    if rd is None:
        raise ConfigError(f"run folder {str(run_dir)!r} does not exist")
    missing = [name for name in REQUIRED if not rd.path(name).is_file()]
    if missing:
        raise ConfigError(
            f"{rd.root} is not a finished run folder: it lacks {missing}; run "
            f"`mosiv run RECIPE output.dir={rd.root}` first"
        )
    # re-validated, so options added since the run was made take their defaults
    from mosiv_framework.recipes import validate_recipe

    stored = OmegaConf.to_container(OmegaConf.load(rd.path("recipe.yaml")), resolve=True)
    resolved, problems = validate_recipe(stored, get_registry())
    if problems:
        raise ConfigError([f"{rd.path('recipe.yaml')}: {p}" for p in problems])
    recipe = OmegaConf.create(resolved)
    identified_json = rd.load_json("identified.json")
    return FinishedRun(
        run_dir=rd,
        recipe=recipe,
        scene=read_scene(recipe.scene.path),
        particles=rd.load_torch("particles.pt"),
        reconstruction=rd.load_torch("reconstruction.pt"),
        identified=ParameterVector.from_json(identified_json),
        identified_json=identified_json,
    )


def _object_id(text: str, params: SimulationParams, what: str) -> int:
    """``"obj2"`` or ``"2"`` -> 2, checked against the run's objects."""
    raw = text.strip().removeprefix("obj")
    try:
        k = int(raw)
    except ValueError:
        raise ConfigError(f"{what}: {text!r} is not an object id like obj1 or 1") from None
    if k not in params.objects:
        raise ConfigError(f"{what}: no object {k}; the run has objects {sorted(params.objects)}")
    return k


def _floats(text: str, n: int, what: str) -> list[float]:
    try:
        values = [float(x) for x in text.split(",")]
    except ValueError:
        values = []
    if len(values) != n:
        raise ConfigError(f"{what}: expected {n} comma-separated numbers, got {text!r}")
    return values


def edit_params(
    params: SimulationParams,
    *,
    swap: str | None = None,
    sets: list[str] = (),
    velocities: list[str] = (),
) -> SimulationParams:
    """A copy of ``params`` with materials swapped (``"1,2"``), values set (``"obj1.E=1e5"``,
    ``"ground_friction=0.5"``, ``"term.wind.acceleration=0,1.5,0"``; SI units, checked against
    the law's or the term's bounds) and initial velocities replaced (``"obj1=0,0,1"`` in m/s).
    Setting a parameter of a physics term the run did not model adds that term, its other
    parameters at their zero (absent) values."""
    objects = {
        k: ObjectParams(p.family, {n: v.detach().clone() for n, v in p.values.items()})
        for k, p in params.objects.items()
    }
    v0 = {k: v.detach().clone() for k, v in params.initial_velocity.items()}
    ground = params.ground_friction.detach().clone()
    terms = {
        t: {n: v.detach().clone() for n, v in vals.items()} for t, vals in params.terms.items()
    }
    if swap:
        parts = swap.split(",")
        if len(parts) != 2:
            raise ConfigError(f"--swap {swap!r}: give two object ids, e.g. --swap 1,2")
        a, b = (_object_id(p, params, "--swap") for p in parts)
        objects[a], objects[b] = objects[b], objects[a]
    for item in sets:
        if "=" not in item:
            raise ConfigError(f"--set {item!r}: expected NAME=VALUE, e.g. obj1.E=1e5")
        name, value_text = item.split("=", 1)
        if name.startswith("term."):
            _set_term(terms, item, name, value_text)
            continue
        try:
            value = float(value_text)
        except ValueError:
            raise ConfigError(f"--set {item!r}: {value_text!r} is not a number") from None
        if name == "ground_friction":
            GROUND_FRICTION.check(value, where="--set")
            ground = torch.tensor(value)
            continue
        if "." not in name:
            raise ConfigError(
                f"--set {item!r}: name a parameter as objK.NAME, ground_friction or term.TERM.NAME"
            )
        obj_text, param = name.split(".", 1)
        k = _object_id(obj_text, params, "--set")
        law = get_law(objects[k].family)
        valid = [s.name for s in law.all_params]
        if param not in valid:
            raise ConfigError(
                f"--set {item!r}: object {k} is {objects[k].family}, whose parameters are {valid}"
            )
        try:
            law.param(param).check(value, where=f"--set object {k}")
        except ValueError as exc:
            raise ConfigError(str(exc)) from None
        objects[k].values[param] = torch.tensor(value)
    for item in velocities:
        if "=" not in item:
            raise ConfigError(f"--velocity {item!r}: expected objK=VX,VY,VZ (m/s)")
        obj_text, vec = item.split("=", 1)
        k = _object_id(obj_text, params, "--velocity")
        v0[k] = torch.tensor(_floats(vec, 3, f"--velocity {item!r}"), dtype=torch.float32)
    return SimulationParams(objects, v0, ground, terms)


def _set_term(terms: dict, item: str, name: str, value_text: str) -> None:
    """Apply ``--set term.TERM.NAME=VALUE`` to ``terms`` (a vector as ``x,y,z``)."""
    parts = name.split(".")
    if len(parts) != 3:
        raise ConfigError(f"--set {item!r}: name a term parameter as term.TERM.NAME")
    _, term, param = parts
    registered = get_registry().names("physics_term")
    if term not in registered:
        raise ConfigError(
            f"--set {item!r}: no physics term {term!r} is registered; registered terms: "
            f"{', '.join(registered) or 'none installed'}"
        )
    specs = term_param_specs(term)
    term_obj = get_registry().create("physics_term", term, {})
    if param not in specs:
        names = term_obj.parameter_names_text() if term_obj.sparse else sorted(specs)
        raise ConfigError(f"--set {item!r}: the parameters of {term} are {names}")
    spec = specs[param]
    values = _floats(value_text, param_size(spec), f"--set {item!r}")
    for v in values:
        try:
            spec.check(v, where=f"--set term {term}")
        except ValueError as exc:
            raise ConfigError(str(exc)) from None
    if term not in terms:  # a newly added term starts from its zero (absent) values
        terms[term] = {
            n: torch.tensor([float(sp.default)] * 3 if param_size(sp) == 3 else float(sp.default))
            for n, sp in specs.items()
            if not term_obj.sparse  # a sparse term holds only the parameters set
        }
    terms[term][param] = torch.tensor(values if len(values) == 3 else values[0])


def params_json(params: SimulationParams) -> dict:
    """Plain numbers of ``params`` (the layout of identified.json)."""
    return {
        "objects": {
            str(k): {
                "family": p.family,
                "params": {n: float(v) for n, v in sorted(p.values.items())},
                "initial_velocity": [float(x) for x in params.initial_velocity[k]],
            }
            for k, p in sorted(params.objects.items())
        },
        "ground_friction": float(params.ground_friction),
        **({"terms": terms_json(params.terms)} if params.terms else {}),
    }


def simulate_novel(
    run: FinishedRun,
    params: SimulationParams,
    *,
    frames: int | None = None,
    out_dir: Path,
    size: int = 256,
) -> dict[str, Path]:
    """Roll ``params`` out from the run's particles; write rollout.npz, params.json and
    video.gif (or .mp4, as evaluate.video_format says) into ``out_dir``. Returns the written
    paths."""
    frames = run.scene.n_frames - 1 if frames is None else int(frames)
    if frames < 1:
        raise ConfigError(f"--frames {frames}: simulate at least 1 frame")
    # swapped objects carry their family to the other body's particles
    particles = replace(run.particles, materials={k: p.family for k, p in params.objects.items()})
    simulator = run.simulator()
    unsupported = sorted(set(params.terms) - set(getattr(simulator, "supported_terms", ())))
    if unsupported:
        raise ConfigError(
            f"physics terms {unsupported} are not implemented by the run's simulator "
            f"{run.recipe.simulator.name!r}; it supports "
            f"{sorted(getattr(simulator, 'supported_terms', ())) or 'no terms'}"
        )
    with torch.no_grad():
        traj = simulator.rollout(particles, params, world=run.scene.world, frames=frames)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    written = {
        "rollout": save_rollout_npz(traj, out_dir / "rollout.npz"),
        "video": write_rollout_video(
            traj,
            camera=pick_camera(run.scene, run.recipe.evaluate.get("video_camera", "")),
            path=out_dir / f"video.{run.recipe.evaluate.get('video_format', 'gif')}",
            size=size,
            fps=run.scene.fps,
        ),
    }
    document = stamped(PARAMS, params_json(params))
    (out_dir / "params.json").write_text(json.dumps(document, indent=2) + "\n")
    written["params"] = out_dir / "params.json"
    return written
