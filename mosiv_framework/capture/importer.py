"""``import_recording``: a capture rig's recording -> a ``mosiv-scene/1`` folder.

The steps, each in its own module: frames (``video``, ``frame_times``), cameras (``colmap``,
``nerfstudio``), time offsets (``offsets``, ``audio_sync``), lens undistortion (``lens``), the
frame alignment (``align``: units, up axis, ground), masks from a registered segmenter, and the
domain from the visual hull (``domain``). Everything is read and checked before OUT is created;
the scene is written with ``SceneWriter``, validated with ``validate_scene``, and previewed as
``preview/contact_sheet.png``; ``import.json`` records what the import decided.
"""

from __future__ import annotations

import logging
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from mosiv_framework.capture import align as al
from mosiv_framework.capture import audio_sync, frame_times, video
from mosiv_framework.capture import domain as dom
from mosiv_framework.capture import materials as mat
from mosiv_framework.capture import offsets as off
from mosiv_framework.capture.common import CaptureError, SourceCamera, refuse_non_empty
from mosiv_framework.capture.lens import undistort_frames
from mosiv_framework.capture.rotations import rotation_to_z
from mosiv_framework.errors import SceneFormatError

logger = logging.getLogger(__name__)

IMPORT_FORMAT = "mosiv-import/1"
#: longest side (pixels) of each frame in the contact sheet the import leaves in preview/
PREVIEW_TILE = 320


@dataclass
class ImportSettings:
    """What ``mosiv data import`` was asked for (docs/SCENE_FORMAT.md, "Importing a
    recording"). Strings are parsed as the command-line flags of the same names."""

    out: Path
    frames_dir: Path
    colmap: Path | None = None
    transforms: Path | None = None
    materials: str | None = None
    objects_yaml: Path | None = None
    offsets: str | None = None
    #: cameras that started late (or stopped early): "keep" every camera and frame, the late
    #: ones declared with the frames they recorded; "trim" the others' leading frames; or
    #: "drop" the late cameras
    late_cameras: str = "keep"
    units: str | None = None
    up: str | None = None
    ground: str | None = None
    fps: float | None = None
    observed: int | None = None
    n_frames: int | None = None
    segmenter: str = "classical"
    segmenter_options: dict[str, Any] = field(default_factory=dict)
    background: Path | None = None
    name: str | None = None
    #: keep every N-th frame (the frame rate divided by N)
    every: int = 1
    #: bring the frames down to this many pixels on their longest side (None: as recorded)
    resolution: int | None = None
    margin: float = 0.1
    hull_voxels: int = 64
    onset_k: float = 4.0


def find_inputs(recording: str | Path) -> dict[str, Path]:
    """Frames folder and camera file of a recording folder: frames in ``videos/``,
    ``images/`` or the folder itself; cameras in ``sparse/0``, ``sparse``, ``colmap`` or
    ``transforms.json``; clean plates (one image of the empty scene per camera) in
    ``background/``. Keys: ``frames_dir``, one of ``colmap`` / ``transforms``, and
    ``background`` where the recording has plates."""
    root = Path(recording)
    if not root.is_dir():
        raise CaptureError(f"recording folder {str(root)!r} does not exist or is not a folder")
    found: dict[str, Path] = {"frames_dir": root}
    for name in ("videos", "images", "frames"):
        if (root / name).is_dir():
            found["frames_dir"] = root / name
            break
    for name in ("sparse/0", "sparse", "colmap"):
        d = root / name
        if any((d / f).is_file() for f in ("cameras.txt", "cameras.bin")):
            found["colmap"] = d
            break
    else:
        if (root / "transforms.json").is_file():
            found["transforms"] = root / "transforms.json"
    if (root / "background").is_dir():
        found["background"] = root / "background"
    return found


