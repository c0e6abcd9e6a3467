"""``mosiv data synth|suite|show|check``: make scenes, the standard benchmark, previews; validate.

- ``synth`` makes one scene with a registered SceneSource. Common settings are real flags that
  map onto the source's option names (``SOURCE_FLAGS``); anything else passes as key=value.
- ``suite`` makes the benchmark of the paper's tables: one scene per material pair (plus a few
  three-object scenes), one folder each, an index ``suite.json``; an interrupted suite resumes.
- ``show`` writes a contact sheet (cameras x frames) and one GIF per camera of a scene folder.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import shutil
import time
from pathlib import Path
from typing import Any

logger = logging.getLogger(__name__)

# flag (argparse dest) -> the option name every scene source uses for that setting
SOURCE_FLAGS: dict[str, str] = {
    "materials": "materials",
    "objects": "n_objects",
    "seed": "seed",
    "resolution": "resolution",
    "cameras": "n_cameras",
    "frames": "n_frames",
    "conceal": "conceal",
    "ranges": "ranges",
}
# material abbreviations of the paper's tables (section 4, table captions): E elastic,
# P plastic(ine), F fluid -- the appendix's Newtonian fluid, Genesis' "Liquid" -- and S sand
ABBREVIATIONS: dict[str, str] = {"E": "elastic", "P": "plasticine", "F": "newtonian", "S": "sand"}
# every material pairing of the paper's tables, then three-object scenes mixing the families
SUITE_SCENES: tuple[str, ...] = (
    "E-P", "E-F", "E-S", "P-F", "P-S", "F-S", "E-E", "P-P", "F-F", "S-S",
    "E-P-F", "E-P-S", "P-F-S",
)  # fmt: skip
SUITE_FORMAT = "mosiv-suite/1"
# contact sheet layout (pixels): gap between tiles, left label column, top label row
SHEET_GAP = 2
SHEET_LABEL_W = 48
SHEET_LABEL_H = 14
# mask overlay colours by object id (1..K, cycling): distinct, saturated sRGB
OVERLAY_COLORS = ((230, 25, 75), (60, 180, 75), (0, 130, 200), (245, 130, 48), (145, 30, 180))
OVERLAY_ALPHA = 0.5


class _KeyValueParser(argparse.ArgumentParser):
    """An ArgumentParser that also takes key=value options after the flags.

    argparse fills the ``options`` positional (nargs="*") right after OUT_DIR, so key=value
    words that follow a flag would be "unrecognized"; they are collected into ``options`` here.
    """

    def parse_known_args(self, args=None, namespace=None):
        namespace, extras = super().parse_known_args(args, namespace)
        if hasattr(namespace, "options"):
            key_values = [a for a in extras if "=" in a and not a.startswith("-")]
            namespace.options = list(namespace.options or []) + key_values
            extras = [a for a in extras if a not in key_values]
        return namespace, extras


def add_parser(sub) -> None:
    p = sub.add_parser("data", help="generate, check or preview scenes (mosiv-scene/1)")
    dsub = p.add_subparsers(
        dest="data_command", metavar="ACTION", required=True, parser_class=_KeyValueParser
    )
    check = dsub.add_parser("check", help="validate a scene folder and list every problem")
    check.add_argument("scene_dir")
    check.set_defaults(handler=run_check)

    synth = dsub.add_parser("synth", help="generate a scene with a registered scene source")
    synth.add_argument("out_dir", help="folder to write the scene into (new or empty)")
    _add_source_flags(synth)
    synth.add_argument(
        "--materials",
        help="material family per object, comma-separated (e.g. elastic,sand); sets --objects",
    )
    synth.add_argument("--objects", type=int, help="number of objects (2 or 3 for synth)")
    synth.add_argument(
        "--conceal",
        action="append",
        default=[],
        metavar="KIND[:param=value,...]",
        help="add physics the scene does not declare (repeatable): linear_drag, quadratic_drag, "
        "wind, gravity, ground_friction; e.g. --conceal wind:acceleration=1.5,0,0",
    )
    synth.set_defaults(handler=run_synth)

    suite = dsub.add_parser(
        "suite", help="generate the standard benchmark: every material pair of the paper's tables"
    )
    suite.add_argument("out_dir", help="folder of the suite (created; an existing one resumes)")
    _add_source_flags(suite)
    suite.add_argument(
        "--only",
        help=f"comma-separated subset of the scenes {','.join(SUITE_SCENES)} "
        "(E elastic, P plasticine, F newtonian fluid, S sand)",
    )
    from mosiv_framework.scale.flags import add_scale_flags

    add_scale_flags(suite, "scenes")
    suite.set_defaults(handler=run_suite)

    show = dsub.add_parser("show", help="contact sheet PNG and one GIF per camera of a scene")
    show.add_argument("scene_dir")
    show.add_argument("--out", help="output folder (default: SCENE_DIR/preview)")
    show.add_argument("--masks", action="store_true", help="overlay the instance masks in colour")
    show.add_argument(
        "--step", type=int, default=1, help="contact sheet: every STEP-th frame (default 1)"
    )
    show.set_defaults(handler=run_show)
    from mosiv_framework.cli.export import add_capture_parser

    add_capture_parser(dsub)


def _add_source_flags(p) -> None:
    p.add_argument("--source", default="synth", help="registered scene source (default: synth)")
    p.add_argument("--seed", type=int, help="random seed of the scene(s)")
    p.add_argument(
        "--ranges",
        choices=("paper", "wide"),
        help="material parameter ranges: paper (the paper's benchmark, default) or wide "
        "(decades of stiffness, yield stress and viscosity)",
    )
    p.add_argument("--resolution", type=int, help="image width = height (pixels)")
    p.add_argument("--cameras", type=int, help="number of cameras")
    p.add_argument(
        "--frames", type=int, help="number of frames (observed frames default to half of them)"
    )
    p.add_argument("options", nargs="*", help="further source options as key=value")


def run_check(args) -> int:
    from mosiv_framework.scene.check import run_check as check

    return check(Path(args.scene_dir))


# ------------------------------------------------------------------------------------ synth
def source_options(source: str, flags: dict[str, Any], dotlist: list[str]) -> dict[str, Any]:
    """Options for scene source ``source`` from CLI flags (``SOURCE_FLAGS`` names, None = not
    given) and key=value strings; raises ConfigError naming flags the source cannot take.

    ``--materials`` also sets ``n_objects`` (unless ``--objects`` is given) and ``--frames``
    sets ``observed_frames`` to half the frames (the paper observes 15 of 30) unless given.
    """
    from omegaconf import OmegaConf

    from mosiv_framework.errors import ConfigError
    from mosiv_framework.registry import get_registry

    bad = [o for o in dotlist if "=" not in o]
    if bad:
        raise ConfigError([f"option {o!r} is not of the form key=value" for o in bad])
    options: dict[str, Any] = OmegaConf.to_container(OmegaConf.from_dotlist(dotlist))
    component = get_registry().get("scene_source", source)
    valid = _option_names(component)
    given = {k: v for k, v in flags.items() if v not in (None, [], "")}
    problems = []
    for flag, value in given.items():
        key = SOURCE_FLAGS[flag]
        if key not in valid:
            problems.append(
                f"--{flag}: scene source {source!r} has no option {key!r}; "
                f"its options: {', '.join(sorted(valid)) or 'none'}"
            )
        elif key in options:
            problems.append(f"--{flag} and {key}=... both given; give one")
        else:
            options[key] = value
    if problems:
        raise ConfigError(problems)
    if "materials" in given and "objects" not in given and "n_objects" in valid:
        options.setdefault("n_objects", len([m for m in given["materials"].split(",") if m]))
    if "frames" in given and "observed_frames" in valid:
        options.setdefault("observed_frames", max(1, given["frames"] // 2))
    return options


def _option_names(component) -> set[str]:
    return {f.name for f in dataclasses.fields(component.options)} if component.options else set()


def _flags(args, names) -> dict[str, Any]:
    return {n: getattr(args, n, None) for n in names}


def run_synth(args) -> int:
    from mosiv_framework.cli.stages import check_writable_folder
    from mosiv_framework.registry import get_registry

    check_writable_folder(args.out_dir, "OUT_DIR")
    options = source_options(args.source, _flags(args, SOURCE_FLAGS), args.options)
    source = get_registry().create("scene_source", args.source, options)
    path = source.generate(Path(args.out_dir))
    print(f"wrote scene {path}")
    return 0


# ------------------------------------------------------------------------------------ suite
def suite_plan(only: str | None) -> list[tuple[str, list[str]]]:
    """(scene code, material families) of the suite, or of the subset ``only`` names."""
    from mosiv_framework.errors import ConfigError

    codes = list(SUITE_SCENES)
    if only:
        wanted = [c.strip().upper() for c in only.split(",") if c.strip()]
        unknown = [c for c in wanted if c not in SUITE_SCENES]
        if unknown:
            raise ConfigError(
                f"--only: unknown scene(s) {unknown}; valid: {', '.join(SUITE_SCENES)}"
            )
        codes = [c for c in codes if c in wanted]
    return [(c, [ABBREVIATIONS[m] for m in c.split("-")]) for c in codes]


def scene_is_complete(path: Path) -> bool:
    """A scene folder whose scene.json (written last) exists and whose layout checks clean."""
    from mosiv_framework.scene.check import check_layout

    return (path / "scene.json").is_file() and not check_layout(path)


def run_suite(args) -> int:
    from mosiv_framework.cli.main import resume_from
    from mosiv_framework.cli.stages import check_writable_folder
    from mosiv_framework.errors import ConfigError
    from mosiv_framework.registry import get_registry
    from mosiv_framework.scale import Task, run_tasks
    from mosiv_framework.scale.flags import scale_options
    from mosiv_framework.scene.io import atomic_write_json

    out = Path(args.out_dir)
    check_writable_folder(out, "OUT_DIR")
    resume_from(args, out, "the scenes already finished", "suite folder")
    plan = suite_plan(args.only)
    flags = _flags(args, ("seed", "resolution", "cameras", "frames", "ranges"))
    if flags["ranges"] is None:  # so suites indexed before --ranges existed still resume
        del flags["ranges"]
    base_seed = args.seed if args.seed is not None else 0
    settings = {"source": args.source, **flags, "seed": base_seed, "options": args.options}
    index_path = out / "suite.json"
    index = {"format": SUITE_FORMAT, "settings": settings, "scenes": {}}
    if index_path.is_file():
        old = json.loads(index_path.read_text())
        if old.get("settings") != settings:
            raise ConfigError(
                f"{index_path} was made with settings {old.get('settings')}, not {settings}; "
                "resume with the same settings or use another folder"
            )
        index["scenes"] = old.get("scenes", {})
    out.mkdir(parents=True, exist_ok=True)
    scratch = out / ".partial"  # scenes being written; renamed into place once complete
    total_start = time.perf_counter()
    tasks = []
    for i, (code, materials) in enumerate(plan, start=1):
        final = out / code
        head = f"[{i}/{len(plan)}] {code} ({', '.join(materials)})"
        if final.exists():
            if not scene_is_complete(final):
                raise ConfigError(
                    f"{final} exists but is not a complete scene; remove it to regenerate it"
                )
            logger.info("%s: complete, skipped", head)
            # complete on disk but made before this index existed
            index["scenes"].setdefault(code, _index_record(code, materials))
            continue
        # the scene's seed derives from the suite seed and its position in SUITE_SCENES,
        # so --only subsets and resumed runs reproduce the same scenes
        seed = base_seed * 1000 + SUITE_SCENES.index(code)
        flags_i = {**flags, "seed": seed, "materials": ",".join(materials)}
        options = source_options(args.source, flags_i, list(args.options))
        component = get_registry().get("scene_source", args.source)
        if "scene_name" in _option_names(component):
            options.setdefault("scene_name", f"{code}-{seed:04d}")
        job = (args.source, options, scratch / code, final, head)
        tasks.append(Task(code, generate_suite_scene, job, out / "logs" / f"{code}.log"))
    atomic_write_json(index_path, index)

    def record(outcome) -> None:  # the index follows every finished scene, for resuming
        if outcome.ok:
            materials = dict(plan)[outcome.name]
            index["scenes"][outcome.name] = {
                **_index_record(outcome.name, materials),
                **outcome.result,
            }
            atomic_write_json(index_path, index)

    outcomes = run_tasks(tasks, on_done=record, **scale_options(args))
    failed = [o.name for o in outcomes.values() if not o.ok]
    retried = [o.name for o in outcomes.values() if o.retried]
    if scratch.is_dir() and not any(scratch.iterdir()):
        scratch.rmdir()
    print(
        f"suite {out}: {len(plan) - len(failed)} of {len(plan)} scene(s) ready in "
        f"{time.perf_counter() - total_start:.1f} s; index {index_path}"
    )
    if retried:
        print(f"run again after their worker died: {', '.join(retried)}")
    if failed:
        print(f"failed (logs in {out / 'logs'}; rerun to resume): {', '.join(failed)}")
        return 1
    return 0


def _index_record(code: str, materials: list[str]) -> dict:
    return {"path": code, "materials": materials, "n_objects": len(materials)}


def generate_suite_scene(source: str, options: dict, partial: Path, final: Path, head: str) -> dict:
    """Generate one suite scene into ``partial`` and move it to ``final`` once complete (a
    scene folder is never half-written); returns its seed and time for the index. The body of
    one task of ``mosiv data suite``, run here or on a Ray worker."""
    from mosiv_framework.registry import get_registry

    if partial.exists():
        shutil.rmtree(partial)  # left by an interrupted run of this suite or a dead worker
    logger.info("%s: generating (seed %d)", head, options["seed"])
    start = time.perf_counter()
    get_registry().create("scene_source", source, options).generate(partial)
    partial.rename(final)
    seconds = round(time.perf_counter() - start, 2)
    logger.info("%s: done in %.1f s", head, seconds)
    return {"seed": options["seed"], "time_s": seconds}


# ------------------------------------------------------------------------------------- show
def overlay_masks(rgb, mask):
    """rgb uint8 [H, W, 3] with each object's pixels (mask id k > 0) blended with its colour."""
    import numpy as np

    palette = np.array([(0, 0, 0), *OVERLAY_COLORS], dtype=np.float32)
    ids = mask.astype(np.int64)
    colour = palette[np.where(ids > 0, (ids - 1) % len(OVERLAY_COLORS) + 1, 0)]
    out = rgb.astype(np.float32)
    fg = ids > 0
    out[fg] = (1.0 - OVERLAY_ALPHA) * out[fg] + OVERLAY_ALPHA * colour[fg]
    return np.clip(np.rint(out), 0, 255).astype(np.uint8)


