"""The ``gauss-dynamic`` reconstructor: scene -> object-aware dynamic Gaussians (Stage I).

``fit`` runs: visual-hull initialisation (``init``), the eq. 1 model (``model``), the motion
prior and eq. 2 training (``train``), and returns a ``Reconstruction`` with, per frame and
object, the Gaussian centres (``points[k]`` [T, N_k, 3], the lifter's input) and the full
``GaussianFrames`` (centres, radii, colours, opacities, object ids), the static per-camera
background, and the training-view scores in ``extras["training"]``.

``save_reconstruction`` / ``load_reconstruction`` store it as ``gaussians.npz`` plus
``reconstruction.json`` in a folder (by default ``<run dir>/gauss-dynamic``), and
``render_silhouettes`` draws per-object silhouettes of a reconstruction for any cameras.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import torch

from mosiv_framework.errors import ConfigError
from mosiv_framework.interfaces import Reconstructor
from mosiv_framework.scene.io import atomic_write_bytes, atomic_write_json
from mosiv_framework.types import GaussianFrames, Reconstruction
from mosiv_gauss.dynamic_options import DynamicGaussOptions
from mosiv_gauss.evaluate import render_views, training_metrics
from mosiv_gauss.init import HullInit, hull_init
from mosiv_gauss.model import DynamicGaussians
from mosiv_gauss.refine import refine_frames
from mosiv_gauss.train import (
    INIT_RADIUS_VOXELS,
    TrainingData,
    estimate_background,
    fit_motion_prior,
    train_dynamic,
)

Tensor = torch.Tensor

#: format tag of reconstruction.json
SAVE_FORMAT = "mosiv-gauss-reconstruction/1"
#: opacity of a freshly seeded Gaussian
INIT_OPACITY = 0.5


def _device(name: str) -> torch.device:
    device = torch.device(name)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ConfigError(
            f"reconstructor gauss-dynamic: device={name!r} but this torch has no CUDA device; "
            "use device=cpu"
        )
    return device


def prepare_training(
    scene, opts: DynamicGaussOptions, device, generator: torch.Generator
) -> tuple[TrainingData, HullInit, Tensor]:
    """What a fit of ``scene`` trains against: (TrainingData on ``device``, the visual-hull
    seeds and tracks, instance ids [T, C, H, W]). Draws the hull seeds from ``generator``."""
    n_objects = len(scene.objects)
    if scene.object_ids != list(range(1, n_objects + 1)):
        raise ValueError(f"scene object ids must be 1..K, got {scene.object_ids}")
    # a view a camera did not record is black and empty here, and ``views`` leaves it out
    rgb = scene.load_rgb_tensor(device=device, missing="zeros")  # [T, C, H, W, 3]
    mask_ids = scene.load_mask_ids(device=device, missing="zeros")  # [T, C, H, W]
    views = None if scene.every_view_recorded else scene.view_mask().to(device)
    ids = torch.arange(1, n_objects + 1, device=device)
    masks = (mask_ids.unsqueeze(2) == ids[:, None, None]).float()  # [T, C, K, H, W]
    seeds = hull_init(
        scene.cameras,
        mask_ids,
        rgb[0],
        lower=scene.domain_lower,
        upper=scene.domain_upper,
        n_objects=n_objects,
        resolution=opts.hull_resolution,
        max_gaussians=opts.max_init_gaussians,
        generator=generator,
        views=views,
    )
    data = TrainingData(
        rgb=rgb,
        masks=masks,
        cameras=list(scene.cameras),
        background=estimate_background(rgb, mask_ids, views),
        voxel_size=seeds.voxel_size,
        tracks=seeds.tracks,
        track_valid=seeds.track_valid,
        hulls=seeds.hulls,
        views=views,
    )
    return data, seeds, mask_ids


class GaussDynamicReconstructor(Reconstructor):
    """Object-aware dynamic Gaussians fitted to a scene's videos and instance masks."""

    def __init__(self, **options) -> None:
        self.options = DynamicGaussOptions(**options)
        #: the trained model of the last ``fit`` (on the training device), for inspection
        self.model: DynamicGaussians | None = None

    def fit(self, scene, *, run_dir: Path | None = None) -> Reconstruction:
        opts = self.options
        device = _device(opts.device)
        start = time.perf_counter()
        generator = torch.Generator().manual_seed(opts.seed)
        n_objects = len(scene.objects)
        data, seeds, mask_ids = prepare_training(scene, opts, device, generator)
        rgb = data.rgb
        n_seeds = len(seeds.means)
        with torch.random.fork_rng(devices=[]):  # network init from the seed, not global state
            torch.manual_seed(opts.seed)
            model = DynamicGaussians(
                means=seeds.means,
                radii=torch.full((n_seeds,), INIT_RADIUS_VOXELS * seeds.voxel_size, device=device),
                colors=seeds.colors,
                opacities=torch.full((n_seeds,), INIT_OPACITY, device=device),
                object_ids=seeds.object_ids,
                n_objects=n_objects,
                n_frames=scene.n_frames,
                lower=scene.domain_lower,
                upper=scene.domain_upper,
                n_bases=opts.n_bases,
                basis_width=opts.basis_width,
                basis_layers=opts.basis_layers,
                coef_width=opts.coef_width,
                coef_layers=opts.coef_layers,
                pe_frequencies=opts.pe_frequencies,
                time_frequencies=opts.time_frequencies,
            )
        motion = fit_motion_prior(
            model,
            seeds.tracks,
            iterations=opts.motion_init_iterations,
            lr=opts.lr_network,
            voxel_size=seeds.voxel_size,
            hulls=seeds.hulls,
            progress=opts.progress,
        )
        history = train_dynamic(model, data, opts, generator=generator)
        self.model = model

        with torch.no_grad():
            gaussians = model.frames()
        refine_loss: list[float] = []
        if opts.refine_iterations > 0:
            gaussians, refine_loss = refine_frames(
                gaussians, data, history.background, opts, generator=generator
            )
        with torch.no_grad():
            scores = training_metrics(
                gaussians,
                data.cameras,
                rgb,
                mask_ids,
                history.background,
                tile_size=opts.tile_size,
                views=data.views,
            )
        extras = {
            "reconstructor": "gauss-dynamic",
            "options": {k: getattr(opts, k) for k in opts.__dataclass_fields__},
            "voxel_size": seeds.voxel_size,
            "n_seeds": n_seeds,
            "n_gaussians": model.n_gaussians,
            "final_loss": history.loss[-1] if history.loss else None,
            "skipped_steps": len(history.skipped_steps),
            "first_skipped_step": history.skipped_steps[0] if history.skipped_steps else None,
            "motion_prior_loss": motion[-1] if motion else None,
            "refine_loss": refine_loss[-1] if refine_loss else None,
            "seconds": time.perf_counter() - start,
            "training": scores,
        }
        recon = to_reconstruction(
            gaussians, history.background, camera_ids=scene.camera_ids, extras=extras
        )
        if run_dir is not None and opts.save_dir:
            save_reconstruction(recon, Path(run_dir) / opts.save_dir)
        return recon


