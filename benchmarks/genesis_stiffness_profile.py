"""How much the observed frames of a Genesis scene say about a body's stiffness.

Identification on Genesis scenes finds elastic and plasticine stiffnesses 2-10x off (docs/
RESULTS.md). This asks whether the data could tell: each solid body's Young's modulus E is
scaled by a factor (the other bodies and every other parameter at their true values, from
``gt/params.json``), the scene rolled out from Genesis's own frame-0 particles and initial
velocities by the model that reproduces Genesis best (``genesis_model_error.py``: the
corotated stress, single-field contact, grid 64), and the body's Chamfer against
``gt/points.npz`` scored over the observed and the future frames. Where the observed Chamfer
hardly changes between factors 0.5 and 2 while the future one does, no fit to the observed
frames can pin E down, and a wrong E shows only in the prediction.

    python benchmarks/genesis_stiffness_profile.py --scenes runs/genesis --out runs/stiffness \\
        --only E-E,E-P --device cpu
    python benchmarks/genesis_stiffness_profile.py --out runs/stiffness --report \\
        --write-results docs/RESULTS.md

Writes ``OUT/stiffness_profile.json`` (one row per scene, body and factor; a rerun skips the
rows already there), ``OUT/stiffness_profile.md`` and ``OUT/stiffness_profile.png`` (each
body's observed and future Chamfer against the factor). ``--report`` measures nothing: it
gathers every ``stiffness_profile.json`` under OUT (one process per scene may each have written
its own folder); ``--write-results FILE`` replaces the section "Stiffness profile on Genesis
scenes" of FILE and copies the plot next to it under ``img/``.
"""

from __future__ import annotations

import argparse
import datetime
import json
import shlex
import shutil
import sys
import time
from pathlib import Path

import torch
from genesis_identify import _device_name, _fill, find_scenes, replace_section
from genesis_model_error import LAW_MAPS, frame0_particles, gather_rows, true_params
from identify_suite import code_version

from mosiv_framework.errors import SimulationDiverged
from mosiv_framework.pipeline.evaluate import score
from mosiv_framework.pipeline.run import build_simulator, with_identified_laws
from mosiv_framework.recipes import load_recipe
from mosiv_framework.scene import read_scene
from mosiv_framework.types import ObjectParams, SimulationParams

FORMAT = "mosiv-genesis-stiffness-profile/1"
SECTION = "Stiffness profile on Genesis scenes"
#: where a new section goes: after "Model error on Genesis scenes", before this one
SECTION_BEFORE = "Choosing the stress on Genesis scenes"
PLOT = "genesis_stiffness_profile.png"
#: the scene materials whose stiffness is profiled (a sand's or liquid's E is not its main
#: parameter)
SOLIDS = ("elastic", "plasticine")
#: a factor-2 error in E that changes the observed Chamfer by less than this fraction is
#: called "not told apart" in the table
FLAT = 0.25


def scaled_stiffness(params: SimulationParams, body: int, factor: float) -> SimulationParams:
    """``params`` with body ``body``'s E multiplied by ``factor``."""
    objects = dict(params.objects)
    old = objects[body]
    values = {**old.values, "E": old.values["E"] * factor}
    objects[body] = ObjectParams(old.family, values)
    return SimulationParams(objects, params.initial_velocity, params.ground_friction, params.terms)


def measure_body(simulator, scene, particles, params, body: int, factor: float, emd: int) -> dict:
    """One rollout with body ``body``'s E scaled by ``factor``, scored; a divergence is a row
    that says so."""
    started = time.perf_counter()
    row = {"factor": factor}
    try:
        with torch.no_grad():
            traj = simulator.rollout(
                particles,
                scaled_stiffness(params, body, factor),
                world=scene.world,
                frames=scene.n_frames - 1,
            )
    except SimulationDiverged as exc:
        return {**row, "diverged": str(exc), "time_s": time.perf_counter() - started}
    blocks = score(
        traj, scene.gt_points(), observed_frames=scene.observed_frames, n_samples=emd, seed=0
    )
    mine = {b: blocks[b]["per_object"][body]["cd_mm2"] for b in ("observed", "future")}
    return {
        **row,
        "observed_cd": mine["observed"],
        "future_cd": mine["future"],
        "scene_observed_cd": blocks["observed"]["cd_mm2"],
        "scene_future_cd": blocks["future"]["cd_mm2"],
        "time_s": time.perf_counter() - started,
    }