def tile_origin(row: int, col: int, *, height: int, width: int) -> tuple[int, int]:
    """Top-left pixel (y, x) of the tile of camera ``row`` and sheet column ``col``."""
    return (
        SHEET_LABEL_H + SHEET_GAP + row * (height + SHEET_GAP),
        SHEET_LABEL_W + SHEET_GAP + col * (width + SHEET_GAP),
    )


def contact_sheet(scene, *, masks: bool, step: int = 1, tile: int | None = None):
    """uint8 [H', W', 3] image: one row per camera, one column per shown frame, labelled; a
    frame a camera did not record stays a blank (white) tile. ``tile``: the frames brought
    down to at most this many pixels on their longest side (None: as recorded; 11 cameras x
    8 frames of 1080p make a 16,000 x 12,000 pixel sheet)."""
    import numpy as np
    from PIL import Image, ImageDraw

    frames = list(range(0, scene.n_frames, step))
    h = max(c.height for c in scene.cameras)
    w = max(c.width for c in scene.cameras)
    scale = 1.0 if tile is None else min(1.0, tile / max(h, w))
    h, w = max(1, round(h * scale)), max(1, round(w * scale))
    y_end, x_end = tile_origin(len(scene.cameras), len(frames), height=h, width=w)
    sheet = np.full((y_end, x_end, 3), 255, dtype=np.uint8)
    for r, cam in enumerate(scene.cameras):
        size = (max(1, round(cam.width * scale)), max(1, round(cam.height * scale)))
        for c, t in enumerate(frames):
            if not scene.records(cam.id, t):
                continue
            img = scene.rgb(cam.id, t)
            if masks:
                img = overlay_masks(img, scene.mask(cam.id, t))
            if scale < 1.0:
                img = np.asarray(Image.fromarray(img).resize(size, Image.Resampling.BOX))
            y, x = tile_origin(r, c, height=h, width=w)
            sheet[y : y + size[1], x : x + size[0]] = img
    pil = Image.fromarray(sheet)
    draw = ImageDraw.Draw(pil)
    for r, cam in enumerate(scene.cameras):
        y, _ = tile_origin(r, 0, height=h, width=w)
        draw.text((2, y + 2), cam.id, fill=(0, 0, 0))
    for c, t in enumerate(frames):
        _, x = tile_origin(0, c, height=h, width=w)
        draw.text((x + 2, 1), f"t={t}", fill=(0, 0, 0))
    return np.asarray(pil)


