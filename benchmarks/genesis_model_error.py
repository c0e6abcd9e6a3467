"""Model error on Genesis scenes: the true parameters rolled out by our simulator.

Identification can only be as good as the model: if warp-mpm, given Genesis's own parameters,
its own particles and its own initial velocities, does not reproduce what Genesis simulated,
the best-fitting parameters are not the true ones. This measures that gap without any
optimisation. For every scene of a suite folder (``mosiv data suite OUT --source genesis``)
and every configuration (a stress-law mapping, a contact between objects, a grid and a
substep count), the recipe's oracle reconstructor and gt-points lifter give the frame-0
particles, each object gets its true parameters from ``gt/params.json`` (the ground's Coulomb
coefficient is Genesis's 0.1, or the one gt/params.json records; a parameter the truth does
not give keeps the law's default: scenes made before gt/params.json recorded a Genesis
liquid's viscosity roll their newtonian bodies out at the default), and the rollout over
every frame is scored against ``gt/points.npz`` (observed and future Chamfer and EMD). On a
scene our own generator made at the same grid and substeps the error is 0 (the test).

    python benchmarks/genesis_model_error.py --scenes runs/genesis --out runs/model_error \\
        --laws own corotated --contacts multi_field single_field --grids 48 64 --substeps 400

``--ground-frictions 0.1 0.3`` rolls the truth out with those coefficients of the ground in
place of the truth's (key suffix ``/gf0.1``), ``--ground-offsets-mm 0 9`` with the table raised
(``/dz9``; warp-mpm's ground acts on whole node layers, so only a whole cell changes it).
``--splits 1 2`` also lifts each point into 2^3 particles (the gt-points lifter's ``split``):
Genesis samples its bodies about 1 cm apart, fewer than one particle a cell on a grid of 96
over the 0.8 m domain. ``--laws own`` rolls each material out with its own law; ``corotated`` with Genesis's fixed-
corotated stress for elastic and plasticine bodies (``elastic_corotated``,
``plasticine_corotated``). Writes ``OUT/model_error.json`` (one row per scene and
configuration, with its wall time, machine and code version) and ``OUT/model_error.md`` (the
table and the per-configuration means). A rerun skips rows already in the JSON. ``--report``
measures nothing: it gathers every ``model_error.json`` under ``OUT`` (one process per scene
may each have written its own folder) into ``OUT/model_error.md``, and with
``--write-results FILE`` into that file's section "Model error on Genesis scenes".
"""

from __future__ import annotations

import argparse
import datetime
import itertools
import json
import statistics
import sys
import time
from dataclasses import replace
from pathlib import Path

import torch
from genesis_identify import _device_name, _fill, find_scenes, replace_section, shown_command
from identify_suite import code_version

from mosiv_framework.errors import SimulationDiverged
from mosiv_framework.pipeline.evaluate import score
from mosiv_framework.pipeline.run import build_simulator, component, with_identified_laws
from mosiv_framework.recipes import load_recipe
from mosiv_framework.recipes.cell_size import resolve_cell_size
from mosiv_framework.registry import get_registry
from mosiv_framework.scene import read_scene
from mosiv_framework.types import ObjectParams, SimulationParams

FORMAT = "mosiv-genesis-model-error/1"
SECTION = "Model error on Genesis scenes"
#: the stress-law mappings a configuration can name (scene material -> law)
LAW_MAPS = {
    "own": {},
    "corotated": {"elastic": "elastic_corotated", "plasticine": "plasticine_corotated"},
}
#: Genesis's Coulomb coefficient on the nodes at or below the table (its coup_friction); a
#: scene whose gt/params.json records its own (mosiv-synth's ``ground_friction``) uses that
GENESIS_GROUND_FRICTION = 0.1


def true_params(scene, materials: dict[int, str]) -> SimulationParams:
    """The scene's true parameters for the laws ``materials`` names, with every parameter the
    truth does not give (a newtonian body's viscosity, a law's extra constants) at the law's
    default value."""
    from mosiv_framework.laws import get_law

    objects, v0 = {}, {}
    gt = scene.gt_params()
    ground = (gt.get("generator_params") or {}).get("ground_friction", GENESIS_GROUND_FRICTION)
    for record in gt["objects"]:
        k = int(record["id"])
        law = get_law(materials[k])
        values = {**law.defaults(), **{n: v for n, v in record["params"].items()}}
        names = {spec.name for spec in law.all_params}
        objects[k] = ObjectParams(
            materials[k],
            {n: torch.tensor(float(v)) for n, v in values.items() if n in names},
        )
        v0[k] = torch.tensor(record["initial_velocity"], dtype=torch.float32)
    return SimulationParams(objects, v0, torch.tensor(float(ground)))