def profile_scene(args, folder: Path, done: set, save) -> None:
    """Every solid body of the scene at ``folder`` and every factor not yet in ``done``."""
    overrides = [f"scene.path={folder}", f"simulator.grid={args.grid}"]
    overrides += [f"simulator.substeps={args.substeps}", f"simulator.contact={args.contact}"]
    if args.device:
        overrides.append(f"simulator.device={args.device}")
    recipe = load_recipe(args.recipe, overrides)
    scene = read_scene(folder)
    materials = {o.id: o.material for o in scene.objects}
    solids = [k for k, material in materials.items() if material in SOLIDS]
    if not solids:
        return
    simulator, _ = build_simulator(recipe.simulator)
    particles = with_identified_laws(frame0_particles(recipe, scene), LAW_MAPS[args.laws])
    params = true_params(scene, particles.materials)
    for body in solids:
        true_e = float(params.objects[body].values["E"])
        for factor in args.factors:
            if (folder.name, body, factor) in done:
                continue
            row = measure_body(simulator, scene, particles, params, body, factor, args.emd_samples)
            row.update(scene=folder.name, body=body, material=materials[body])
            row.update(true_E=true_e, model=model_name(args), device=_device_name(recipe))
            row["code"] = code_version()
            print(json.dumps(row), flush=True)
            save(row)


def model_name(args) -> str:
    return f"{args.laws}/{args.contact}/g{args.grid}/s{args.substeps}"


def measure_all(args) -> list[dict]:
    args.out.mkdir(parents=True, exist_ok=True)
    path = args.out / "stiffness_profile.json"
    data = json.loads(path.read_text()) if path.exists() else {"format": FORMAT, "rows": []}
    if data.get("format") != FORMAT:
        raise SystemExit(f"{path}: not a stiffness profile (format {data.get('format')!r})")
    done = {(r["scene"], r["body"], r["factor"]) for r in data["rows"]}

    def save(row: dict) -> None:
        data["rows"].append(row)
        path.write_text(json.dumps(data, indent=1))

    for name in find_scenes(args.scenes, args.only):
        profile_scene(args, args.scenes / name, done, save)
    return data["rows"]


def gather(out: Path) -> list[dict]:
    return gather_rows(out, "stiffness_profile.json", FORMAT, "a stiffness profile")


# --------------------------------------------------------------------------------------------
# the table and the plot


def by_body(rows: list[dict]) -> dict[tuple[str, str, int], dict[float, dict]]:
    """(model, scene, body) -> factor -> row, in model, scene and body order."""
    out: dict[tuple[str, str, int], dict[float, dict]] = {}
    for r in sorted(rows, key=lambda r: (r["model"], r["scene"], r["body"], r["factor"])):
        out.setdefault((r["model"], r["scene"], r["body"]), {})[r["factor"]] = r
    return out


def body_summary(curve: dict[float, dict]) -> dict:
    """The factor that fits the observed frames best, and how much a factor-2 error in E
    changes the observed and the future Chamfer (the larger of the two sides, relative to the
    true E's; None where a side is missing or diverged)."""
    ok = {f: r for f, r in curve.items() if "diverged" not in r}
    best = min(ok, key=lambda f: ok[f]["observed_cd"]) if ok else None
    out = {"best_factor": best}
    for block in ("observed", "future"):
        base = ok.get(1.0)
        sides = [ok.get(0.5), ok.get(2.0)]
        if base is None or any(s is None for s in sides) or base[f"{block}_cd"] <= 0:
            out[f"{block}_change"] = None
            continue
        ref = base[f"{block}_cd"]
        out[f"{block}_change"] = max(abs(s[f"{block}_cd"] - ref) / ref for s in sides)
    return out


def _num(value) -> str:
    if value is None:
        return "-"
    return f"{value:,.0f}" if abs(value) >= 100 else f"{value:.3g}"


def _cell(row: dict | None, block: str) -> str:
    if row is None:
        return ""
    return "diverged" if "diverged" in row else _num(row[f"{block}_cd"])


