"""The built-in ``classical`` segmenter: background subtraction per camera, a voxel visual hull
that ties the cameras together, and identities tracked through the hull's 3D components.

No learned model: it suits static cameras, a static background that differs in colour from
the objects, and objects inside a known domain box. The steps (each in its own module):

1. ``foreground``: per camera, a background image (the recording's clean plate, a given folder,
   or the temporal median), the RGB distance
   to it, a threshold (just above the background's noise, Otsu's, or set), morphological cleanup.
2. ``hull``: voxels of the domain whose centres project into the foreground of the cameras
   that see them; 3D connected components.
3. ``track``: ids 1..K in order of world x at the first frame; matched over frames by centroid
   (Hungarian); touching objects split by nearest previous-frame voxels.
4. ``hull.paint``: each camera's mask from the labelled voxels, nearest depth winning,
   restricted to that camera's foreground.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mosiv_framework.errors import ConfigError
from mosiv_framework.interfaces import Segmenter
from mosiv_framework.segment import foreground as fgmod
from mosiv_framework.segment import hull, track
from mosiv_framework.types import Frames


@dataclass
class ClassicalOptions:
    """threshold: RGB distance (8-bit units, 0..441) above which a pixel differs from the
    background; None picks it per camera by auto_threshold: "noise" (just above the
    background's own spread, ``foreground.noise_threshold``: objects of any contrast) or
    "otsu" (Otsu's two-class cut); min_threshold: lower bound on the automatic threshold, so
    sensor noise alone is never called foreground; edge_fraction: a pixel at an object's rim
    counts when it reaches this fraction of the object's nearby distance (0.5: covered at
    least half, as masks are drawn; 0: every pixel above the threshold);
    background_frames: frame indices that show the empty scene, the background is their
    per-pixel median (None: the median over all frames, right where each pixel shows the
    background in more than half of the clip);
    background_dir: folder with one image per camera named <camera id>.png (or .jpg) showing the
    empty scene; it takes precedence over background_frames;
    open_px (pixels), close_px (pixels): radii of the morphological opening (removes specks) and
    closing (bridges gaps) of each foreground; 0 skips the step;
    voxels: hull cells along the domain's longest side; view_tolerance: cameras that may see a
    voxel as background without carving it (for a camera that misses part of an object);
    min_voxels: smaller hull components are dropped as noise;
    max_jump (m): largest centroid move between frames that still matches an object (None: no
    limit)."""

    threshold: float | None = None
    auto_threshold: str = "noise"
    min_threshold: float = 10.0
    edge_fraction: float = 0.5
    background_frames: list[int] | None = None
    background_dir: str | None = None
    open_px: int = 1
    close_px: int = 1
    voxels: int = 64
    view_tolerance: int = 0
    min_voxels: int = 8
    max_jump: float | None = None

    def __post_init__(self) -> None:
        problems = []
        if self.threshold is not None and not self.threshold > 0:
            problems.append(f"threshold must be > 0 (or None: automatic), got {self.threshold}")
        if self.auto_threshold not in fgmod.AUTO_THRESHOLDS:
            problems.append(
                f"auto_threshold {self.auto_threshold!r}: valid values are "
                f"{list(fgmod.AUTO_THRESHOLDS)}"
            )
        if not 0.0 <= self.edge_fraction < 1.0:
            problems.append(f"edge_fraction must lie in [0, 1), got {self.edge_fraction}")
        if not self.min_threshold >= 0:
            problems.append(f"min_threshold must be >= 0, got {self.min_threshold}")
        for name in ("open_px", "close_px", "view_tolerance", "min_voxels"):
            if getattr(self, name) < 0:
                problems.append(f"{name} must be >= 0, got {getattr(self, name)}")
        if self.voxels < 2:
            problems.append(f"voxels must be >= 2, got {self.voxels}")
        if self.max_jump is not None and not self.max_jump > 0:
            problems.append(f"max_jump must be > 0 m (or None), got {self.max_jump}")
        if self.background_frames is not None and not self.background_frames:
            problems.append("background_frames must name at least one frame (or be None)")
        if problems:
            raise ValueError("; ".join(problems))


def background_image(folder: Path, camera_id: str) -> Path | None:
    """The background image of ``camera_id`` in ``folder`` (``<camera id>.png``, ``.jpg`` or
    ``.jpeg``), or None. The one naming rule of this segmenter's ``background_dir`` and of a
    recording's clean plates (``mosiv data import --background``)."""
    for suffix in (".png", ".jpg", ".jpeg"):
        path = Path(folder) / f"{camera_id}{suffix}"
        if path.is_file():
            return path
    return None


def _read_background(folder: Path, camera_id: str, shape: tuple[int, ...]) -> np.ndarray:
    import imageio.v3 as iio  # lazy: image I/O only when a background folder is given

    path = background_image(folder, camera_id)
    if path is not None:
        image = np.asarray(iio.imread(path))[..., :3]
        if image.shape != shape:
            raise ConfigError(
                f"background_dir: {path} is {list(image.shape)}, the camera's frames are "
                f"{list(shape)}"
            )
        return image.astype(np.float32)
    raise ConfigError(
        f"background_dir: {folder} has no image for camera {camera_id!r} "
        f"(expected {camera_id}.png or {camera_id}.jpg)"
    )


class ClassicalSegmenter(Segmenter):
    """Background subtraction + voxel hull + tracking (see the module docstring)."""

    def __init__(self, **options):
        self.options = ClassicalOptions(**options)

    def backgrounds(self, frames: Frames) -> dict[str, np.ndarray]:
        """Background image of every camera, float32 [H, W, 3]: background_dir, else the
        clean plates the frames come with, else a temporal median."""
        opts = self.options
        if opts.background_dir is None and frames.backgrounds:
            missing = sorted(set(frames.rgb) - set(frames.backgrounds))
            if missing:
                raise ConfigError(f"no background image for camera(s) {', '.join(missing)}")
            return {cam: plate.astype(np.float32) for cam, plate in frames.backgrounds.items()}
        if opts.background_dir is not None:
            folder = Path(opts.background_dir)
            if not folder.is_dir():
                raise ConfigError(f"background_dir: {folder} is not a folder")
            return {
                cam: _read_background(folder, cam, video.shape[1:])
                for cam, video in frames.rgb.items()
            }
        if opts.background_frames is not None:
            bad = [i for i in opts.background_frames if not 0 <= i < frames.n_frames]
            if bad:
                raise ConfigError(
                    f"background_frames {bad} lie outside the clip's frames 0..{frames.n_frames - 1}"
                )
        return {  # over the frames each camera recorded
            cam: fgmod.estimate_background(video, _background_frames(frames, cam, opts))
            for cam, video in frames.rgb.items()
        }

    def foregrounds(self, frames: Frames, *, packed: bool = False) -> dict[str, np.ndarray]:
        """Cleaned foreground of every camera, bool [T, H, W] (empty at a frame the camera did
        not record: ``segment`` leaves those views out of the hull). ``packed``: each camera's
        as ``np.packbits`` along the rows, uint8 [T, H, ceil(W / 8)] (``_unpacked`` reads a
        frame back), an eighth of the memory: every camera's is held while the hull is carved."""
        opts = self.options
        out = {}
        for cam, background in self.backgrounds(frames).items():
            span = _span(frames, cam)
            mask = np.zeros(frames.rgb[cam].shape[:3], dtype=bool)
            mask[span], _ = fgmod.foreground(
                frames.rgb[cam][span],
                background,
                threshold=opts.threshold,
                min_threshold=opts.min_threshold,
                open_px=opts.open_px,
                close_px=opts.close_px,
                auto=opts.auto_threshold,
                edge_fraction=opts.edge_fraction,
            )
            out[cam] = np.packbits(mask, axis=-1) if packed else mask
        return out

    def segment(self, frames: Frames) -> dict[str, np.ndarray]:
        if frames.domain is None:
            raise ConfigError(
                "the classical segmenter carves a visual hull and needs the domain box that "
                "holds the objects (Frames.domain; scene.json's domain)"
            )
        opts = self.options
        cams = frames.camera_ids
        fg = self.foregrounds(frames, packed=True)
        width = {c: frames.rgb[c].shape[2] for c in cams}
        grid = hull.VoxelGrid.over(frames.domain, opts.voxels)
        centres = grid.centres()
        tables = [hull.project_grid(grid, frames.cameras[c]) for c in cams]
        parts = []
        for t in range(frames.n_frames):
            views = [i for i, c in enumerate(cams) if t in frames.recorded(c)]
            occupied = hull.carve(
                [tables[i] for i in views],
                [_unpacked(fg[cams[i]], t, width[cams[i]]) for i in views],
                view_tolerance=opts.view_tolerance,
            )
            parts.append(hull.components(occupied, grid.shape, opts.min_voxels))
        history = track.track(parts, centres, frames.n_objects, opts.max_jump)
        n_found = max((len(objects) for objects in history), default=0)
        if n_found > 255:
            raise ConfigError(
                f"{n_found} objects found; masks hold at most 255 (set n_objects or "
                "raise min_voxels)"
            )
        masks = {}
        for cam, table in zip(cams, tables):
            video = np.zeros(frames.rgb[cam].shape[:3], dtype=np.uint8)
            for t, objects in enumerate(history):
                if not objects:
                    continue
                voxels = np.concatenate(objects)
                labels = np.concatenate(
                    [np.full(v.size, k, dtype=np.uint8) for k, v in enumerate(objects, 1)]
                )
                video[t] = hull.paint(table, _unpacked(fg[cam], t, width[cam]), voxels, labels)
            recorded = np.zeros(len(video), dtype=bool)
            recorded[_span(frames, cam)] = True
            video[~recorded] = 0  # no mask where the camera recorded no image
            masks[cam] = video
        return masks


def _unpacked(packed: np.ndarray, t: int, width: int) -> np.ndarray:
    """Frame ``t`` of a packed foreground (``foregrounds(packed=True)``), bool [H, W]."""
    return np.unpackbits(packed[t], axis=-1, count=width).astype(bool)


def _background_frames(frames: Frames, camera_id: str, opts: ClassicalOptions) -> list[int]:
    """The frames of ``camera_id`` its temporal median uses: background_frames (or every
    frame), less those the camera did not record."""
    recorded = frames.recorded(camera_id)
    wanted = recorded if opts.background_frames is None else opts.background_frames
    use = [t for t in wanted if t in recorded]
    if not use:
        raise ConfigError(
            f"background_frames {opts.background_frames}: camera {camera_id!r} recorded none "
            f"of them (it recorded frames {recorded.start}..{recorded.stop - 1})"
        )
    return use


def _span(frames: Frames, camera_id: str) -> slice:
    """The frames ``camera_id`` recorded, as a slice of its video."""
    recorded = frames.recorded(camera_id)
    return slice(recorded.start, recorded.stop)
