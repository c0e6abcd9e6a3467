"""How far a from-video run's lifted particles send the truth: the true parameters rolled out
from them.

From-video identification fits parameters to the particles that Stage II lifts from Stage I's
Gaussians at frame 0. If the scene's true parameters, rolled out from those particles, do not
reproduce the recording, the best-fitting parameters are not the true ones, whatever the
optimiser does; the difference is the lift's share of the model error. For each RUN (a
finished from-video run folder: its ``recipe.yaml``, ``run.json`` naming the scene, and its
Stage I reconstruction, ``reconstruction.pt`` or the ``gauss-dynamic`` folder the reconstructor
saved) and each lifter variant (``--variant KEY=VALUE[,KEY=VALUE...]`` over the run's own
``lifter`` section; ``""``: the run's own lifter), this lifts the reconstruction again and
reports, per object, the particle count, the rest volume against the body's true volume (the
scene's ground-truth point count times the particle volume its generator records, where it
records one) and the frame-0 Chamfer to the ground truth; then it rolls the scene's true
parameters (``gt/params.json``, read as ``benchmarks/genesis_model_error.py`` reads them) out
with the run's simulator and scores them over the observed and future frames. The reference
row rolls the truth out from the scene's own frame-0 points (the gt-points lifter): on a
scene the project simulated at the run's settings it is near exact.

The truth is rolled out with the run's simulator as its recipe gives it: its contact (give
the generator's with ``--contact``, e.g. ``single_field`` for a Genesis scene), each
material's own law, and none of the effects a diagnosis scene conceals. A scene whose ground
truth lacks the initial velocities (an import that trimmed its first frames) is refused.

    python benchmarks/lift_gap.py RUN [RUN ...] --variant "" --variant mask_dilation_px=0 \\
        --device cpu --out OUT.json

Writes OUT.json (one row per run and variant, with the machine and code version) and prints
the table (``--markdown OUT.md`` also writes it).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import torch
from genesis_identify import _device_name
from genesis_model_error import measure
from identify_suite import code_version

from mosiv_framework.metrics import chamfer_mm2
from mosiv_framework.pipeline.run import component
from mosiv_framework.recipes import load_recipe
from mosiv_framework.recipes.cell_size import resolve_cell_size
from mosiv_framework.registry import get_registry
from mosiv_framework.scene import read_scene


def parse_variant(text: str) -> dict:
    """``KEY=VALUE,KEY=VALUE`` -> lifter options (values read as JSON, else kept as text)."""
    options = {}
    for item in filter(None, (part.strip() for part in text.split(","))):
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise SystemExit(f"--variant {text!r}: give KEY=VALUE pairs separated by commas")
        try:
            options[key] = json.loads(value)
        except json.JSONDecodeError:
            options[key] = value
    return options


def load_run(run: Path, device: str, sets: list[str] = ()):
    """The run's recipe (its simulator on ``device``, then ``sets`` applied), scene and Stage I
    reconstruction."""
    for name in ("recipe.yaml", "run.json"):
        if not (run / name).is_file():
            raise SystemExit(f"{run}: no {name}; give a from-video run folder")
    recipe = load_recipe(run / "recipe.yaml", [f"simulator.device={device}", *sets])
    scene_path = Path(json.loads((run / "run.json").read_text())["scene"]["path"])
    if not scene_path.is_dir():  # a run made on another machine: its scene beside the run
        scene_path = run.parent / scene_path.name
    if not scene_path.is_dir():
        raise SystemExit(
            f"{run}: its scene {scene_path.name} is neither where run.json says nor beside the run"
        )
    scene = read_scene(scene_path)
    resolve_cell_size(recipe, scene.world.extent)
    missing = [o["id"] for o in scene.gt_params()["objects"] if "initial_velocity" not in o]
    if missing:
        raise SystemExit(
            f"{scene_path}: gt/params.json gives no initial velocity for object(s) {missing} "
            "(an import that trimmed its first frames): the truth cannot be rolled out"
        )
    if (run / "reconstruction.pt").is_file():
        reconstruction = torch.load(run / "reconstruction.pt", weights_only=False)
    elif (run / "gauss-dynamic").is_dir():
        from mosiv_gauss.reconstructor import load_reconstruction

        reconstruction = load_reconstruction(run / "gauss-dynamic")
    else:
        raise SystemExit(f"{run}: neither reconstruction.pt nor gauss-dynamic/; no Stage I")
    return recipe, scene, reconstruction


def true_volumes(scene) -> dict[int, float | None]:
    """Each object's true rest volume: its frame-0 ground-truth points times the particle volume
    the generator records (None where it records none)."""
    volume = (scene.gt_params().get("generator_params") or {}).get("particle_volume")
    points = scene.gt_points()
    return {k: (len(p[0]) * float(volume) if volume else None) for k, p in points.items()}


def geometry_row(scene, particles) -> dict:
    """Per object: particle count, rest volume, true volume and frame-0 Chamfer (mm^2)."""
    truth, volumes = scene.gt_points(), true_volumes(scene)
    objects = {}
    for k in particles.object_list:
        mine = particles.object_ids == k
        volume = float(particles.volumes[mine].sum())
        true = volumes.get(k)
        objects[str(k)] = {
            "material": particles.materials[k],
            "particles": int(mine.sum()),
            "volume_m3": volume,
            "true_volume_m3": true,
            "volume_ratio": volume / true if true else None,
            "frame0_cd_mm2": chamfer_mm2(particles.positions[mine].numpy(), truth[k][0].numpy()),
        }
    return objects


def truth_row(recipe, scene, particles, contact: str | None) -> dict:
    """The truth rolled out from ``particles`` with the recipe's simulator and each material's
    own law, scored (``genesis_model_error.measure``; a divergence is a row that says so)."""
    section = recipe.simulator
    config = {
        "laws": "own",
        "contact": contact or section.get("contact", "multi_field"),
        "grid": section.grid,
        "substeps": section.substeps,
    }
    return measure(recipe, scene, particles, config, emd_samples=256)


def measure_run(
    run: Path, variants: list[str], *, device: str, contact: str | None, sets: list[str] = ()
) -> list:
    """The reference row and one row per lifter variant of ``run``."""
    recipe, scene, reconstruction = load_run(run, device, sets)
    registry = get_registry()
    # the run's folder with its parent: runs of several scenes are often all named alike
    base = {"run": f"{run.parent.name}/{run.name}", "scene": scene.root.name}
    base["code"] = code_version()
    base.update(grid=int(recipe.simulator.grid), extent_m=float(scene.world.extent))
    base["machine"] = _device_name(recipe)
    oracle = registry.create("reconstructor", "oracle", {}).fit(scene, run_dir=None)
    points = registry.create("lifter", "gt-points", {}).lift(oracle, scene)
    rows = [
        {
            **base,
            "variant": "scene's own points (gt-points lifter)",
            "objects": geometry_row(scene, points),
            **truth_row(recipe, scene, points, contact),
        }
    ]
    name, options = component(recipe.lifter)
    for variant in variants:
        lifter = registry.create("lifter", name, {**options, **parse_variant(variant)})
        particles = lifter.lift(reconstruction, scene)
        row = {**base, "variant": variant or "the run's lifter", "lifter": name}
        row["objects"] = geometry_row(scene, particles)
        rows.append({**row, **truth_row(recipe, scene, particles, contact)})
        print(markdown_row(rows[-1]), flush=True)
    return rows


def markdown_row(row: dict) -> str:
    objects = "; ".join(
        f"{k}: {o['particles']} p, volume {_ratio(o['volume_ratio'])}, CD0 {o['frame0_cd_mm2']:.0f}"
        for k, o in row["objects"].items()
    )
    cds = (
        f"diverged ({row['diverged']})"
        if "diverged" in row
        else f"{row['observed_cd']:,.0f} / {row['future_cd']:,.0f}"
    )
    return f"| {row['run']} | {row['grid']} | {row['variant']} | {objects} | {cds} |"


def _ratio(value: float | None) -> str:
    return "-" if value is None else f"{value:.2f}x"


def markdown(rows: list[dict]) -> str:
    head = (
        "| run | grid | particles from | per object: particles, volume / true, frame-0 "
        "Chamfer mm^2 | truth's observed / future Chamfer mm^2 |\n|---|---|---|---|---|\n"
    )
    return head + "\n".join(markdown_row(row) for row in rows) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("runs", nargs="+", type=Path, help="finished from-video run folders")
    parser.add_argument(
        "--variant", action="append", default=None, help='lifter options, "" = the run\'s own'
    )
    parser.add_argument("--device", default="cpu", help="simulator device for the rollouts")
    parser.add_argument("--contact", default=None, help="contact mode (default: the recipe's)")
    parser.add_argument(
        "--set",
        action="append",
        default=[],
        help="override of the run's recipe, e.g. simulator.cell_size=0.0125 "
        "(with simulator.grid=null, so that the cell size sets the grid)",
    )
    parser.add_argument("--out", type=Path, required=True, help="JSON file to write")
    parser.add_argument("--markdown", type=Path, default=None, help="also write the table")
    args = parser.parse_args(argv)
    if args.out.exists():
        raise SystemExit(f"--out {args.out}: exists; give a new file")
    variants = args.variant if args.variant is not None else [""]
    rows = []
    for run in args.runs:
        rows += measure_run(run, variants, device=args.device, contact=args.contact, sets=args.set)
    args.out.write_text(json.dumps({"rows": rows}, indent=2) + "\n")
    text = markdown(rows)
    if args.markdown:
        args.markdown.write_text(text)
    sys.stdout.write(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