def frame0_particles(recipe, scene, split: int = 1):
    """The recipe's reconstructor and lifter on ``scene``: the particles identification uses;
    ``split`` > 1: the gt-points lifter's ``split`` option (each point into split^3)."""
    registry = get_registry()
    name, options = component(recipe.reconstructor)
    reconstruction = registry.create("reconstructor", name, options).fit(scene, run_dir=None)
    name, options = component(recipe.lifter)
    if split != 1:
        options = {**options, "split": split}
    return registry.create("lifter", name, options).lift(reconstruction, scene)


def configurations(args) -> list[dict]:
    """Every (laws, contact, grid, substeps, split, ground friction, ground offset) the command
    names, in a fixed order."""
    return [
        {
            "laws": laws, "contact": contact, "grid": grid, "substeps": substeps, "split": split,
            "ground_friction": friction, "ground_offset_mm": offset,
        }
        for laws, contact, grid, substeps, split, friction, offset in itertools.product(
            args.laws, args.contacts, args.grids, args.substeps, args.splits,
            args.ground_frictions, args.ground_offsets_mm,
        )
    ]  # fmt: skip


def config_key(config: dict) -> str:
    key = f"{config['laws']}/{config['contact']}/g{config['grid']}/s{config['substeps']}"
    split = config.get("split", 1)
    if split != 1:
        key += f"/split{split}"
    if config.get("ground_friction") is not None:
        key += f"/gf{config['ground_friction']:g}"
    if config.get("ground_offset_mm"):
        key += f"/dz{config['ground_offset_mm']:g}"
    return key


def rollout_truth(recipe, scene, particles, config: dict):
    """The scene's true parameters rolled out from ``particles`` over every frame, with the
    recipe's simulator at ``config``'s contact, grid and substeps and the stress laws of its
    ``laws`` (default: each material's own); ``ground_friction`` (when not None) in place of
    the truth's, the table ``ground_offset_mm`` higher (warp-mpm's ground acts on the node
    layers at or below it, so an offset counts in whole cells); raises SimulationDiverged."""
    resolve_cell_size(recipe, scene.world.extent)  # a recipe giving its cell in metres
    section = recipe.simulator.copy()
    section.contact = config["contact"]
    section.grid = config["grid"]
    section.substeps = config["substeps"]
    simulator, _ = build_simulator(section)
    mapped = with_identified_laws(particles, LAW_MAPS[config.get("laws", "own")])
    params = true_params(scene, mapped.materials)
    if config.get("ground_friction") is not None:
        params = replace(params, ground_friction=torch.tensor(float(config["ground_friction"])))
    world = scene.world
    if config.get("ground_offset_mm"):
        if world.ground_height is None:
            raise SystemExit(f"{scene.root}: --ground-offsets-mm on a scene without a ground")
        world = replace(world, ground_height=world.ground_height + config["ground_offset_mm"] / 1e3)
    with torch.no_grad():
        return simulator.rollout(mapped, params, world=world, frames=scene.n_frames - 1)


def measure(recipe, scene, particles, config: dict, *, emd_samples: int) -> dict:
    """One configuration's rollout of the truth, scored; a divergence is a row that says so."""
    started = time.perf_counter()
    row = {"scene": scene.root.name, "config": config_key(config), **config}
    row.update(device=_device_name(recipe), code=code_version())
    try:
        traj = rollout_truth(recipe, scene, particles, config)
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
            "median_future_cd": statistics.median(r["future_cd"] for r in ok) if ok else None,
            "time_s": sum(r["time_s"] for r in mine),
        })  # fmt: skip
    return out


def _mean(rows: list[dict], name: str) -> float | None:
    return sum(r[name] for r in rows) / len(rows) if rows else None


def _num(value) -> str:
    return "-" if value is None else f"{value:.3g}"


def markdown(rows: list[dict]) -> str:
    """The per-scene table (observed / future CD per configuration) and the means."""
    keys = list(dict.fromkeys(r["config"] for r in rows))
    scenes = sorted(dict.fromkeys(r["scene"] for r in rows))
    cell = {(r["scene"], r["config"]): r for r in rows}
    lines = ["| scene | " + " | ".join(keys) + " |", "|---|" + "---|" * len(keys)]
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
    lines += [
        "",
        "| configuration | scenes | diverged | mean observed CD | mean future CD | "
        "median future CD | wall s (sum; a process compiles in its first) |",
        "|---|---|---|---|---|---|---|",
    ]
    for s in summary(rows):
        lines.append(
            f"| {s['config']} | {s['scenes']} | {s['diverged']} | {_num(s['mean_observed_cd'])} "
            f"| {_num(s['mean_future_cd'])} | {_num(s['median_future_cd'])} | {s['time_s']:.0f} |"
        )
    return "\n".join(lines) + "\n"


