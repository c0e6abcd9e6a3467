"""The ``sam2`` segmenter: SAM2's video predictor, prompted and identified by the hull.

The classical segmenter (``mosiv_framework.segment``) runs first. Its masks give, for each
camera and object id k, a prompt on the first frame in which the object shows in that camera
(a box around its hull mask, and/or the point deepest inside it); SAM2 then propagates every
object through that camera's video. SAM2's object id is the hull's id, so object k is the same
object in every camera. Where SAM2's masks overlap, the object with the larger logit wins.
"""

from __future__ import annotations

import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from scipy import ndimage

from mosiv_framework.errors import ConfigError, StageNotAvailable
from mosiv_framework.interfaces import Segmenter
from mosiv_framework.types import Frames

INSTALL = "pip install sam2  (or: pip install -e 'plugins/mosiv-sam2[sam2]')"
PROMPTS = ("box", "point", "box+point")


@dataclass
class Sam2Options:
    """checkpoint: path of a SAM2 checkpoint (.pt) on this machine; never downloaded;
    config: SAM2 model config matching the checkpoint, as SAM2's build_sam2_video_predictor
    takes it (e.g. configs/sam2.1/sam2.1_hiera_l.yaml for sam2.1_hiera_large.pt);
    device: torch device for SAM2 (auto: cuda when available, else cpu);
    prompt: what each object is prompted with, one of box, point, box+point (the box around the
    hull mask, the mask pixel farthest from its edge);
    min_prompt_pixels: an object is prompted on the first frame whose hull mask has at least
    this many pixels in that camera;
    classical: options of the classical segmenter that gives the prompts and ids (e.g.
    background_dir); see mosiv plugins --options segmenter:classical."""

    checkpoint: str | None = None
    config: str | None = None
    device: str = "auto"
    prompt: str = "box"
    min_prompt_pixels: int = 16
    classical: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.prompt not in PROMPTS:
            raise ValueError(f"prompt must be one of {', '.join(PROMPTS)}, got {self.prompt!r}")
        if self.min_prompt_pixels < 1:
            raise ValueError(f"min_prompt_pixels must be >= 1, got {self.min_prompt_pixels}")


def _check_paths(opts: Sam2Options) -> None:
    problems = []
    if not opts.checkpoint:
        problems.append("segmenter 'sam2' option checkpoint: give the path of a SAM2 checkpoint")
    elif not Path(opts.checkpoint).expanduser().is_file():
        problems.append(
            f"segmenter 'sam2' option checkpoint: {opts.checkpoint} is not a file "
            "(SAM2 checkpoints are not downloaded; point to one you have)"
        )
    if not opts.config:
        problems.append(
            "segmenter 'sam2' option config: give the SAM2 model config of the checkpoint, "
            "e.g. configs/sam2.1/sam2.1_hiera_l.yaml"
        )
    if problems:
        raise ConfigError(problems)


def _build_predictor(opts: Sam2Options):
    """SAM2's video predictor from the user's checkpoint and config (imports sam2)."""
    import torch
    from sam2.build_sam import build_sam2_video_predictor

    device = opts.device
    if device == "auto":
        device = "cuda" if torch.cuda.is_available() else "cpu"
    return build_sam2_video_predictor(
        opts.config, str(Path(opts.checkpoint).expanduser()), device=device
    )