def write_previews(scene_dir: Path, out: Path, *, masks: bool, step: int = 1) -> list[Path]:
    """Write ``contact_sheet.png`` and ``<camera id>.gif`` (at the scene's fps) into ``out``."""
    import imageio.v3 as iio
    import numpy as np

    from mosiv_framework.errors import ConfigError
    from mosiv_framework.scene.io import read_scene

    if step < 1:
        raise ConfigError(f"--step={step}: must be at least 1")
    scene = read_scene(scene_dir)
    out.mkdir(parents=True, exist_ok=True)
    written = [out / "contact_sheet.png"]
    iio.imwrite(written[0], contact_sheet(scene, masks=masks, step=step))
    for cam in scene.cameras:
        frames = []
        for t in scene.recorded_frames(cam.id):
            img = scene.rgb(cam.id, t)
            frames.append(overlay_masks(img, scene.mask(cam.id, t)) if masks else img)
        path = out / f"{cam.id}.gif"
        iio.imwrite(path, np.stack(frames), extension=".gif", duration=1000.0 / scene.fps, loop=0)
        written.append(path)
    return written


def run_show(args) -> int:
    from mosiv_framework.cli.stages import check_writable_folder

    scene_dir = Path(args.scene_dir)
    out = Path(args.out) if args.out else scene_dir / "preview"
    if args.out:  # the default lies in the scene folder, which the scene check covers
        check_writable_folder(out, "--out")
    written = write_previews(scene_dir, out, masks=args.masks, step=args.step)
    print(f"wrote {written[0]} and {len(written) - 1} GIF(s) in {out}")
    return 0
