"""A ``mosiv-scene/1`` folder written the way a multi-camera capture rig delivers a recording.

Layout of the capture folder::

    capture.json               fps, units, up axis, distortion, per camera: video, start offset
    videos/<camera_id>.mp4     H.264 (yuv420p, or yuv444p on request) through the lens, no masks
    sparse/0/cameras.txt       COLMAP text model (options.WRITE_MODELS, with the distortion)
    sparse/0/images.txt        world-to-camera pose per camera, in the rig's units and up axis
    sparse/0/points3D.txt      empty
    sparse/0/rigs.txt          one trivial rig per camera (COLMAP 3.12 and later)
    sparse/0/frames.txt        one frame per camera, with its pose
    background/<camera_id>.png only with ``with_plates``: the empty scene through the lens, the
                               clean plate a rig records before the take
    reference_gt/              only with ``with_reference``: the scene's gt/ for benchmarking

What a rig does not know stays out: instance masks, object count and materials, the ground
plane and every ground truth. ``offsets`` (the syntax of ``mosiv data import --offsets``)
drops leading frames per camera, as unsynchronised cameras that started late; capture.json
records each camera's first frame, which is the time offset ``start_frame / fps`` of its video.
The lens model is ``lens``, the COLMAP writer ``colmap``, the rig's frame ``align.RigFrame``:
the same modules the import reads a capture with.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np

from mosiv_framework.capture.align import RigFrame
from mosiv_framework.capture.colmap import colmap_params, write_colmap
from mosiv_framework.capture.common import refuse_non_empty
from mosiv_framework.capture.lens import Distortion, distort_frames
from mosiv_framework.capture.offsets import parse_offsets
from mosiv_framework.capture.options import DEFAULT_CRF
from mosiv_framework.errors import ConfigError

CAPTURE_FORMAT = "mosiv-capture/1"


def _even(frame: np.ndarray) -> np.ndarray:
    """Pad the bottom row / right column by repetition to even sizes, as yuv420p needs; padding
    at the far edges leaves cx, cy (measured from the top-left corner) valid."""
    h, w = frame.shape[:2]
    return np.pad(frame, ((0, h % 2), (0, w % 2), (0, 0)), mode="edge")


#: the H.264 pixel formats a capture may use: yuv420p, what cameras and players use, keeps the
#: colour at half resolution per axis; yuv444p keeps it whole (High 4:4:4 profile)
PIXEL_FORMATS = ("yuv420p", "yuv444p")


def encode_h264(
    frames: list[np.ndarray], path: Path, *, fps: float, crf: int, pixel_format: str = "yuv420p"
) -> tuple[int, int]:
    """Write uint8 [H, W, 3] frames as an H.264 mp4 in ``pixel_format`` (PIXEL_FORMATS);
    returns its (width, height)."""
    import imageio_ffmpeg

    frames = [_even(f) for f in frames]
    h, w = frames[0].shape[:2]
    writer = imageio_ffmpeg.write_frames(
        str(path),
        (w, h),
        fps=fps,
        codec="libx264",
        pix_fmt_in="rgb24",
        pix_fmt_out=pixel_format,
        quality=None,  # the CRF below sets the quality
        macro_block_size=1,  # never rescale: the intrinsics refer to these pixels
        output_params=["-crf", str(int(crf))],
    )
    writer.send(None)
    for frame in frames:
        writer.send(np.ascontiguousarray(frame))
    writer.close()
    return w, h


def _check_options(scene, crf, offsets, distortion: Distortion, camera_model: str) -> dict:
    """Every option checked before anything is written; returns the start frame per camera."""
    if not 0 <= int(crf) <= 51:
        raise ConfigError(f"--crf {crf}: H.264 takes a constant rate factor from 0 to 51")
    starts = parse_offsets(offsets, scene.camera_ids, "--offsets") or dict.fromkeys(
        scene.camera_ids, 0
    )
    too_late = [c for c, s in starts.items() if s >= scene.n_frames]
    if too_late:
        raise ConfigError(
            f"--offsets drops every one of the {scene.n_frames} frames of {', '.join(too_late)}"
        )
    for cam in scene.cameras:  # before any video is written: a model that cannot describe
        try:  # a camera must not leave a half-written capture behind
            colmap_params(cam, distortion, camera_model)
        except ValueError as exc:
            raise ConfigError(f"--camera-model {camera_model} with --distortion: {exc}") from None
    return starts


def _write_videos(
    scene, out: Path, starts: dict, distortion: Distortion, crf: int, pixel_format: str
) -> list[dict]:
    """One H.264 video per camera through the lens; returns capture.json's camera entries."""
    (out / "videos").mkdir(parents=True, exist_ok=True)
    entries = []
    for cam in scene.cameras:
        ideal = np.stack([scene.rgb(cam.id, t) for t in range(starts[cam.id], scene.n_frames)])
        frames = list(distort_frames(ideal, cam, distortion))
        video = f"videos/{cam.id}.mp4"
        size = encode_h264(frames, out / video, fps=scene.fps, crf=crf, pixel_format=pixel_format)
        entries.append(
            {
                "id": cam.id,
                "video": video,
                "colmap_image": f"{cam.id}.mp4",
                "width": size[0],
                "height": size[1],
                "n_frames": len(frames),
                "start_frame": starts[cam.id],
                "start_time_s": starts[cam.id] / scene.fps,
            }
        )
    return entries


