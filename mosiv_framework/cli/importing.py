"""``mosiv data import OUT``: a capture rig's recording -> a ``mosiv-scene/1`` folder.

The work is in ``mosiv_framework.capture``; this module maps the flags onto its
``ImportSettings`` (docs/SCENE_FORMAT.md, "Importing a recording"; docs/CLI.md).
"""

from __future__ import annotations

import argparse
from pathlib import Path


def _data_subparsers(sub) -> argparse._SubParsersAction:
    """The sub-command action of ``mosiv data`` (its ACTION argument)."""
    data = sub.choices["data"]
    return next(a for a in data._actions if isinstance(a, argparse._SubParsersAction))


def add_parser(sub) -> None:
    """Register ``import`` under ``mosiv data`` (``sub``: the top-level sub-commands)."""
    p = _data_subparsers(sub).add_parser(
        "import", help="turn a recording (videos + COLMAP or nerfstudio cameras) into a scene"
    )
    p.add_argument("out_dir", help="folder to write the scene into (new or empty)")
    src = p.add_argument_group("recording")
    src.add_argument(
        "--recording",
        help="recording folder: frames in videos/ (or images/, frames/, the folder itself), "
        "cameras in sparse/0, sparse, colmap (COLMAP) or transforms.json",
    )
    src.add_argument("--videos", help="folder with one video or image folder per camera")
    src.add_argument("--colmap", help="COLMAP sparse model folder (text or binary)")
    src.add_argument("--transforms", help="nerfstudio transforms.json")
    src.add_argument("--fps", type=float, help="frame rate (default: the videos' own)")
    src.add_argument(
        "--offsets",
        help="leading frames each camera drops, CAM:N,... ('none': synchronised; 'audio': "
        "from a sound every camera's audio track holds, a clap say; default: estimated from "
        "motion onset)",
    )
    src.add_argument(
        "--late-cameras",
        choices=("trim", "drop", "keep"),
        default="keep",
        help="cameras that started late or stopped early: keep every camera and frame, each "
        "camera declared with the frames it recorded (default: the first frames hold the "
        "starting state), trim every camera to the frames all recorded, or drop the late "
        "cameras and keep every frame of the others",
    )
    src.add_argument("--frames", type=int, help="keep the first N frames after the offsets")
    src.add_argument(
        "--every",
        type=int,
        default=1,
        help="keep every N-th frame of the videos (the frame rate divided by N; offsets and "
        "--frames count the frames kept)",
    )
    src.add_argument(
        "--resolution",
        type=int,
        help="bring the frames down to this many pixels on their longest side as they are "
        "read, the cameras' intrinsics alike (default: as recorded; a long 1080p clip from "
        "11 cameras takes tens of GB at full size)",
    )
    src.add_argument(
        "--background",
        help="clean plates: one image of the empty scene per camera, <camera id>.png or .jpg, "
        "through the same lens (default: the recording's background/ folder, if any; else the "
        "segmenter estimates the background)",
    )
    world = p.add_argument_group("world frame")
    world.add_argument("--units", help="length unit of the cameras: m, cm, mm, in, ... or m/unit")
    world.add_argument("--up", help="up axis of the cameras' world: x, y, z, -y, or a,b,c")
    world.add_argument(
        "--ground", help="ground plane AXIS=VALUE in the recording's units, or none (default: fit)"
    )
    world.add_argument(
        "--margin", type=float, default=0.1, help="domain margin, fraction of the hull's size"
    )
    world.add_argument("--hull-voxels", type=int, default=64, help="visual hull cells per side")
    obj = p.add_argument_group("objects")
    obj.add_argument("--materials", help="material family per object, e.g. elastic,sand")
    obj.add_argument("--objects", help="YAML: objects (id -> material, name, hints), offsets")
    obj.add_argument("--observed", type=int, help="observed frames (default: half)")
    obj.add_argument("--name", help="scene name (default: OUT's folder name)")
    obj.add_argument("--segmenter", default="classical", help="registered segmenter")
    obj.add_argument(
        "--segmenter-option",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="an option of the segmenter (repeatable)",
    )
    p.set_defaults(handler=run_import)


def settings_from_args(args):
    """``ImportSettings`` of the parsed flags."""
    from omegaconf import OmegaConf

    from mosiv_framework.capture import ImportSettings, find_inputs
    from mosiv_framework.errors import ConfigError

    bad = [o for o in args.segmenter_option if "=" not in o]
    if bad:
        raise ConfigError([f"--segmenter-option {o!r}: not of the form key=value" for o in bad])
    options = OmegaConf.to_container(OmegaConf.from_dotlist(args.segmenter_option))
    found = find_inputs(args.recording) if args.recording else {}
    frames_dir = args.videos or found.get("frames_dir")
    if frames_dir is None:
        raise ConfigError("give the frames: --recording DIR or --videos DIR")
    explicit = args.colmap is not None or args.transforms is not None
    return ImportSettings(
        out=Path(args.out_dir),
        frames_dir=Path(frames_dir),
        colmap=Path(args.colmap) if args.colmap else (None if explicit else found.get("colmap")),
        transforms=Path(args.transforms)
        if args.transforms
        else (None if explicit else found.get("transforms")),
        materials=args.materials,
        objects_yaml=Path(args.objects) if args.objects else None,
        offsets=args.offsets,
        late_cameras=args.late_cameras,
        units=args.units,
        up=args.up,
        ground=args.ground,
        fps=args.fps,
        observed=args.observed,
        n_frames=args.frames,
        every=args.every,
        resolution=args.resolution,
        segmenter=args.segmenter,
        segmenter_options=options,
        background=Path(args.background) if args.background else found.get("background"),
        name=args.name,
        margin=args.margin,
        hull_voxels=args.hull_voxels,
    )


def resolution_note(extent: float, *, grid: int = 64, cell_size: float = 0.0125) -> str:
    """What the imported domain's size means for a simulator's resolution: a recipe's grid
    counts cells along its largest side (``extent`` m), ``simulator.cell_size`` fixes the cell
    (``mosiv_framework.recipes.cell_size``; the defaults are recipes/video_paper.yaml's)."""
    from mosiv_framework.recipes.cell_size import grid_for

    return (
        f"domain: largest side {extent:.3g} m; a recipe's simulator.grid={grid} simulates it at "
        f"{100 * extent / grid:.3g} cm cells, simulator.cell_size={cell_size:g} (as "
        f"recipes/video_paper.yaml) at grid {grid_for(extent, cell_size)}"
    )


def run_import(args) -> int:
    from mosiv_framework.capture import import_recording
    from mosiv_framework.cli.stages import check_writable_folder
    from mosiv_framework.scene import read_scene, summary

    check_writable_folder(args.out_dir, "OUT_DIR")
    out = import_recording(settings_from_args(args))
    scene = read_scene(out)
    print(f"wrote scene {out}: {summary(scene)}")
    print(resolution_note(scene.world.extent))
    print(f"preview: {out / 'preview' / 'contact_sheet.png'}")
    return 0
