"""What ``mosiv export`` reads from a finished run folder.

A run folder (docs/ARCHITECTURE.md) holds, among others: ``rollout.pt`` (``positions`` [T, N, 3]
m in the order of the lifted particles, ``object_ids`` [N]) and ``rollout.npz`` (``obj_<k>``
[T, N_k, 3] and ``fps``), written by the evaluate stage; ``particles.pt`` (the lifted
``ParticleSet``: rest volumes, and, from the ``gaussians`` lifter, Gaussians bound to the
particles in ``appearance.binding``); ``reconstruction.pt`` (Stage I's ``Reconstruction``,
with dynamic Gaussians from ``gauss-dynamic``); ``identified.json``, ``metrics.json`` and
``recipe.yaml`` (whose ``scene.path`` gives the scene's fps and observed frames).
"""

from __future__ import annotations

import logging
import shlex
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from mosiv_framework.errors import ConfigError
from mosiv_framework.pipeline.formats import FormatError

log = logging.getLogger(__name__)


@dataclass
class RunData:
    """A run's rollout and what goes with it. positions [T, N, 3] m; object_ids [N];
    volumes [N] m^3 or None; particles / reconstruction: the run's objects or None."""

    root: Path
    positions: np.ndarray
    object_ids: np.ndarray
    fps: float
    volumes: np.ndarray | None
    particles: object | None
    reconstruction: object | None
    observed_frames: int | None
    scene_note: str
    identified: dict | None
    metrics: dict | None

    @property
    def n_frames(self) -> int:
        return self.positions.shape[0]

    @property
    def object_list(self) -> list[int]:
        return sorted(int(k) for k in np.unique(self.object_ids))

    def velocities(self) -> np.ndarray:
        """[T, N, 3] m/s by finite differences of the positions, second-order (central inside,
        three-point at the ends, so exact for motion of constant acceleration): the rollout
        files store positions only."""
        if self.n_frames < 2:
            return np.zeros_like(self.positions)
        order = 2 if self.n_frames >= 3 else 1
        return np.gradient(
            self.positions.astype(np.float64), 1.0 / self.fps, axis=0, edge_order=order
        )


def _load_torch(path: Path, what: str):
    """A torch pickle of the run, or None (with a log line) when it cannot be read, e.g. when
    the plugin whose classes it holds is not installed."""
    if not path.is_file():
        return None
    try:
        return torch.load(path, weights_only=False, map_location="cpu")
    except Exception as exc:  # noqa: BLE001 -- an unpicklable extra must not stop the export
        log.warning("%s: not read (%s: %s); %s left out", path, type(exc).__name__, exc, what)
        return None


def _load_json(root: Path, name: str) -> dict | None:
    from mosiv_framework.pipeline.rundir import RunDir

    if not (root / name).is_file():
        return None
    return RunDir(root).load_json(name)


def _rollout(root: Path, particles) -> tuple[np.ndarray, np.ndarray, float | None]:
    """(positions [T, N, 3], object_ids [N], fps or None) from rollout.pt or rollout.npz."""
    npz_path, pt_path = root / "rollout.npz", root / "rollout.pt"
    fps = None
    if npz_path.is_file():
        try:
            with np.load(npz_path) as data:
                fps = float(data["fps"]) if "fps" in data else None
                per_object = {int(k[4:]): data[k] for k in data.files if k.startswith("obj_")}
        except (OSError, ValueError) as exc:
            raise FormatError(f"{npz_path}: cannot be read as an npz archive ({exc})") from None
    if pt_path.is_file():
        data = _load_torch(pt_path, "the rollout of rollout.pt")
        if isinstance(data, dict) and "positions" in data and "object_ids" in data:
            return data["positions"].numpy(), data["object_ids"].numpy(), fps
    if not npz_path.is_file():
        raise FormatError(
            f"{pt_path}: not a rollout (a dict of positions and object_ids) and rollout.npz is "
            "missing; rerun the evaluate stage (`mosiv eval RUN`)"
        )
    if not per_object:
        raise FormatError(f"{npz_path}: no obj_<k> arrays (the layout of save_rollout_npz)")
    ids = None if particles is None else particles.object_ids.numpy()
    if ids is not None and all(int((ids == k).sum()) == a.shape[1] for k, a in per_object.items()):
        # the lifted particles' order, so volumes and bound Gaussians line up with the rollout
        positions = np.empty((next(iter(per_object.values())).shape[0], len(ids), 3), np.float32)
        for k, arr in per_object.items():
            positions[:, ids == k] = arr
        return positions, ids, fps
    order = sorted(per_object)
    positions = np.concatenate([per_object[k] for k in order], axis=1)
    ids = np.concatenate([np.full(per_object[k].shape[1], k) for k in order])
    return positions, ids, fps