def body_lines(rows: list[dict]) -> list[str]:
    """Per model, body and block: the body's Chamfer at every factor, the factor that fits
    the observed frames best and the change a factor-2 error makes."""
    factors = sorted({r["factor"] for r in rows})
    heads = " | ".join(f"x{f:g}" for f in factors)
    lines = [
        f"| model | scene | body | material | true E Pa | block | {heads} | best x | "
        "change at x0.5 / x2 |",
        "|---|---|---|---|---:|---|" + "---:|" * len(factors) + "---:|---:|",
    ]
    for (model, scene, body), curve in by_body(rows).items():
        first = next(iter(curve.values()))
        s = body_summary(curve)
        for block in ("observed", "future"):
            cells = [_cell(curve.get(f), block) for f in factors]
            change = s[f"{block}_change"]
            best = f"x{s['best_factor']:g}" if block == "observed" and s["best_factor"] else ""
            lines.append(
                f"| {model} | {scene} | {body} | {first['material']} | {first['true_E']:,.0f} | "
                f"{block} | " + " | ".join(cells) + f" | {best} | "
                f"{'-' if change is None else f'{100 * change:.0f} %'} |"
            )
    return lines


def model_lines(rows: list[dict]) -> list[str]:
    """Per model: on how many bodies the true E fits the observed frames best, and on how
    many a factor-2 error changes the observed Chamfer by less than FLAT."""
    lines = [
        "| model | bodies | true E fits the observed frames best | best factor, each body | "
        f"factor-2 error changes the observed Chamfer by < {100 * FLAT:.0f} % |",
        "|---|---:|---:|---|---:|",
    ]
    curves = by_body(rows)
    for model in dict.fromkeys(key[0] for key in curves):
        summaries = [body_summary(c) for key, c in curves.items() if key[0] == model]
        best = [s["best_factor"] for s in summaries]
        flat = sum(
            s["observed_change"] is not None and s["observed_change"] < FLAT for s in summaries
        )
        listed = ", ".join("-" if b is None else f"x{b:g}" for b in best)
        lines.append(
            f"| {model} | {len(summaries)} | {sum(b == 1.0 for b in best)} | {listed} | {flat} |"
        )
    return lines


def markdown(rows: list[dict]) -> str:
    lines = [*model_lines(rows), "", *body_lines(rows), "", "(Chamfer of the body in mm^2.)"]
    return "\n".join(lines) + "\n"


def plot(rows: list[dict], path: Path) -> None:
    """Per model (a row of panels), each body's observed and future Chamfer against the
    factor on E."""
    import matplotlib
    import matplotlib.ticker

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    curves = by_body(rows)
    models = list(dict.fromkeys(key[0] for key in curves))
    fig, axes = plt.subplots(
        len(models), 2, figsize=(11, 3.8 * len(models)), sharex=True, squeeze=False
    )
    for row_axes, model in zip(axes, models):
        for (m, scene, body), curve in curves.items():
            ok = [(f, r) for f, r in sorted(curve.items()) if m == model and "diverged" not in r]
            if not ok:
                continue
            label = f"{scene} #{body} ({ok[0][1]['material']})"
            for ax, block in zip(row_axes, ("observed", "future")):
                values = [r[f"{block}_cd"] for _, r in ok]
                ax.plot([f for f, _ in ok], values, marker="o", label=label)
        factors = sorted({r["factor"] for r in rows})
        for ax, block in zip(row_axes, ("observed", "future")):
            ax.set_xscale("log")
            ax.set_yscale("log")
            ax.set_xticks(factors, [f"{f:g}" for f in factors])
            ax.xaxis.set_minor_locator(matplotlib.ticker.NullLocator())
            ax.axvline(1.0, color="grey", lw=0.8)
            ax.set_xlabel("E / true E")
            ax.set_ylabel("Chamfer of the body (mm^2)")
            ax.set_title(f"{block} frames, model {model}", fontsize=9)
        row_axes[1].legend(fontsize=6, loc="best")
    fig.suptitle(
        "Genesis scenes (mosiv data suite --source genesis --ranges wide): the true "
        "parameters rolled out by warp-mpm, one body's E scaled",
        fontsize=9,
    )
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def section_text(rows: list[dict], *, command: str, report: str, data: str | None = None) -> str:
    machines = sorted({str(r.get("device", "not recorded")) for r in rows})
    codes = sorted({str(r.get("code", "not recorded")) for r in rows})
    models = sorted({r["model"] for r in rows})
    intro = (
        "Each elastic or plasticine body's Young's modulus scaled by a factor, every other "
        "parameter at its true value (gt/params.json), Genesis's own frame-0 particles and "
        "initial velocities rolled out by warp-mpm with each model named (stress law / contact "
        f"/ grid / substeps: {', '.join(models)}), and the body's Chamfer "
        "against gt/points.npz over the observed and the future frames: how much the observed "
        "frames say about E."
    )
    return "\n".join(
        [
            f"## {SECTION}",
            "",
            _fill(intro),
            "",
            f"- Command: `{command}`, then `{report}`",
            f"- Machine: {', '.join(machines)}. Date {datetime.date.today().isoformat()}. "
            f"Code {', '.join(codes)}.",
            "- Data: scenes of the Genesis suite of [Identification on Genesis scenes]"
            "(#identification-on-genesis-scenes) (`mosiv data suite SCENES --source genesis "
            "--ranges wide`, seeds 0-12), their solid bodies"
            + (f"; the rows in `{data}`." if data else "."),
            "",
            markdown(rows),
            f"![observed and future Chamfer against the factor on E](img/{PLOT})",
            "",
        ]
    )