def section_text(rows: list[dict], *, command: str, report: str) -> str:
    """The RESULTS section: what is measured, how, where, and the tables."""
    machines = sorted({str(r.get("device", "not recorded")) for r in rows})
    codes = sorted({str(r.get("code", "not recorded")) for r in rows})
    intro = (
        "The true parameters of each Genesis scene (gt/params.json), Genesis's own frame-0 "
        "particles (oracle reconstructor, gt-points lifter of `recipes/genesis_oracle.yaml`) "
        "and initial velocities, rolled out by warp-mpm and scored against gt/points.npz: the "
        "error of the model itself, before any identification. Columns: LAWS/CONTACT/gGRID/"
        "sSUBSTEPS; own: each material's own law, corotated: Genesis's fixed-corotated stress "
        "for elastic and plasticine bodies. Cells: observed / future Chamfer (mm^2)."
    )
    return "\n".join(
        [
            f"## {SECTION}",
            "",
            _fill(intro),
            "",
            f"- Command: `{command}` (one process per scene), then `{report}`",
            f"- Machine: {', '.join(machines)}. Date {datetime.date.today().isoformat()}. "
            f"Code {', '.join(codes)}.",
            "- Data: the 13 Genesis scenes of [Identification on Genesis scenes]"
            "(#identification-on-genesis-scenes), wide ranges, seeds 0-12, with a liquid's "
            "viscosity and bulk modulus as gt/params.json now records them.",
            "",
            markdown(rows),
        ]
    )


def gather_rows(out: Path, name: str, fmt: str, what: str) -> list[dict]:
    """Every row of every ``name`` file of format ``fmt`` under ``out`` (one process per scene
    may each have written its own folder); ``what`` names the table in errors."""
    rows = []
    for path in sorted(out.rglob(name)):
        data = json.loads(path.read_text())
        if data.get("format") != fmt:
            raise SystemExit(f"{path}: not {what} (format {data.get('format')!r})")
        rows += data["rows"]
    if not rows:
        raise SystemExit(f"--report: no {name} under {out}")
    return rows


def gather(out: Path) -> list[dict]:
    """Every row of every model_error.json under ``out``."""
    return gather_rows(out, "model_error.json", FORMAT, "a model-error table")


def parse_args(argv: list[str] | None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", type=Path, help="suite folder (not needed with --report)")
    ap.add_argument("--out", type=Path, required=True, help="folder for model_error.json/.md")
    ap.add_argument("--recipe", type=Path, default=Path("recipes/genesis_oracle.yaml"))
    ap.add_argument("--only", help="comma-separated scene names")
    ap.add_argument("--laws", nargs="+", default=["own"], choices=sorted(LAW_MAPS))
    ap.add_argument("--contacts", nargs="+", default=["multi_field", "single_field"])
    ap.add_argument("--grids", nargs="+", type=int, default=[64])
    ap.add_argument("--substeps", nargs="+", type=int, default=[400])
    ap.add_argument("--device", default=None, help="simulator device (default: the recipe's)")
    ap.add_argument(
        "--splits", nargs="+", type=int, default=[1],
        help="gt-points lifter splits: each point into k^3 particles (default 1: as given)",
    )  # fmt: skip
    ap.add_argument(
        "--ground-frictions", nargs="+", type=float, default=[None],
        help="the ground's Coulomb coefficient in place of the truth's (default: the truth's)",
    )  # fmt: skip
    ap.add_argument(
        "--ground-offsets-mm", nargs="+", type=float, default=[0.0],
        help="the table raised by this much (mm; warp-mpm counts it in whole cells)",
    )  # fmt: skip
    ap.add_argument("--emd-samples", type=int, default=1024)
    ap.add_argument("--report", action="store_true", help="gather the rows under --out")
    ap.add_argument("--measured-with", default=None, help="the measuring command, for --report")
    ap.add_argument("--write-results", type=Path, default=None, help="markdown file to update")
    args = ap.parse_args(argv)
    if not args.report and args.scenes is None:
        ap.error("--scenes is required unless --report")
    if any(offset < 0 for offset in args.ground_offsets_mm):
        ap.error(
            f"--ground-offsets-mm {args.ground_offsets_mm}: the table can only be raised (>= 0)"
        )
    return args


def measure_all(args) -> list[dict]:
    """Measure every scene and configuration not yet in OUT/model_error.json; its rows."""
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
        lifted = {k: frame0_particles(recipe, scene, k) for k in args.splits}
        for config in configurations(args):
            if (scene.root.name, config_key(config)) in done:
                continue
            particles = lifted[config["split"]]
            row = measure(recipe, scene, particles, config, emd_samples=args.emd_samples)
            print(json.dumps(row), flush=True)
            data["rows"].append(row)
            path.write_text(json.dumps(data, indent=1))
    return data["rows"]


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    args = parse_args(argv)
    rows = gather(args.out) if args.report else measure_all(args)
    (args.out / "model_error.md").write_text(markdown(rows))
    print(markdown(rows))
    if args.write_results is not None:
        # the report's own command, without the quoted one
        command = shown_command(
            "benchmarks/genesis_model_error.py", argv, drop=("--measured-with",)
        )
        measured = args.measured_with or command
        body = section_text(rows, command=measured, report=command)
        text = args.write_results.read_text()
        args.write_results.write_text(replace_section(text, body, title=SECTION))
    return 0


if __name__ == "__main__":
    sys.exit(main())