def load_plates(
    folder: Path | None, cams, longest_side: int | None = None
) -> dict[str, np.ndarray] | None:
    """Each camera's clean plate (``<camera id>.png`` or ``.jpg`` in ``folder``, the empty scene
    through the same lens) brought down to ``longest_side`` pixels and undistorted like its
    frames; None without a folder."""
    if folder is None:
        return None
    from mosiv_framework.segment.classical import background_image

    if not Path(folder).is_dir():
        raise CaptureError(f"--background {folder}: not a folder")
    plates = {}
    for cid, cam in sorted(cams.items()):
        path = background_image(folder, cid)
        if path is None:
            raise CaptureError(
                f"--background {folder}: no {cid}.png or {cid}.jpg for camera {cid!r}"
            )
        plate = video.rgb8(video.read_image(Path(path)), str(path))  # as the frames are read
        plate = video.shrink(plate, video.shrunk_size(*plate.shape[:2], longest_side))
        k = cam.intrinsics
        if plate.shape[:2] != (k.height, k.width):
            raise CaptureError(
                f"{path}: {plate.shape[1]}x{plate.shape[0]} pixels, but {cam.origin} gives "
                f"camera {cid!r} {k.width}x{k.height}"
            )
        plates[cid] = undistort_frames(plate[None], k, cam.distortion)[0]
    return plates


def load_cameras(s: ImportSettings, known: set[str]) -> dict[str, SourceCamera]:
    if s.colmap is not None and s.transforms is not None:
        raise CaptureError("give only one of --colmap and --transforms for the cameras")
    if s.colmap is None and s.transforms is None:
        raise CaptureError("give the cameras: either a COLMAP model (--colmap) or --transforms")
    if s.colmap:  # pycolmap is imported only for a COLMAP model
        from mosiv_framework.capture.colmap import read_colmap

        cams = read_colmap(s.colmap, known)
    else:
        from mosiv_framework.capture.nerfstudio import read_nerfstudio

        cams = read_nerfstudio(s.transforms, known)
    by_id = {c.id: c for c in cams}
    missing = sorted(known - set(by_id))
    if missing:
        model = s.colmap or s.transforms
        raise CaptureError(
            f"{model}: no camera for the frames of {', '.join(missing)} (in {s.frames_dir}); "
            "a camera's image name must be the video's name (see docs/SCENE_FORMAT.md)"
        )
    return by_id


def load_frames(s: ImportSettings, sources, cams) -> tuple[dict[str, np.ndarray], float, dict]:
    """Every camera's frames (checked against its intrinsics' size) and the frame rate: every
    ``s.every``-th frame (the rate divided alike; of a camera at a whole multiple of the
    slowest camera's rate, every ``s.every`` x that multiple), brought down to
    ``s.resolution`` pixels on the longest side, with each camera's intrinsics in ``cams``
    scaled to match. Returns the frames, the rate and each camera's source frames per frame
    read (``s.every`` x its multiple)."""
    videos, rates = {}, {}
    # a camera at a whole multiple of the others' rate keeps the frames at their instants
    # (--fps says every frame is equally spaced at that rate: nothing is skipped then)
    steps = video.rate_steps(sources) if s.fps is None else dict.fromkeys(sources, 1)
    for cid, src in sources.items():
        k = cams[cid].intrinsics
        size = video.shrunk_size(k.height, k.width, s.resolution)
        expect = ((k.height, k.width), f"{cams[cid].origin} gives camera {cid!r}")
        every = s.every * steps[cid]
        frames, rate = video.read_frames(src, every=every, longest_side=s.resolution, expect=expect)
        if len(frames) < 2:
            raise CaptureError(
                f"{src}: keeps {len(frames)} frame of its clip (--every {s.every}); a camera "
                "needs at least 2"
            )
        rates[cid] = rate / every if rate else None
        cams[cid] = replace(cams[cid], intrinsics=k.resized(size[1], size[0]))
        videos[cid] = frames
    longest = max(len(v) for v in videos.values())
    per_read = {cid: s.every * steps[cid] for cid in videos}
    if s.fps is not None:  # checked as given, then divided alike
        return videos, video.common_fps(rates, s.fps, s.frames_dir, longest) / s.every, per_read
    return videos, video.common_fps(rates, None, s.frames_dir, longest), per_read


def time_offsets(s: ImportSettings, videos, yaml_offsets, sources, per_read: dict):
    """(camera id -> leading frames to drop, how they were found: "given", "motion" or
    "audio", the sub-frame remainders of audio offsets) from --offsets, the objects YAML,
    the cameras' sound (``--offsets audio``) or the motion onsets; ``per_read``: each
    camera's source frames per frame read (``load_frames``)."""
    if s.offsets is not None and yaml_offsets is not None:
        raise CaptureError(f"offsets given twice (--offsets and {s.objects_yaml}); give one")
    given, where = (s.offsets, "--offsets") if s.offsets is not None else (yaml_offsets, "")
    if isinstance(given, str) and given.strip().lower() == "audio":
        return _audio_offsets({c: sources[c] for c in videos}, per_read)
    offsets = off.parse_offsets(given, sorted(videos), where or f"{s.objects_yaml}: offsets")
    if offsets is not None:
        return offsets, "given", {}
    offsets = off.estimate_offsets(videos, k=s.onset_k)
    logger.info("estimated time offsets (frames dropped): %s", offsets)
    return offsets, "motion", {}