def parse_args(argv: list[str]):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", type=Path, help="suite folder (not needed with --report)")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--recipe", type=Path, default=Path("recipes/genesis_oracle.yaml"))
    ap.add_argument("--only", help="comma-separated scene names")
    ap.add_argument("--factors", nargs="+", type=float, default=[0.1, 0.25, 0.5, 1, 2, 4, 10])
    ap.add_argument("--laws", default="corotated", choices=sorted(LAW_MAPS))
    ap.add_argument("--contact", default="single_field")
    ap.add_argument("--grid", type=int, default=64)
    ap.add_argument("--substeps", type=int, default=400)
    ap.add_argument("--device", default=None, help="simulator device (default: the recipe's)")
    ap.add_argument("--emd-samples", type=int, default=256)
    ap.add_argument("--report", action="store_true", help="gather the rows under --out")
    ap.add_argument("--measured-with", default=None, help="the measuring command, for --report")
    ap.add_argument("--write-results", type=Path, default=None, help="markdown file to update")
    args = ap.parse_args(argv)
    if not args.report and args.scenes is None:
        ap.error("--scenes is required unless --report")
    if 1.0 not in args.factors:
        ap.error("--factors must include 1 (the true E)")
    return args


def shown_args(argv: list[str]) -> list[str]:
    """``argv`` as a results file shows it: folders as SCENES and OUT (no machine paths),
    without the quoted measuring command."""
    shown, skip = [], False
    for i, arg in enumerate(argv):
        if skip:
            skip = False
            continue
        if arg == "--measured-with":
            skip = True
            continue
        before = argv[i - 1] if i else ""
        if before == "--write-results" and Path(arg).is_absolute():
            arg = str(Path(*Path(arg).parts[-2:]))  # docs/RESULTS.md, not where it lies
        shown.append({"--scenes": "SCENES", "--out": "OUT"}.get(before, arg))
    return shown


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    args = parse_args(argv)
    rows = gather(args.out) if args.report else measure_all(args)
    (args.out / "stiffness_profile.md").write_text(markdown(rows))
    plot(rows, args.out / "stiffness_profile.png")
    print(markdown(rows))
    if args.write_results is not None:
        command = "python benchmarks/genesis_stiffness_profile.py " + shlex.join(shown_args(argv))
        data = None if args.out.is_absolute() else args.out.as_posix()
        body = section_text(rows, command=args.measured_with or command, report=command, data=data)
        text = args.write_results.read_text() if args.write_results.is_file() else "# Results\n"
        new = replace_section(text, body, title=SECTION, before=SECTION_BEFORE)
        args.write_results.write_text(new)
        image = args.write_results.parent / "img" / PLOT
        image.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(args.out / "stiffness_profile.png", image)
    return 0


if __name__ == "__main__":
    sys.exit(main())
