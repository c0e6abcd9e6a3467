"""Model error on Genesis scenes: the true parameters rolled out by our simulator.

Identification can only be as good as the model: if warp-mpm, given Genesis's own parameters,
its own particles and its own initial velocities, does not reproduce what Genesis simulated,
the best-fitting parameters are not the true ones. This measures that gap without any
optimisation. For every scene of a suite folder (``mosiv data suite OUT --source genesis``)
and every configuration (a stress-law mapping, a contact between objects, a grid and a
substep count), the recipe's oracle reconstructor and gt-points lifter give the frame-0
particles, each object gets its true parameters from ``gt/params.json`` (the ground's Coulomb
coefficient is Genesis's 0.1; a parameter the truth does not give keeps the law's default:
scenes made before gt/params.json recorded a Genesis liquid's viscosity roll their newtonian
bodies out at the default), and the rollout over every frame is scored against
``gt/points.npz`` (observed and future Chamfer and EMD).

    python benchmarks/genesis_model_error.py --scenes runs/genesis --out runs/model_error \\
        --laws own corotated --contacts multi_field single_field --grids 48 64 --substeps 400

``--laws own`` rolls each material out with its own law; ``corotated`` with Genesis's fixed-
corotated stress for elastic and plasticine bodies (``elastic_corotated``,
``plasticine_corotated``). Writes ``OUT/model_error.json`` (one row per scene and
configuration, with the configuration's wall time) and ``OUT/model_error.md`` (the table and
the per-configuration means). A rerun skips rows already in the JSON.
"""

from __future__ import annotations

import argparse
import itertools
import json
import sys
import time
from pathlib import Path

import torch
from genesis_identify import find_scenes
from identify_suite import code_version

from mosiv_framework.errors import SimulationDiverged
from mosiv_framework.pipeline.evaluate import score
from mosiv_framework.pipeline.run import build_simulator, component, with_identified_laws
from mosiv_framework.recipes import load_recipe
from mosiv_framework.registry import get_registry
from mosiv_framework.scene import read_scene
from mosiv_framework.types import ObjectParams, SimulationParams

FORMAT = "mosiv-genesis-model-error/1"
#: the stress-law mappings a configuration can name (scene material -> law)
LAW_MAPS = {
    "own": {},
    "corotated": {"elastic": "elastic_corotated", "plasticine": "plasticine_corotated"},
}
#: Genesis's Coulomb coefficient on the nodes at or below the table (its coup_friction)
GENESIS_GROUND_FRICTION = 0.1


def true_params(scene, materials: dict[int, str]) -> SimulationParams:
    """The scene's true parameters for the laws ``materials`` names, with every parameter the
    truth does not give (a newtonian body's viscosity, a law's extra constants) at the law's
    default value."""
    from mosiv_framework.laws import get_law

    objects, v0 = {}, {}
    for record in scene.gt_params()["objects"]:
        k = int(record["id"])
        law = get_law(materials[k])
        values = {**law.defaults(), **{n: v for n, v in record["params"].items()}}
        names = {spec.name for spec in law.all_params}
        objects[k] = ObjectParams(
            materials[k],
            {n: torch.tensor(float(v)) for n, v in values.items() if n in names},
        )
        v0[k] = torch.tensor(record["initial_velocity"], dtype=torch.float32)
    return SimulationParams(objects, v0, torch.tensor(GENESIS_GROUND_FRICTION))


def frame0_particles(recipe, scene):
    """The recipe's reconstructor and lifter on ``scene``: the particles identification uses."""
    registry = get_registry()
    name, options = component(recipe.reconstructor)
    reconstruction = registry.create("reconstructor", name, options).fit(scene, run_dir=None)
    name, options = component(recipe.lifter)
    return registry.create("lifter", name, options).lift(reconstruction, scene)


def configurations(args) -> list[dict]:
    """Every (laws, contact, grid, substeps) the command names, in a fixed order."""
    return [
        {"laws": laws, "contact": contact, "grid": grid, "substeps": substeps}
        for laws, contact, grid, substeps in itertools.product(
            args.laws, args.contacts, args.grids, args.substeps
        )
    ]


def config_key(config: dict) -> str:
    return f"{config['laws']}/{config['contact']}/g{config['grid']}/s{config['substeps']}"


def measure(recipe, scene, particles, config: dict, *, emd_samples: int) -> dict:
    """One configuration's rollout of the truth, scored; a divergence is a row that says so."""
    section = recipe.simulator.copy()
    section.contact = config["contact"]
    section.grid = config["grid"]
    section.substeps = config["substeps"]
    simulator, _ = build_simulator(section)
    mapped = with_identified_laws(particles, LAW_MAPS[config["laws"]])
    params = true_params(scene, mapped.materials)
    started = time.perf_counter()
    row = {"scene": scene.root.name, "config": config_key(config), **config}
    try:
        with torch.no_grad():
            traj = simulator.rollout(mapped, params, world=scene.world, frames=scene.n_frames - 1)
    except SimulationDiverged as exc:
        return {**row, "diverged": str(exc), "time_s": time.perf_counter() - started}
    blocks = score(
        traj,
        scene.gt_points(),
        observed_frames=scene.observed_frames,
        n_samples=emd_samples,
        seed=0,
    )
    return {
        **row,
        "observed_cd": blocks["observed"]["cd_mm2"],
        "future_cd": blocks["future"]["cd_mm2"],
        "observed_emd": blocks["observed"]["emd_mm"],
        "future_emd": blocks["future"]["emd_mm"],
        "time_s": time.perf_counter() - started,
    }


