"""Videos and rollout files a person can look at: point clouds drawn through a scene camera.

Each object's particles are splatted (``silhouettes.splat_alpha``) into a soft silhouette and
composited far-to-near over a white background in the object's colour. Videos are GIFs (Pillow,
always available) or MP4s when imageio's ffmpeg plugin is installed.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from mosiv_framework.errors import ConfigError
from mosiv_framework.pipeline.silhouettes import splat_alpha
from mosiv_framework.scene.cameras import Camera
from mosiv_framework.types import Trajectory

#: object colours (RGB in [0, 1]), cycled by object id
PALETTE = np.array(
    [
        [0.12, 0.47, 0.71],
        [1.00, 0.50, 0.05],
        [0.17, 0.63, 0.17],
        [0.84, 0.15, 0.16],
        [0.58, 0.40, 0.74],
        [0.55, 0.34, 0.29],
    ]
)
#: strip on top of each frame: green while the frame was observed, orange in the future
OBSERVED_RGB, FUTURE_RGB = np.array([0.2, 0.7, 0.3]), np.array([0.95, 0.55, 0.1])


def pick_camera(scene, camera_id: str = "") -> Camera:
    """The camera named ``camera_id`` (the first of cameras.json when empty)."""
    if not camera_id:
        return scene.cameras[0]
    try:
        return scene.camera(camera_id)
    except KeyError as exc:
        raise ConfigError(f"evaluate.video_camera={camera_id!r}: {exc.args[0]}") from None


def draw_points(
    per_object: dict[int, torch.Tensor], camera: Camera, *, size: int, radius: float
) -> np.ndarray:
    """One frame: object id -> [N_k, 3] points (m) drawn as uint8 [size, size, 3]."""
    image = np.ones((size, size, 3))
    # far objects first, so nearer ones cover them
    order = sorted(
        per_object, key=lambda k: -float(camera.project(per_object[k].float())[1].mean())
    )
    for k in order:
        alpha = splat_alpha(per_object[k].float(), radius, camera, size).numpy()[..., None]
        colour = PALETTE[(k - 1) % len(PALETTE)]
        image = image * (1 - alpha) + colour * alpha
    return (image * 255).round().clip(0, 255).astype(np.uint8)


def _strip(frame: np.ndarray, observed: bool) -> np.ndarray:
    out = frame.copy()
    out[: max(2, frame.shape[0] // 40)] = (255 * (OBSERVED_RGB if observed else FUTURE_RGB)).astype(
        np.uint8
    )
    return out


def write_video(frames: list[np.ndarray], path: Path, *, fps: float) -> Path:
    """Write uint8 [H, W, 3] frames as a GIF or MP4 (by ``path``'s suffix)."""
    import imageio.v3 as iio

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if path.suffix == ".mp4":
        try:
            import imageio_ffmpeg  # noqa: F401  (the plugin imageio needs for MP4)
        except ImportError:
            raise ConfigError(
                f"{path}: writing MP4 needs the imageio-ffmpeg package; install it or use .gif"
            ) from None
        iio.imwrite(path, np.stack(frames), fps=fps)
    elif path.suffix == ".gif":
        iio.imwrite(path, np.stack(frames), duration=1000.0 / fps, loop=0)
    else:
        raise ConfigError(f"{path}: videos are written as .gif or .mp4, not {path.suffix!r}")
    return path


def _radius(points: dict[int, torch.Tensor]) -> float:
    """A drawing radius (m): half the typical spacing of the largest object's points."""
    biggest = max(points.values(), key=lambda p: p.shape[-2])
    pts = biggest[0] if biggest.ndim == 3 else biggest
    extent = float((pts.max(0).values - pts.min(0).values).max())
    return 0.5 * extent / max(1.0, pts.shape[0] ** (1.0 / 3.0))


def write_rollout_video(
    traj: Trajectory,
    *,
    camera: Camera,
    path: Path,
    size: int = 256,
    fps: float = 24.0,
    observed_frames: int | None = None,
) -> Path:
    """Every frame of a rollout, per-object colours, through ``camera``."""
    per_object = {
        int(k): traj.object_positions(int(k)).detach().cpu() for k in traj.object_ids.unique()
    }
    radius = _radius(per_object)
    frames = []
    for t in range(traj.n_frames):
        frame = draw_points(
            {k: p[t] for k, p in per_object.items()}, camera, size=size, radius=radius
        )
        frames.append(frame if observed_frames is None else _strip(frame, t < observed_frames))
    return write_video(frames, path, fps=fps)


def write_comparison_video(
    traj: Trajectory,
    reference: dict[int, torch.Tensor],
    *,
    camera: Camera,
    path: Path,
    size: int = 256,
    fps: float = 24.0,
    observed_frames: int,
) -> Path:
    """Reference (left) beside prediction (right), frame by frame through ``camera``; the strip
    on top is green on observed frames and orange on future ones."""
    predicted = {k: traj.object_positions(k).detach().cpu() for k in reference}
    n = min(traj.n_frames, min(r.shape[0] for r in reference.values()))
    radius = _radius(predicted)
    frames = []
    for t in range(n):
        left = draw_points(
            {k: r[t] for k, r in reference.items()}, camera, size=size, radius=radius
        )
        right = draw_points(
            {k: p[t] for k, p in predicted.items()}, camera, size=size, radius=radius
        )
        gap = np.full((size, max(2, size // 64), 3), 96, np.uint8)
        frames.append(_strip(np.concatenate([left, gap, right], axis=1), t < observed_frames))
    return write_video(frames, path, fps=fps)


def save_rollout_npz(traj: Trajectory, path: Path, **extra) -> Path:
    """A rollout as ``obj_<k>`` [T, N_k, 3] arrays (the layout of gt/points.npz) plus ``fps``."""
    arrays = {
        f"obj_{int(k)}": traj.object_positions(int(k)).detach().cpu().numpy().astype(np.float32)
        for k in traj.object_ids.unique().tolist()
    }
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.tmp.npz")
    np.savez_compressed(tmp, fps=np.float64(traj.fps), **arrays, **extra)
    tmp.replace(path)
    return path
