"""A scene through a capture rig and back: does the import cost accuracy?

The scene of a from-video recipe is run directly, then written as a rig delivers it
(``mosiv data capture``: centimetres, y up, a barrel lens, one camera starting late, H.264,
a clean plate per camera),
imported back (``mosiv data import``: materials, units/up and the late camera's offset given:
the objects are thrown and move from the first frame, so there is no motion onset to estimate
offsets from; the ground as the scene has it, lens undone, masks from the classical segmenter, domain from the
visual hull) and run again with the same recipe. The capture's reference ground truth is carried
into the imported frame (``mosiv_framework.capture.reference``), so both runs are scored the same
way. Reported per run: identified E of every object, its relative error to the truth and the
imported run's E relative to the direct run's (E is frame-free), and the future Chamfer distance
(mm^2) against each scene's own ground truth.

Paper size (GPU; the targets: E within 10 % and future CD within 20 % of the direct run)::

    python benchmarks/capture_roundtrip.py --out runs/capture_roundtrip

CPU smoke run (the tiny scene and short schedule of tests/test_capture_roundtrip.py)::

    python benchmarks/capture_roundtrip.py --quick --out runs/capture_roundtrip

In parts, e.g. on a GPU machine whose calls are limited in time (the scene first, then the rest
at once on different GPUs, then the comparison; a part run again reuses finished runs)::

    python benchmarks/capture_roundtrip.py --out OUT --part direct
    python benchmarks/capture_roundtrip.py --out OUT --part reseeded --spread-seed 1
    python benchmarks/capture_roundtrip.py --out OUT --part capture
    python benchmarks/capture_roundtrip.py --out OUT --part imported
    python benchmarks/capture_roundtrip.py --out OUT --merge

Writes OUT/capture_roundtrip.json and prints a table; OUT must be new or empty for the whole
round trip.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from genesis_identify import _portable

from mosiv_framework.logs import configure_logging, level_from_flags

ROOT = Path(__file__).resolve().parents[1]
PAPER_RECIPE = ROOT / "recipes" / "video_paper.yaml"
QUICK_RECIPE = ROOT / "recipes" / "video_quickstart.yaml"

#: the short schedule of tests/test_pipeline_video.py: the whole run in about a minute on 2 cores
QUICK = [
    "scene.source.n_frames=8",
    "reconstructor.iterations=300",
    "reconstructor.motion_init_iterations=200",
    "reconstructor.densify_from=50",
    "reconstructor.densify_until=250",
    "identify.velocity_iterations=5",
    "identify.param_iterations=5",
    "evaluate.emd_samples=128",
    "evaluate.video_size=64",
    "evaluate.render_videos=false",
]
#: at 48 px an object covers a few pixels: no morphological cleanup, no minimum hull size
QUICK_SEGMENTER = ["open_px=0", "close_px=0", "min_voxels=1"]
#: domain margin of the import, a fraction of the objects' hull size (see capture_and_import)
MARGIN = 0.7
#: the rig: units, up axis, lens (k1, k2: a mild barrel lens) and one camera starting late
UNITS, UP, LENS, LATE = "cm", "y", "-0.05,0.01", ("cam_01", 1)


def run_recipe(recipe_path: Path, scene: Path, run: Path, overrides: list[str]) -> dict:
    """``mosiv run`` of ``recipe_path`` on ``scene`` into ``run``; returns metrics.json."""
    from mosiv_framework.pipeline import run_pipeline
    from mosiv_framework.recipes import load_recipe

    recipe = load_recipe(recipe_path, [f"scene.path={scene}", f"output.dir={run}", *overrides])
    return run_pipeline(recipe, run_dir=run)


def segmenter_order(scene, frame: int) -> list:
    """The scene's objects in the order the classical segmenter numbers them: by world x at the
    first imported frame (the rig frame keeps the x axis for up = y or z), so that the materials
    given to the import name the right objects."""
    points = scene.gt_points()
    return sorted(scene.objects, key=lambda o: float(points[o.id][frame, :, 0].mean()))


def capture_and_import(
    scene: Path,
    out: Path,
    segmenter: list[str] = (),
    late: int = LATE[1],
    lens: str = LENS,
    crf: int | None = None,
    pixel_format: str | None = None,
    plate: bool = True,
    late_cameras: str = "keep",
) -> Path:
    """Write ``scene`` as a rig's capture into out/capture, import it into out/imported with
    the reference gt attached; ``late``: frames the late camera (LATE) misses at the start;
    ``late_cameras``: the import's ``--late-cameras`` (trim: every camera drops those frames;
    drop: the late camera is left out and the others keep every frame; keep: every camera and
    frame, the late camera declared as starting late); ``lens``: k1,k2 of the
    rig's lens ("0,0": none); ``crf``: H.264 quality and ``pixel_format`` its chroma (None: the
    capture's defaults); ``plate``: the rig records a clean plate per camera, which the
    import's segmenter takes as its background (without one it estimates the background as
    each pixel's median, which is the object wherever an object rests for most of the clip).
    Returns the imported scene."""
    from mosiv_framework.capture.reference import attach_reference
    from mosiv_framework.cli.main import main
    from mosiv_framework.scene import read_scene

    original = read_scene(scene)
    capture, imported = out / "capture", out / "imported"
    argv = ["data", "capture", str(scene), str(capture), "--units", UNITS, "--up", UP]
    argv += [f"--distortion={lens}", "--offsets", f"{LATE[0]}={late}", "--with-reference"]
    argv += [] if crf is None else ["--crf", str(crf)]
    argv += [] if pixel_format is None else ["--pixel-format", pixel_format]
    argv += ["--background-plate"] if plate else []
    if main(argv) != 0:
        raise RuntimeError(f"mosiv {' '.join(argv)} failed")
    shift = frame_shift(late, late_cameras)
    argv = import_argv(
        capture,
        imported,
        materials=",".join(o.material for o in segmenter_order(original, shift)),
        ground_height=original.ground_height,
        observed=original.observed_frames - shift,
        late=late,
        late_cameras=late_cameras,
        segmenter=segmenter,
    )
    if main(argv) != 0:
        raise RuntimeError(f"mosiv {' '.join(argv)} failed")
    attach_reference(capture, imported)
    return imported


def frame_shift(late: int, late_cameras: str) -> int:
    """The scene's frame that the import's frame 0 shows: the late camera's missing frames
    when every camera drops them (trim), 0 when that camera is left out (drop) or declared as
    starting late (keep)."""
    return late if late_cameras == "trim" else 0


def import_argv(
    capture: Path,
    imported: Path,
    *,
    materials: str,
    ground_height: float | None,
    observed: int,
    late: int,
    late_cameras: str,
    segmenter: list[str],
) -> list[str]:
    """The ``mosiv data import`` command line of the round trip."""
    argv = ["data", "import", str(imported), "--recording", str(capture), "--units", UNITS]
    argv += ["--up", UP, "--materials", materials, "--offsets", f"{LATE[0]}:{-late}"]
    argv += ["--late-cameras", late_cameras]
    # the ground as the scene has it (a rig measures its floor): none, or the plane y = height
    argv += ["--ground", "none" if ground_height is None else f"y={ground_height * 100.0}"]
    # the observed window ends at the original's last observed frame
    argv += ["--observed", str(observed)]
    argv += [f"--segmenter-option={option}" for option in segmenter]
    # the visual hull is tight around the objects (0.41 m for the quick scene): a margin of
    # 0.7 of its size brings the domain near the synthetic scene's 0.8 m, so that a recipe
    # giving a grid count (the quick one) simulates the import at about the direct run's
    # cell; recipes/video_paper.yaml gives its cell in metres (simulator.cell_size), which
    # holds whatever the domain (at paper size the hull made it 1.08 m)
    argv += ["--margin", str(MARGIN)]
    return argv


def mask_iou(scene_dir: Path, imported_dir: Path, shift: int) -> dict:
    """How well the import's masks (the segmenter's) cover the scene's own: per object
    (original id), the IoU of each frame pooled over the cameras the import kept that recorded
    the frame, its lowest
    and mean over the frames, and the mask area relative to the scene's (mean over frames);
    ``shift``: the scene's frame the import's frame 0 shows (``frame_shift``)."""
    from mosiv_framework.scene import read_scene

    original, imported = read_scene(scene_dir), read_scene(imported_dir)
    gt = json.loads((imported_dir / "gt" / "params.json").read_text())
    ids = {int(k): int(v) for k, v in gt["reference"]["object_ids"].items()}
    out = {}
    for mine, theirs in sorted(ids.items()):
        ious, areas = [], []
        for t in range(imported.n_frames):
            inter = union = area = area_ref = 0
            for cam in (c.id for c in imported.cameras_at(t)):
                a = imported.mask(cam, t) == mine
                b = original.mask(cam, t + shift) == theirs
                inter, union = inter + int((a & b).sum()), union + int((a | b).sum())
                area, area_ref = area + int(a.sum()), area_ref + int(b.sum())
            ious.append(inter / max(union, 1))
            areas.append(area / max(area_ref, 1))
        out[str(theirs)] = {
            "iou_min": min(ious),
            "iou_mean": sum(ious) / len(ious),
            "area_ratio_mean": sum(areas) / len(areas),
        }
    return out


def summary(metrics: dict) -> dict:
    """Identified E and its error per object, and the future Chamfer distance (mm^2)."""
    errors = metrics.get("param_error") or {}
    objects = {}
    for oid, obj in metrics["params"]["objects"].items():
        e_error = errors.get(oid, {}).get("E", {})
        objects[oid] = {"E": obj["params"].get("E"), "E_rel_error": e_error.get("rel_error")}
    return {"objects": objects, "future_cd_mm2": metrics["future"]["cd_mm2"]}


def compare(direct: dict, imported: dict) -> dict:
    """Imported against direct: E ratio - 1 per object and the future CD ratio - 1."""
    e_rel = {}
    for oid, obj in direct["objects"].items():
        e_direct, e_imported = obj["E"], imported["objects"][oid]["E"]
        if e_direct is not None and e_imported is not None:
            e_rel[oid] = abs(e_imported / e_direct - 1.0)
    cd_rel = imported["future_cd_mm2"] / direct["future_cd_mm2"] - 1.0
    return {"E_rel_to_direct": e_rel, "future_cd_rel_to_direct": cd_rel}


#: the parts of a round trip, in order; each one's result lands in OUT/parts/PART.json
PARTS = ("direct", "reseeded", "capture", "imported")


@dataclass(frozen=True)
class Rig:
    """How the capture is written: frames the late camera (LATE) misses, the lens (k1,k2;
    "0,0": none), H.264 quality and chroma (None: the capture's defaults)."""

    late: int = LATE[1]
    lens: str = LENS
    crf: int | None = None
    pixel_format: str | None = None
    plate: bool = True
    late_cameras: str = "keep"

    def record(self) -> dict:
        return {
            "units": UNITS,
            "up": UP,
            "distortion": self.lens,
            "crf": self.crf,
            "pixel_format": self.pixel_format,
            "late": {LATE[0]: self.late},
            "background_plate": self.plate,
            "late_cameras": self.late_cameras,
        }


def _finished_run(recipe: Path, scene: Path, run: Path, overrides: list[str]) -> dict:
    """run_recipe, or the metrics of a run that already finished there: a part that is run
    again (after a lost GPU machine, say) never repeats finished work."""
    metrics = run / "metrics.json"
    if metrics.is_file():
        return json.loads(metrics.read_text())
    return run_recipe(recipe, scene, run, overrides)


def run_part(
    part: str,
    out: Path,
    recipe: Path,
    overrides: list[str],
    segmenter: list[str] = (),
    spread_seed: int | None = None,
    rig: Rig = Rig(),
) -> dict:
    """One part of the round trip into ``out``; writes and returns out/parts/PART.json.

    "direct" and "reseeded" run the scene (generated by the recipe into out/scene if missing),
    "capture" writes and imports it (no simulator run), "imported" runs the import. Once the
    scene exists, "direct", "reseeded" and "capture" + "imported" are independent: they may run
    at the same time, on different GPUs."""
    if part not in PARTS:
        raise ValueError(f"part {part!r}: not one of {', '.join(PARTS)}")
    scene, imported_scene = out / "scene", out / "imported"
    if part == "direct":
        result = summary(_finished_run(recipe, scene, out / "run_direct", overrides))
    elif part == "reseeded":
        if spread_seed is None:
            raise ValueError("part 'reseeded' needs a spread seed (--spread-seed)")
        reseeded = [*overrides, f"reconstructor.seed={spread_seed}"]
        again = summary(_finished_run(recipe, scene, out / "run_direct_reseeded", reseeded))
        result = {"reconstructor_seed": spread_seed, "direct": again}
    elif part == "capture":
        if not (imported_scene / "scene.json").is_file():
            capture_and_import(
                scene,
                out,
                segmenter,
                rig.late,
                rig.lens,
                rig.crf,
                rig.pixel_format,
                rig.plate,
                rig.late_cameras,
            )
        result = {
            "rig": rig.record(),
            "segmenter_options": list(segmenter),
            "mask_iou": mask_iou(scene, imported_scene, frame_shift(rig.late, rig.late_cameras)),
        }
    else:
        if not (imported_scene / "scene.json").is_file():
            raise FileNotFoundError(f"{imported_scene}: no import yet; run part 'capture' first")
        result = summary(_finished_run(recipe, imported_scene, out / "run_imported", overrides))
        # the import numbers objects its own way: report them under the original ids
        gt = json.loads((imported_scene / "gt" / "params.json").read_text())
        ids = gt["reference"]["object_ids"]
        result["objects"] = {str(ids[k]): v for k, v in result["objects"].items()}
    (out / "parts").mkdir(exist_ok=True)
    (out / "parts" / f"{part}.json").write_text(json.dumps(result, indent=2) + "\n")
    return result


def merge(out: Path, recipe: Path, overrides: list[str]) -> dict:
    """The comparison from the finished parts in out/parts (FileNotFoundError naming a
    missing part)."""

    def part(name: str, required: bool = True) -> dict | None:
        path = out / "parts" / f"{name}.json"
        if not path.is_file():
            if required:
                raise FileNotFoundError(f"{path}: part {name!r} has not finished")
            return None
        return json.loads(path.read_text())

    direct, capture, imported = part("direct"), part("capture"), part("imported")
    spread = part("reseeded", required=False)
    if spread is not None:
        spread["comparison"] = compare(direct, spread["direct"])
    return {
        "recipe": _portable(str(recipe)),  # a results file names no machine's paths
        "overrides": overrides,
        **capture,
        "direct": direct,
        "imported": imported,
        "comparison": compare(direct, imported),
        "spread": spread,
    }


def roundtrip(
    out: Path,
    recipe: Path,
    overrides: list[str],
    segmenter: list[str] = (),
    spread_seed: int | None = None,
    rig: Rig = Rig(),
) -> dict:
    """The whole comparison into ``out``, its parts one after another (direct scene and run,
    the reseeded run where ``spread_seed`` is given, capture and import, imported run).

    ``spread_seed``: also run the direct scene again with this reconstructor seed
    (``run_direct_reseeded``): how far two direct runs differ is the yardstick for how far the
    imported run may differ from the direct one (at small sizes from-video identification
    varies with the seed more than the targets allow)."""
    times = {}
    for part in PARTS:
        if part == "reseeded" and spread_seed is None:
            continue
        t0 = time.perf_counter()
        run_part(part, out, recipe, overrides, segmenter, spread_seed, rig)
        times[part] = time.perf_counter() - t0
    return {**merge(out, recipe, overrides), "time_s": times}


def table(result: dict) -> str:
    rows = ["object  E direct      E imported    E rel. diff   E err direct  E err imported"]
    for oid, d in result["direct"]["objects"].items():
        i = result["imported"]["objects"][oid]
        rel = result["comparison"]["E_rel_to_direct"].get(oid)
        cells = [d["E"], i["E"], rel, d["E_rel_error"], i["E_rel_error"]]
        rows.append(f"{oid:>6}  " + "  ".join(_cell(c) for c in cells))
    cd_d, cd_i = result["direct"]["future_cd_mm2"], result["imported"]["future_cd_mm2"]
    rel = result["comparison"]["future_cd_rel_to_direct"]
    rows.append(f"future CD (mm^2): direct {cd_d:.4g}, imported {cd_i:.4g} ({rel:+.1%})")
    spread = result.get("spread")
    if spread:
        e_rel = spread["comparison"]["E_rel_to_direct"]
        cd_again = spread["direct"]["future_cd_mm2"]
        rows.append(
            f"direct again (reconstructor seed {spread['reconstructor_seed']}): E rel. diff "
            + ", ".join(f"{oid} {v:.3g}" for oid, v in e_rel.items())
            + f"; future CD {cd_again:.4g} ({spread['comparison']['future_cd_rel_to_direct']:+.1%})"
        )
    return "\n".join(rows)


def _cell(value) -> str:
    return f"{'-':>12}" if value is None else f"{value:>12.4g}"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, required=True, help="new or empty folder")
    parser.add_argument(
        "--quick", action="store_true", help="tiny CPU version: video_quickstart, short schedule"
    )
    parser.add_argument("--recipe", type=Path, help="a from-video recipe (default by --quick)")
    parser.add_argument(
        "--spread-seed",
        type=int,
        help="also run the direct scene with this reconstructor seed: the run-to-run spread "
        "that the import's difference is measured against",
    )
    parser.add_argument(
        "--late-frames",
        type=int,
        default=LATE[1],
        help=f"frames {LATE[0]} starts late (the import drops them from every camera; 0: none)",
    )
    parser.add_argument("--lens", default=LENS, help=f"k1,k2 of the rig's lens (default {LENS})")
    parser.add_argument("--crf", type=int, help="H.264 quality of the capture (0: lossless)")
    parser.add_argument("--pixel-format", help="H.264 chroma of the capture: yuv420p or yuv444p")
    parser.add_argument(
        "--late-cameras",
        choices=("trim", "drop", "keep"),
        default="keep",
        help="the import's --late-cameras: every camera and frame kept, the late camera "
        "declared as starting late (keep, default), every camera drops the late camera's "
        "missing frames (trim), or the late camera is left out (drop)",
    )
    parser.add_argument(
        "--no-plate",
        action="store_true",
        help="the rig records no clean plate: the segmenter estimates the background itself",
    )
    parser.add_argument(
        "--part",
        choices=PARTS,
        help="run only this part (OUT may hold others; a finished run is not run again); the "
        "scene must exist or be generated first, by 'direct'",
    )
    parser.add_argument(
        "--merge", action="store_true", help="compare the finished parts in OUT (no run)"
    )
    parser.add_argument("overrides", nargs="*", help="extra recipe overrides key=value")
    args = parser.parse_args(argv)
    # the pipeline's progress (stages, global candidates) is logged at INFO: show it
    configure_logging(level_from_flags())
    whole = args.part is None and not args.merge
    if whole and args.out.exists() and any(args.out.iterdir()):
        parser.error(f"--out {args.out}: not empty; give a new or empty folder")
    recipe = args.recipe or (QUICK_RECIPE if args.quick else PAPER_RECIPE)
    overrides = (QUICK if args.quick else []) + list(args.overrides)
    args.out.mkdir(parents=True, exist_ok=True)
    segmenter = QUICK_SEGMENTER if args.quick else []
    rig = Rig(
        args.late_frames,
        args.lens,
        args.crf,
        args.pixel_format,
        not args.no_plate,
        args.late_cameras,
    )
    if args.part is not None:
        result = run_part(args.part, args.out, recipe, overrides, segmenter, args.spread_seed, rig)
        print(json.dumps(result, indent=2))
        return 0
    if args.merge:
        result = merge(args.out, recipe, overrides)
    else:
        result = roundtrip(args.out, recipe, overrides, segmenter, args.spread_seed, rig)
    (args.out / "capture_roundtrip.json").write_text(json.dumps(result, indent=2) + "\n")
    print(table(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