def to_reconstruction(
    gaussians: GaussianFrames, background: Tensor, *, camera_ids, extras: dict
) -> Reconstruction:
    """Detached CPU Reconstruction: ``points[k]`` are object k's Gaussian centres per frame."""
    g = GaussianFrames(
        means=gaussians.means.detach().float().cpu(),
        radii=gaussians.radii.detach().float().cpu(),
        colors=gaussians.colors.detach().float().cpu(),
        opacities=gaussians.opacities.detach().float().cpu(),
        object_ids=gaussians.object_ids.detach().long().cpu(),
    )
    points = {int(k): g.means[:, g.object_ids == k] for k in g.object_ids.unique().tolist()}
    bg = {cid: background[c].detach().float().cpu() for c, cid in enumerate(camera_ids)}
    return Reconstruction(points=points, gaussians=g, background=bg, extras=dict(extras))


def save_reconstruction(reconstruction: Reconstruction, folder: str | Path) -> Path:
    """Write ``gaussians.npz`` and ``reconstruction.json`` into ``folder`` (created); returns it.

    ``extras`` must be JSON-serialisable (numbers, strings, lists, dicts).
    """
    folder = Path(folder)
    arrays: dict[str, np.ndarray] = {}
    for k, pts in reconstruction.points.items():
        arrays[f"points_{int(k)}"] = pts.detach().cpu().numpy().astype(np.float32)
    g = reconstruction.gaussians
    if g is not None:
        arrays["means"] = g.means.detach().cpu().numpy().astype(np.float32)
        arrays["radii"] = g.radii.detach().cpu().numpy().astype(np.float32)
        arrays["colors"] = g.colors.detach().cpu().numpy().astype(np.float32)
        arrays["opacities"] = g.opacities.detach().cpu().numpy().astype(np.float32)
        arrays["object_ids"] = g.object_ids.detach().cpu().numpy().astype(np.int64)
    cams = list(reconstruction.background or {})
    for i, cid in enumerate(cams):
        arrays[f"background_{i}"] = reconstruction.background[cid].detach().cpu().numpy()
    import io

    buffer = io.BytesIO()
    np.savez_compressed(buffer, **arrays)
    atomic_write_bytes(folder / "gaussians.npz", buffer.getvalue())
    atomic_write_json(
        folder / "reconstruction.json",
        {
            "format": SAVE_FORMAT,
            "objects": [int(k) for k in reconstruction.object_list],
            "has_gaussians": g is not None,
            "background_cameras": cams,
            "extras": reconstruction.extras,
        },
    )
    return folder