class Sam2Segmenter(Segmenter):
    """SAM2 video masks with the classical hull's prompts and ids (see the module docstring).

    ``predictor`` (not an option) replaces SAM2's video predictor with any object of the same
    methods (init_state, add_new_points_or_box, propagate_in_video, reset_state); without it
    the checkpoint and config are checked and the ``sam2`` package imported here.
    """

    def __init__(self, *, predictor=None, **options):
        from mosiv_framework.registry import get_registry

        self.options = Sam2Options(**options)
        self._predictor = predictor
        if predictor is None:
            _check_paths(self.options)
            try:
                import sam2  # noqa: F401  (only to say early that it is missing)
            except ImportError as exc:
                raise StageNotAvailable(
                    f"the sam2 segmenter needs the sam2 package ({exc}); install it: {INSTALL}"
                ) from None
        self.classical = get_registry().create("segmenter", "classical", self.options.classical)

    @property
    def predictor(self):
        if self._predictor is None:
            self._predictor = _build_predictor(self.options)
        return self._predictor

    def segment(self, frames: Frames) -> dict[str, np.ndarray]:
        hull_masks = self.classical.segment(frames)
        out = {}
        with tempfile.TemporaryDirectory(prefix="mosiv-sam2-") as tmp:
            for cam in frames.camera_ids:
                folder = Path(tmp) / cam
                span = frames.recorded(cam)  # SAM2 sees only the frames the camera recorded
                span = slice(span.start, span.stop)
                write_jpeg_frames(frames.rgb[cam][span], folder)
                out[cam] = np.zeros_like(hull_masks[cam])
                out[cam][span] = self._segment_camera(folder, hull_masks[cam][span])
        return out

    def _segment_camera(self, folder: Path, hull: np.ndarray) -> np.ndarray:
        """One camera: prompt every object the hull shows, propagate, combine by logit."""
        predictor = self.predictor
        masks = np.zeros(hull.shape, dtype=np.uint8)
        prompts = object_prompts(hull, self.options.min_prompt_pixels)
        if not prompts:
            return masks
        state = predictor.init_state(video_path=str(folder))
        for obj_id, (frame, box, point) in prompts.items():
            kwargs = {}
            if "box" in self.options.prompt:
                kwargs["box"] = box
            if "point" in self.options.prompt:
                kwargs["points"] = point[None]
                kwargs["labels"] = np.ones(1, dtype=np.int32)
            predictor.add_new_points_or_box(
                inference_state=state, frame_idx=frame, obj_id=obj_id, **kwargs
            )
        for frame, obj_ids, logits in predictor.propagate_in_video(state):
            masks[frame] = combine_logits(obj_ids, logits, hull.shape[1:])
        predictor.reset_state(state)
        return masks


def write_jpeg_frames(video: np.ndarray, folder: Path) -> None:
    """The frames as ``00000.jpg``, ``00001.jpg``... , the folder layout SAM2's init_state reads."""
    import imageio.v3 as iio

    folder.mkdir(parents=True)
    for t, image in enumerate(video):
        iio.imwrite(folder / f"{t:05d}.jpg", image, extension=".jpg", quality=95)


def object_prompts(hull: np.ndarray, min_pixels: int) -> dict[int, tuple]:
    """Object id -> (frame, box [x0, y0, x1, y1] in pixels, point [x, y]) from one camera's hull
    masks uint8 [T, H, W]: the first frame where the object covers ``min_pixels``, the box
    around it there (pixel edges) and its pixel farthest from the mask's edge (the centre of
    that pixel), which lies inside the object even for a non-convex mask."""
    prompts = {}
    for obj_id in (int(k) for k in np.unique(hull) if k):
        areas = (hull == obj_id).reshape(hull.shape[0], -1).sum(1)
        frames = np.flatnonzero(areas >= min_pixels)
        if frames.size == 0:
            continue
        frame = int(frames[0])
        mask = hull[frame] == obj_id
        rows, cols = np.nonzero(mask)
        box = np.array([cols.min(), rows.min(), cols.max() + 1, rows.max() + 1], dtype=np.float32)
        depth = ndimage.distance_transform_edt(np.pad(mask, 1))[1:-1, 1:-1]
        row, col = np.unravel_index(int(np.argmax(depth)), mask.shape)
        prompts[obj_id] = (frame, box, np.array([col + 0.5, row + 0.5], dtype=np.float32))
    return prompts


def combine_logits(obj_ids, logits, shape: tuple[int, int]) -> np.ndarray:
    """Instance mask uint8 [H, W] from SAM2's per-object logits [n, 1, H, W] (torch or numpy):
    a pixel belongs to the object of largest logit among those above 0."""
    values = logits.detach().float().cpu().numpy() if hasattr(logits, "detach") else logits
    values = np.asarray(values, dtype=np.float32).reshape(len(obj_ids), *shape)
    best = np.argmax(values, axis=0)
    ids = np.asarray(list(obj_ids), dtype=np.uint8)
    return np.where(values.max(axis=0) > 0.0, ids[best], 0).astype(np.uint8)
