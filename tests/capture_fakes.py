"""The capture that the import tests read: two spheres rendered by four cameras (a scene), written
as a rig delivers it (videos through a known lens, COLMAP text cameras in cm with y up, cameras
that started late), and the helpers the tests share (import settings, PSNR, an expected error).
Used by tests/test_import.py and tests/test_import_time_offsets.py.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from mosiv_framework.capture import ImportSettings, RigFrame, import_recording
from mosiv_framework.capture.colmap import write_colmap
from mosiv_framework.capture.lens import Distortion, Intrinsics, distort_frames
from mosiv_framework.scene import SceneObject, read_scene, write_scene
from mosiv_framework.scene.example import _render, example_cameras

SIZE, N_FRAMES, REST = 96, 28, 6
RADIUS, SPEED = 0.1, 0.03  # m, m per frame
LENS = Distortion(k1=-0.08, k2=0.01, p1=0.001, p2=-0.0005)
LATE = {"cam_01": 2, "cam_03": 1}  # cameras that started late: leading frames they lack
RIG = RigFrame(units="cm", up="y")  # the capture's world: scene (x, y, z) -> rig (x, z, -y) * 100


def sphere_paths() -> np.ndarray:
    """[T, 2, 3] centres: two spheres at rest on the ground for REST frames, then sliding."""
    t = np.clip(np.arange(N_FRAMES) - (REST - 1), 0, None)[:, None]
    a = np.array([-0.2, -0.35, RADIUS]) + t * np.array([0.0, SPEED, 0.0])
    b = np.array([0.2, 0.33, RADIUS]) + t * np.array([0.0, -SPEED, 0.0])
    return np.stack([a, b], axis=1)


def render_spheres(folder: Path, name: str, centres: np.ndarray) -> Path:
    """The two spheres (red elastic, blue sand) along ``centres`` [T, 2, 3] seen by four
    cameras, written as a scene into ``folder``."""
    cameras = example_cameras(n_cameras=4, size=SIZE)
    paths = torch.as_tensor(centres)
    radii = torch.tensor([RADIUS, RADIUS], dtype=torch.float64)
    albedos = torch.tensor([(0.8, 0.15, 0.1), (0.1, 0.25, 0.8)], dtype=torch.float64)
    rgb, masks = {}, {}
    for cam in cameras:
        o, d = cam.rays(dtype=torch.float64)
        frames = [_render(o, d, paths[t], radii, albedos) for t in range(N_FRAMES)]
        rgb[cam.id] = np.stack([f[0] for f in frames])
        masks[cam.id] = np.stack([f[1] for f in frames])
    return write_scene(
        folder,
        name=name,
        fps=24.0,
        objects=[SceneObject(1, "a", "elastic"), SceneObject(2, "b", "sand")],
        cameras=cameras,
        rgb=rgb,
        masks=masks,
        domain_lower=(-0.5, -0.5, 0.0),
        domain_upper=(0.5, 0.5, 1.0),
    )


def intrinsics(cam) -> Intrinsics:
    return Intrinsics(cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy)


def write_model(folder: Path, cameras) -> None:
    names = [f"{cam.id}.mp4" for cam in cameras]
    write_colmap(folder, cameras, names=names, distortion=LENS, rig=RIG)


def write_capture(scene_dir: Path, out: Path, late=LATE, drop_video: str | None = None) -> Path:
    import imageio.v2 as iio2

    scene = read_scene(scene_dir)
    (out / "videos").mkdir(parents=True)
    for cam in scene.cameras:
        if cam.id == drop_video:
            continue
        frames = np.stack([scene.rgb(cam.id, t) for t in range(late.get(cam.id, 0), N_FRAMES)])
        frames = distort_frames(frames, intrinsics(cam), LENS)
        iio2.mimwrite(out / "videos" / f"{cam.id}.mp4", list(frames), fps=24, quality=10)
    write_model(out / "sparse" / "0", scene.cameras)
    return out


def settings(capture: Path, out: Path, **kw) -> ImportSettings:
    base = dict(
        out=out, frames_dir=capture / "videos", colmap=capture / "sparse" / "0",
        materials="elastic,sand", units="cm", up="y", ground="y=0",
    )  # fmt: skip
    base.update(kw)
    return ImportSettings(**base)


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2)
    return float(10 * np.log10(255.0**2 / mse))


def expect_error(s: ImportSettings, error, *words: str) -> None:
    with pytest.raises(error) as info:
        import_recording(s)
    message = str(info.value)
    for word in words:
        assert word in message, (word, message)
    assert not s.out.exists()  # everything is checked before OUT is created