def empty_plate(scene, camera_id: str) -> tuple[np.ndarray, int]:
    """The scene without its objects as ``camera_id`` sees it, uint8 [H, W, 3], and how many
    pixels no frame shows uncovered: each pixel's median over the frames whose instance mask
    leaves it free (over all frames where none does)."""
    rgb = np.stack([scene.rgb(camera_id, t) for t in range(scene.n_frames)]).astype(np.float32)
    free = np.stack([scene.mask(camera_id, t) == 0 for t in range(scene.n_frames)])
    masked = np.where(free[..., None], rgb, np.nan)
    never_free = ~free.any(axis=0)
    masked[:, never_free] = rgb[:, never_free]
    plate = np.nanmedian(masked, axis=0)
    return np.clip(np.rint(plate), 0, 255).astype(np.uint8), int(never_free.sum())


def _write_plates(scene, out: Path, distortion: Distortion) -> dict[str, int]:
    """background/<camera>.png per camera through the lens; returns the pixels per camera that
    no frame showed free of objects (their plate is the median of every frame)."""
    import imageio.v3 as iio

    (out / "background").mkdir(parents=True, exist_ok=True)
    never_free = {}
    for cam in scene.cameras:
        plate, never_free[cam.id] = empty_plate(scene, cam.id)
        iio.imwrite(
            out / "background" / f"{cam.id}.png", distort_frames(plate[None], cam, distortion)[0]
        )
    return never_free


def write_capture(
    scene_dir: str | Path,
    out: str | Path,
    *,
    rig: RigFrame | None = None,
    distortion: Distortion | None = None,
    camera_model: str = "OPENCV",
    crf: int = DEFAULT_CRF,
    offsets: str | None = None,
    with_reference: bool = False,
    pixel_format: str = "yuv420p",
    with_plates: bool = False,
) -> Path:
    """Write the scene at ``scene_dir`` as a capture into the new or empty folder ``out``:
    ``rig`` its units and up axis (default metres, z up), ``distortion`` the lens (default none),
    ``with_plates``: a clean plate per camera in background/ (``empty_plate``).

    Returns ``out``. Raises SceneFormatError for an invalid scene, ConfigError for bad options,
    OutputError when ``out`` is refused."""
    from mosiv_framework.scene import read_scene

    if pixel_format not in PIXEL_FORMATS:
        raise ConfigError(
            f"--pixel-format {pixel_format!r}: valid values are {list(PIXEL_FORMATS)}"
        )
    rig = rig or RigFrame()
    distortion = distortion or Distortion()
    scene = read_scene(scene_dir)
    out = Path(out)
    refuse_non_empty(out, "capture folder")
    starts = _check_options(scene, crf, offsets, distortion, camera_model)
    entries = _write_videos(scene, out, starts, distortion, crf, pixel_format)
    write_colmap(
        out / "sparse" / "0",
        scene.cameras,
        names=[e["colmap_image"] for e in entries],
        sizes=[(e["width"], e["height"]) for e in entries],
        distortion=distortion,
        model=camera_model,
        rig=rig,
    )
    meta = {
        "format": CAPTURE_FORMAT,
        "fps": scene.fps,
        "units": rig.units,
        "up": rig.up,
        "colmap": "sparse/0",
        "camera_model": camera_model,
        "distortion": distortion.as_dict(),  # lens.py gives each model's equations
        "crf": int(crf),
        "pixel_format": pixel_format,
        "cameras": entries,
    }
    if with_plates:
        never_free = _write_plates(scene, out, distortion)
        meta["background"] = {"path": "background", "pixels_never_free": never_free}
    if with_reference and scene.has_gt:
        shutil.copytree(scene.root / "gt", out / "reference_gt")
        # the ground truth stays in the scene's own frame: an importer maps it, not the rig
        meta["reference_gt"] = {"path": "reference_gt", "frame": "scene: metres, z up"}
    (out / "capture.json").write_text(json.dumps(meta, indent=2) + "\n")
    return out