def _audio_offsets(sources: dict, per_read: dict):
    """``time_offsets`` from the cameras' sound: each camera's lag in its container's time,
    turned into frames as read by the rate of its own timestamps over ``per_read`` (not
    --fps, which may say the frames stand for another rate)."""
    first_shown, read_rates = {}, {}
    for cam, path in sources.items():
        stamps = frame_times.presentation_times(path) if path.is_file() else None
        if stamps is None or len(stamps.times) < 2:
            first_shown[cam], read_rates[cam] = 0.0, 0.0  # refused below: no sound
            continue
        first_shown[cam] = float(stamps.times[0])
        read_rates[cam] = stamps.rate() / per_read[cam]
    found = audio_sync.estimate_audio_offsets(sources, read_rates, first_shown)
    logger.info(
        "time offsets from the cameras' sound (frames dropped): %s; sub-frame remainders %s; "
        "peak ratios %s",
        found.frames,
        {c: round(r, 2) for c, r in found.remainders.items()},
        {c: round(r, 1) for c, r in found.peak_ratios.items()},
    )
    return found.frames, "audio", found.remainders


def synchronise(s: ImportSettings, videos, offsets) -> tuple[dict, dict, list, dict]:
    """(videos on a common time base, offsets, the cameras left out because they started
    late: ``--late-cameras drop``, and camera id -> (first, last) recorded frames of the
    cameras that started late: ``--late-cameras keep``)."""
    left_out = off.cameras_left_out(offsets, s.late_cameras)
    if left_out:
        logger.info("cameras that started late, left out: %s", ", ".join(left_out))
        videos = {c: v for c, v in videos.items() if c not in left_out}
        offsets = {c: 0 for c in videos}  # the cameras kept all started first
    if s.late_cameras == "keep":
        videos, spans = off.pad_late_cameras(videos, offsets, s.n_frames)
        if spans:  # a camera that started late or stopped early: worth a user's look
            logger.warning(
                "cameras that did not record every frame, kept with the frames they recorded "
                "(first, last): %s; --late-cameras trim or drop leave them out instead",
                spans,
            )
        return videos, offsets, left_out, spans
    return off.apply_offsets(videos, offsets, s.n_frames), offsets, left_out, {}


def read_objects(s: ImportSettings):
    if s.materials is not None and s.objects_yaml is not None:
        raise CaptureError("give only one of --materials and --objects for the objects")
    if s.materials is None and s.objects_yaml is None:
        raise CaptureError("give the objects: either --materials elastic,sand or --objects FILE")
    if s.materials is not None:
        return mat.from_flag(s.materials), {}, None
    return mat.read_objects_yaml(s.objects_yaml)


def segment(
    s: ImportSettings, videos, cameras, n_objects: int, box, plates=None, spans=None
) -> dict[str, np.ndarray]:
    """Masks of the registered segmenter ``s.segmenter``, checked against the objects;
    ``plates``: the recording's clean plates (load_plates), if any; ``spans``: the recorded
    frames of cameras that started late (``synchronise``)."""
    from mosiv_framework.registry import get_registry
    from mosiv_framework.types import Frames

    seg = get_registry().create("segmenter", s.segmenter, s.segmenter_options)
    domain = (tuple(map(float, box[0])), tuple(map(float, box[1])))
    frames = Frames(
        videos,
        cameras,
        n_objects=n_objects,
        domain=domain,
        backgrounds=plates,
        camera_frames=dict(spans or {}),
    )
    masks = seg.segment(frames)
    found = max(int(m.max()) for m in masks.values())
    if found != n_objects:
        raise CaptureError(
            f"segmenter {s.segmenter!r} found {found} object(s) but {n_objects} material(s) are "
            "given; name every object's material, or tune the segmenter (--segmenter-option)"
        )
    return masks