def summary(rows: list[dict]) -> list[dict]:
    """Per configuration: how many scenes, how many diverged, mean observed and future CD over
    the scenes that did not."""
    out = []
    for key in dict.fromkeys(r["config"] for r in rows):
        mine = [r for r in rows if r["config"] == key]
        ok = [r for r in mine if "diverged" not in r]
        out.append({
            "config": key, "scenes": len(mine), "diverged": len(mine) - len(ok),
            "mean_observed_cd": _mean(ok, "observed_cd"), "mean_future_cd": _mean(ok, "future_cd"),
            "time_s": sum(r["time_s"] for r in mine),
        })  # fmt: skip
    return out


def _mean(rows: list[dict], name: str) -> float | None:
    return sum(r[name] for r in rows) / len(rows) if rows else None


def _num(value) -> str:
    return "-" if value is None else f"{value:.3g}"


def markdown(rows: list[dict], *, command: str, version: str) -> str:
    """The per-scene table (observed / future CD per configuration) and the means."""
    keys = list(dict.fromkeys(r["config"] for r in rows))
    scenes = list(dict.fromkeys(r["scene"] for r in rows))
    cell = {(r["scene"], r["config"]): r for r in rows}
    lines = [
        f"Command: `{command}`. Code {version}.",
        "",
        "Observed / future Chamfer (mm^2) of the true parameters' rollout against gt/points.npz.",
        "",
        "| scene | " + " | ".join(keys) + " |",
        "|---|" + "---|" * len(keys),
    ]
    for scene in scenes:
        cells = []
        for key in keys:
            r = cell.get((scene, key))
            if r is None:
                cells.append("")
            elif "diverged" in r:
                cells.append("diverged")
            else:
                cells.append(f"{_num(r['observed_cd'])} / {_num(r['future_cd'])}")
        lines.append(f"| {scene} | " + " | ".join(cells) + " |")
    lines += ["", "| configuration | scenes | diverged | mean observed CD | mean future CD | time s |",
              "|---|---|---|---|---|---|"]  # fmt: skip
    for s in summary(rows):
        lines.append(
            f"| {s['config']} | {s['scenes']} | {s['diverged']} | {_num(s['mean_observed_cd'])} "
            f"| {_num(s['mean_future_cd'])} | {s['time_s']:.0f} |"
        )
    return "\n".join(lines) + "\n"


def parse_args(argv: list[str] | None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", type=Path, required=True, help="suite folder")
    ap.add_argument("--out", type=Path, required=True, help="folder for model_error.json/.md")
    ap.add_argument("--recipe", type=Path, default=Path("recipes/genesis_oracle.yaml"))
    ap.add_argument("--only", help="comma-separated scene names")
    ap.add_argument("--laws", nargs="+", default=["own"], choices=sorted(LAW_MAPS))
    ap.add_argument("--contacts", nargs="+", default=["multi_field", "single_field"])
    ap.add_argument("--grids", nargs="+", type=int, default=[64])
    ap.add_argument("--substeps", nargs="+", type=int, default=[400])
    ap.add_argument("--device", default=None, help="simulator device (default: the recipe's)")
    ap.add_argument("--emd-samples", type=int, default=1024)
    return ap.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    path = args.out / "model_error.json"
    data = json.loads(path.read_text()) if path.exists() else {"format": FORMAT, "rows": []}
    if data.get("format") != FORMAT:
        raise SystemExit(f"{path}: not a model-error table (format {data.get('format')!r})")
    done = {(r["scene"], r["config"]) for r in data["rows"]}
    overrides = [f"simulator.device={args.device}"] if args.device else []
    for name in find_scenes(args.scenes, args.only):
        folder = args.scenes / name
        recipe = load_recipe(args.recipe, [f"scene.path={folder}", *overrides])
        scene = read_scene(folder)
        particles = frame0_particles(recipe, scene)
        for config in configurations(args):
            if (scene.root.name, config_key(config)) in done:
                continue
            row = measure(recipe, scene, particles, config, emd_samples=args.emd_samples)
            print(json.dumps(row), flush=True)
            data["rows"].append(row)
            path.write_text(json.dumps(data, indent=1))
    command = "python benchmarks/genesis_model_error.py " + " ".join(argv or sys.argv[1:])
    (args.out / "model_error.md").write_text(
        markdown(data["rows"], command=command, version=code_version())
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