def load_reconstruction(folder: str | Path) -> Reconstruction:
    """Read a folder written by :func:`save_reconstruction`; raise ValueError naming the file
    and the problem when it is not one."""
    folder = Path(folder)
    meta_path, npz_path = folder / "reconstruction.json", folder / "gaussians.npz"
    for path in (meta_path, npz_path):
        if not path.is_file():
            raise ValueError(f"{path}: missing; not a saved gauss-dynamic reconstruction")
    meta = json.loads(meta_path.read_text(encoding="utf-8"))
    if meta.get("format") != SAVE_FORMAT:
        raise ValueError(f"{meta_path}: format {meta.get('format')!r}, expected {SAVE_FORMAT!r}")
    with np.load(npz_path, allow_pickle=False) as npz:
        data = {name: torch.from_numpy(np.array(npz[name])) for name in npz.files}
    needed = [f"points_{k}" for k in meta["objects"]]
    if meta["has_gaussians"]:
        needed += ["means", "radii", "colors", "opacities", "object_ids"]
    needed += [f"background_{i}" for i in range(len(meta["background_cameras"]))]
    missing = [n for n in needed if n not in data]
    if missing:
        raise ValueError(f"{npz_path}: lacks arrays {missing}")
    gaussians = None
    if meta["has_gaussians"]:
        gaussians = GaussianFrames(
            means=data["means"],
            radii=data["radii"],
            colors=data["colors"],
            opacities=data["opacities"],
            object_ids=data["object_ids"],
        )
    background = {
        cid: data[f"background_{i}"] for i, cid in enumerate(meta["background_cameras"])
    } or None
    return Reconstruction(
        points={int(k): data[f"points_{k}"] for k in meta["objects"]},
        gaussians=gaussians,
        background=background,
        extras=meta["extras"],
    )


def render_silhouettes(
    reconstruction: Reconstruction,
    cameras,
    *,
    frames=None,
    n_objects: int | None = None,
    tile_size: int = 16,
    device: str | torch.device = "cpu",
) -> dict[int, Tensor]:
    """Per-object silhouettes of a reconstruction: object id -> alpha [F, C, H, W] in [0, 1].

    The layout of ``GeometryFrames.silhouettes``; ``frames`` defaults to every frame, cameras
    must share one resolution; ``n_objects`` defaults to the largest object id present.
    """
    g = reconstruction.gaussians
    if g is None:
        raise ValueError(
            "this reconstruction has no Gaussians (points only, e.g. the oracle); silhouettes "
            "need a reconstructor that fits Gaussians, such as gauss-dynamic"
        )
    n_objects = n_objects or int(g.object_ids.max())
    on_device = GaussianFrames(
        g.means.to(device),
        g.radii.to(device),
        g.colors.to(device),
        g.opacities.to(device),
        g.object_ids.to(device),
    )
    _, alpha = render_views(
        on_device, cameras, n_objects=n_objects, frames=frames, tile_size=tile_size
    )
    return {k + 1: alpha[:, :, k].cpu() for k in range(n_objects)}