def check_objects_seen(masks: dict[str, np.ndarray], n_objects: int, plates) -> None:
    """Every object in some camera's mask at every frame, else a CaptureError naming the
    object and its frames. An object that vanishes mid-clip is what a wrong background gives:
    a median background that holds an object resting for most of the clip (the frames before
    it arrives then show a phantom there), or a threshold that cuts off a dim object."""
    n = len(next(iter(masks.values())))
    missing = {}
    for k in range(1, n_objects + 1):
        frames = [t for t in range(n) if not any(bool((m[t] == k).any()) for m in masks.values())]
        if frames:
            missing[k] = frames
    if not missing:
        return
    where = "; ".join(
        f"object {k} in frame(s) {', '.join(map(str, f[:8]))}{' ...' if len(f) > 8 else ''}"
        for k, f in missing.items()
    )
    hint = (
        "check the plates in --background (they must show the empty scene)"
        if plates
        else "record a clean plate of the empty scene per camera (--background DIR, or "
        "background/ in the recording), or give --segmenter-option "
        "background_frames=[...] naming frames without objects"
    )
    raise CaptureError(
        f"the segmenter lost objects: {where} (no camera shows them); {hint}, or set "
        "--segmenter-option threshold=T for objects close to the background's colour"
    )


def _alignment(s: ImportSettings, cams: dict[str, SourceCamera]):
    """(Alignment without the ground offset, up direction, ground: height (m) before the
    offset, "none", or None to fit it)."""
    up = al.parse_up(s.up)
    up_given = up is not None
    if up is None:
        up = al.cameras_up(list(cams.values()))
        logger.info("up direction from the cameras: %s", np.round(up, 4).tolist())
    align = al.Alignment(al.parse_units(s.units), rotation_to_z(up))
    ground = al.parse_ground(s.ground)
    if isinstance(ground, tuple):
        ground = al.ground_height_given(ground, align, up if up_given else _axis_up(ground, up))
    return align, up, ground


def _axis_up(ground: tuple[int, float], up: np.ndarray) -> np.ndarray:
    """With an inferred up, --ground AXIS=... names the up axis: the inferred up is snapped to
    that axis when within 10 degrees of it (else the plane is refused as not horizontal)."""
    axis = np.zeros(3)
    axis[ground[0]] = np.sign(up[ground[0]]) or 1.0
    return axis if float(axis @ up) > np.cos(np.radians(10.0)) else up


def _locate(s, videos, cameras, n_objects, box, ground, plates=None, spans=None):
    """One segmenter pass over ``box``: (masks, lower, upper, ground) where the ground is
    fitted under the hull when ``ground`` is None."""
    masks = segment(s, videos, cameras, n_objects, box, plates, spans)
    points, step = dom.voxel_grid(box[0], box[1], s.hull_voxels)
    hull = dom.visual_hull(masks, cameras, points, spans)
    if ground is None:
        ground = dom.fit_ground(hull, points, step)
    height = None if ground == "none" else float(ground)
    lo, hi = dom.hull_domain(hull, points, step, height, s.margin)
    return masks, lo, hi, ground, step


def _hull_frame(s, videos, cameras, origins, n_objects, ground, plates=None, spans=None):
    """Masks, domain (lower, upper) and ground height (m, None = no ground), all before the
    ground offset. Two segmenter passes: the first over the region the cameras look at locates
    the objects; the second over the box around their hull (finer voxels) gives the masks,
    the domain and the fitted ground that are kept."""
    centre, half = dom.region(cameras)
    dom.check_in_front(centre, cameras, origins, "centre of the region the cameras look at")
    box = [centre - half, centre + half]
    if isinstance(ground, float):
        box[0][2] = max(box[0][2], ground)
    _, lo, hi, fitted, step = _locate(s, videos, cameras, n_objects, box, ground, plates, spans)
    if ground is None:  # leave room below a fitted ground for the finer hull to go lower
        lo[2] = fitted - 2 * step
    masks, lo, hi, ground, _ = _locate(
        s, videos, cameras, n_objects, (lo, hi), ground, plates, spans
    )
    check_objects_seen(masks, n_objects, plates)
    ground = None if ground == "none" else float(ground)
    logger.info("ground: %s", "none" if ground is None else f"z = {ground:.4f} m")
    return masks, lo, hi, ground