def _scene_info(root: Path) -> tuple[float | None, int | None, str]:
    """(fps, observed_frames, a note on where they came from) from the run's scene."""
    from omegaconf import OmegaConf

    from mosiv_framework.scene import read_scene

    recipe = root / "recipe.yaml"
    if not recipe.is_file():
        return None, None, f"{recipe} is missing"
    scene_path = OmegaConf.select(OmegaConf.load(recipe), "scene.path")
    if scene_path is None:
        return None, None, f"{recipe} names no scene.path"
    for candidate in (Path(scene_path), root / scene_path):
        if (candidate / "scene.json").is_file():
            scene = read_scene(candidate)
            return scene.fps, scene.observed_frames, f"scene {candidate}"
    return None, None, f"the run's scene {scene_path!r} (recipe.yaml scene.path) is not found"


def load_run(path: str | Path) -> RunData:
    """Read the run folder at ``path`` (ConfigError naming what is missing when it is not one)."""
    root = Path(path)
    if not root.is_dir():
        state = "is a file, not a folder" if root.exists() else "does not exist"
        raise ConfigError(f"run folder {str(path)!r} {state}; give a folder written by `mosiv run`")
    if not any((root / n).is_file() for n in ("rollout.npz", "rollout.pt")):
        present = [
            n for n in ("recipe.yaml", "identified.json", "metrics.json") if (root / n).is_file()
        ]
        from mosiv_framework.pipeline.novel import REQUIRED

        if all((root / n).is_file() for n in REQUIRED):  # what `mosiv eval` starts from
            hint = (
                f"it has {', '.join(present)}, so `mosiv eval {shlex.quote(str(root))}` writes "
                "the rollout again (the evaluate stage stopped before saving it, or the file "
                "was removed)"
            )
        elif present:
            hint = f"it has {', '.join(present)}: the run did not finish; rerun `mosiv run`"
        else:
            hint = "it is not a run folder (no recipe.yaml either)"
        raise ConfigError(f"run folder {str(root)!r} holds no rollout.npz or rollout.pt; {hint}")
    particles = _load_torch(root / "particles.pt", "particle volumes and bound Gaussians")
    positions, ids, fps = _rollout(root, particles)
    if particles is not None and len(particles) != len(ids):
        log.warning(
            "particles.pt has %d particles, the rollout %d; not used", len(particles), len(ids)
        )
        particles = None
    scene_fps, observed, note = _scene_info(root)
    fps = fps if fps is not None else scene_fps
    if fps is None:
        raise ConfigError(f"{root}: the frame rate is unknown: rollout.npz is missing and {note}")
    return RunData(
        root=root,
        positions=np.asarray(positions, dtype=np.float32),
        object_ids=np.asarray(ids, dtype=np.int64),
        fps=fps,
        volumes=None if particles is None else particles.volumes.detach().numpy(),
        particles=particles,
        reconstruction=_load_torch(root / "reconstruction.pt", "the reconstruction's Gaussians"),
        observed_frames=observed,
        scene_note=note,
        identified=_load_json(root, "identified.json"),
        metrics=_load_json(root, "metrics.json"),
    )
