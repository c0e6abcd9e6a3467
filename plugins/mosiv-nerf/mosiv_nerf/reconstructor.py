"""Reconstructor ``nerf-field``: the frame-0 voxel radiance field of every object.

Stage I of the CoupNeRF* baseline. The field (``mosiv_nerf.field``) is fitted once, to frame 0;
later frames are never fitted as fields: the simulated particles carry the frame-0 colours and
densities (the lifter ``nerf-particles``, the renderer ``nerf-grid``). What identification needs
at every frame besides images, the target points whose centroids give the initial velocities,
comes from the masks' visual hull at each frame (``mosiv_nerf.hull``).

The Reconstruction holds: ``points`` (object id -> [T, N, 3] hull points), ``background``
(camera id -> [H, W, 3]), ``extras["nerf_field"]`` (the field's grids, ``VoxelField.state``)
and ``extras["nerf_fit"]`` (loss history, frame-0 PSNR over all pixels and over the objects).
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np
import torch

from mosiv_framework.errors import ConfigError
from mosiv_framework.interfaces import Reconstructor
from mosiv_framework.types import Reconstruction
from mosiv_nerf.field import fit_data, fit_field, hull_field, render_image
from mosiv_nerf.hull import backgrounds, carve, frame_views, hull_points, lattice
from mosiv_nerf.options import NerfFieldOptions
from mosiv_nerf.volume import GridBox

log = logging.getLogger(__name__)


def resolve_device(name: str) -> torch.device:
    """``auto`` -> cuda when available, else cpu; ``cuda`` without a GPU is a ConfigError."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cuda" and not torch.cuda.is_available():
        raise ConfigError("device='cuda' but torch sees no CUDA device; use device=cpu")
    return torch.device(name)


def field_box(scene, options: NerfFieldOptions, device) -> GridBox:
    """The field's lattice: the frame-0 visual hull's bounding box plus ``margin`` voxels,
    ``resolution`` voxels along its longest side, clipped to the domain."""
    grid, coarse = lattice(*scene.domain, options.hull_resolution, device=device)
    labels = carve(grid, *frame_views(scene, 0, device))
    inside = grid[labels > 0]
    if inside.shape[0] == 0:
        raise ConfigError("the frame-0 masks carve an empty visual hull: no field to fit")
    lower = inside.min(dim=0).values - coarse
    upper = inside.max(dim=0).values + coarse
    dom_lo = torch.tensor(scene.domain_lower, dtype=torch.float32, device=device)
    dom_hi = torch.tensor(scene.domain_upper, dtype=torch.float32, device=device)
    lower, upper = torch.maximum(lower, dom_lo), torch.minimum(upper, dom_hi)
    cell = float((upper - lower).max()) / options.resolution
    return GridBox.around(lower, upper, cell, margin=options.margin)


def psnr(a: torch.Tensor, b: torch.Tensor) -> float:
    """PSNR (dB) of images in [0, 1]."""
    mse = float((a - b).square().mean())
    return float("inf") if mse == 0 else -10.0 * float(np.log10(mse))


class NerfFieldReconstructor(Reconstructor):
    """Reconstructor ``nerf-field``; keyword options are those of NerfFieldOptions."""

    def __init__(self, **options):
        self.options = NerfFieldOptions(**options)

    def fit(self, scene, *, run_dir: Path | None = None) -> Reconstruction:
        opts = self.options
        device = resolve_device(opts.device)
        generator = torch.Generator(device=device).manual_seed(opts.seed)
        start = time.perf_counter()
        bgs = backgrounds(scene)
        box = field_box(scene, opts, device)
        field = hull_field(box, *frame_views(scene, 0, device), scene.object_ids)
        data = fit_data(scene, box, bgs, scene.object_ids)
        log.info(
            "nerf-field: %d x %d x %d voxels of %.4g m, %d frame-0 rays cross the box",
            *box.shape,
            box.cell,
            data.origins.shape[0],
        )
        history = fit_field(field, data, opts, generator)
        report = self._report(scene, field, bgs, history, time.perf_counter() - start)
        log.info(
            "nerf-field: frame-0 PSNR %.2f dB (objects %.2f dB) after %d steps",
            report["psnr_db"],
            report["object_psnr_db"],
            opts.iterations,
        )
        cpu_gen = torch.Generator().manual_seed(opts.seed)
        points = hull_points(
            scene,
            nodes=opts.hull_resolution,
            per_object=opts.hull_points,
            generator=cpu_gen,
            device=device,
        )
        return Reconstruction(
            points=points,
            gaussians=None,
            background=bgs,
            extras={"nerf_field": field.state(), "nerf_fit": report},
        )

    def _report(self, scene, field, bgs, history, seconds) -> dict:
        """Frame-0 PSNR of the fitted field, over all pixels and over the masked ones."""
        step = self.options.step_ratio * field.box.cell
        preds, recs, masks = [], [], []
        with torch.no_grad():
            for cam in scene.cameras_at(0):
                out = render_image(
                    field.sample,
                    field.box,
                    cam,
                    n_objects=field.n_objects,
                    step=step,
                    background=bgs[cam.id].to(field.box.lo.device),
                )
                preds.append(out.rgb.clamp(0, 1).cpu())
                recs.append(torch.from_numpy(scene.rgb(cam.id, 0)).float() / 255.0)
                masks.append(torch.from_numpy(scene.mask(cam.id, 0) > 0))
        pred, rec, mask = torch.stack(preds), torch.stack(recs), torch.stack(masks)
        return {
            "psnr_db": psnr(pred, rec),
            "object_psnr_db": psnr(pred[mask], rec[mask]) if bool(mask.any()) else None,
            "loss_first": history[0] if history else None,
            "loss_last": history[-1] if history else None,
            "iterations": len(history),
            "seconds": seconds,
            "voxels": list(field.box.shape),
            "cell_m": field.box.cell,
        }