def import_recording(s: ImportSettings) -> Path:
    """Import the recording described by ``s`` into the new folder ``s.out``; returns it.

    Raises CaptureError (a ConfigError) naming the file and field of bad input, OutputError for
    unreadable files or a refused OUT, SceneFormatError if the written scene fails validation.
    """
    out = Path(s.out)
    refuse_non_empty(out, "OUT")
    objects, hints, yaml_offsets = read_objects(s)
    sources = video.find_sources(s.frames_dir)
    cams = load_cameras(s, set(sources))
    videos, fps, per_read = load_frames(s, sources, cams)
    offsets, found_by, remainders = time_offsets(s, videos, yaml_offsets, sources, per_read)
    videos, offsets, left_out, spans = synchronise(s, videos, offsets)
    cams = {c: cam for c, cam in cams.items() if c in videos}
    for c in videos:  # in place: a long clip is held once (no loop variable keeps one alive)
        undistort_frames(videos[c], cams[c].intrinsics, cams[c].distortion, in_place=True)
    plates = load_plates(s.background, cams, s.resolution)
    align, up, ground = _alignment(s, cams)
    origins = {cid: cam.origin for cid, cam in cams.items()}
    cameras = {cid: align.camera(cam) for cid, cam in sorted(cams.items())}
    masks, lo, hi, ground = _hull_frame(
        s, videos, cameras, origins, len(objects), ground, plates, spans
    )
    shift = 0.0 if ground is None else ground  # the ground goes to z = 0
    align.offset = np.array([0.0, 0.0, -shift])
    lo, hi = lo + align.offset, hi + align.offset
    cameras = {cid: align.camera(cam) for cid, cam in sorted(cams.items())}
    dom.check_in_front((lo + hi) / 2, cameras, origins, "domain centre")
    n = len(next(iter(videos.values())))
    observed = _observed(s.observed, n)
    record = {
        "format": IMPORT_FORMAT,
        "settings": {k: str(v) if isinstance(v, Path) else v for k, v in asdict(s).items()},
        "offsets": offsets,
        "offsets_estimated": found_by != "given",
        "offsets_from": found_by,
        "offset_remainders_frames": remainders,
        "late_cameras_left_out": left_out,
        "late_cameras_kept": {c: list(span) for c, span in spans.items()},
        "up_in_recording": up.tolist(),
        "alignment": align.as_dict(),
        "ground_fitted": s.ground is None,
        "distortion": {c: cam.distortion.as_dict() for c, cam in cams.items()},
        "hints": {str(k): v for k, v in hints.items()},
    }
    write(out, s.name or out.name, fps, observed, objects, cameras, videos, masks, (lo, hi),
          None if ground is None else 0.0, record, spans)  # fmt: skip
    return out


def _observed(observed: int | None, n: int) -> int:
    if observed is None:
        return max(1, n // 2)  # as ``mosiv data synth``: the first half is observed
    if not 1 <= observed <= n:
        raise CaptureError(f"--observed {observed}: must lie in 1..{n} (the imported frames)")
    return int(observed)


def write(
    out, name, fps, observed, objects, cameras, videos, masks, box, ground, record, spans=None
) -> None:
    """Write, validate and preview the scene; ``record`` goes to import.json; ``spans``: the
    recorded frames of cameras that started late (their other frames are not written). Each
    camera's frames leave ``videos`` once written, so the preview does not hold the clip too."""
    from mosiv_framework.cli.data import contact_sheet
    from mosiv_framework.scene import SceneWriter, atomic_write_json, read_scene, validate_scene

    n = len(next(iter(videos.values())))
    writer = SceneWriter(
        out, name=name, fps=fps, n_frames=n, observed_frames=observed, objects=objects,
        cameras=list(cameras.values()), domain_lower=box[0].tolist(),
        domain_upper=box[1].tolist(), ground_height=ground, camera_frames=spans,
    )  # fmt: skip
    for cid in cameras:
        first, last = (spans or {}).get(cid, (0, n - 1))
        for t in range(first, last + 1):
            writer.write_frame(cid, t, rgb=videos[cid][t], mask=masks[cid][t])
        del videos[cid]
    atomic_write_json(out / "import.json", record)
    writer.finish()
    problems = validate_scene(out)
    if problems:
        raise SceneFormatError([f"{out / p}" for p in problems])
    import imageio.v3 as iio

    sheet = contact_sheet(read_scene(out), masks=True, step=max(1, -(-n // 8)), tile=PREVIEW_TILE)
    (out / "preview").mkdir(exist_ok=True)
    iio.imwrite(out / "preview" / "contact_sheet.png", sheet)
