"""Images of a rollout for PSNR/SSIM: the lifted Gaussians carried by the simulated particles.

A lifter that binds Gaussians to its particles (the ``gaussians`` lifter) attaches to
``ParticleSet.appearance`` an object with ``binding`` (``gaussian_frames(positions)``: the
Gaussians at a particle state), ``background`` (camera id -> [H, W, 3] static background, or
None) and ``renderer`` / ``renderer_options`` (the registered renderer it used). This module
renders every frame of a simulated trajectory through every scene camera with them, so the
evaluation can compare against the recorded videos (paper section 4: observed and future PSNR,
SSIM). Particles without a binding (``gt-points``, points only) have no images: PSNR stays None.
The binding is reached by attribute, never by importing the lifter's plugin.
"""

from __future__ import annotations

import numpy as np
import torch

from mosiv_framework.registry import get_registry
from mosiv_framework.types import ParticleSet, Trajectory

Tensor = torch.Tensor


def can_render(particles: ParticleSet) -> bool:
    """Whether ``particles`` carry bound Gaussians and name the renderer to draw them with."""
    appearance = particles.appearance
    return getattr(appearance, "binding", None) is not None and bool(
        getattr(appearance, "renderer", "")
    )


def rollout_images(traj: Trajectory, particles: ParticleSet, scene) -> tuple[list, list, list]:
    """(predicted, recorded, regions): per frame of ``traj``, the images of every scene camera
    that recorded the frame as one batch [C, 3, H, W] in [0, 1] (sRGB; the layout of
    ``metrics.image_metrics``), predicted ones composited over the reconstruction's background (black where it has none
    for a camera), and the object region [C, H, W] bool: pixels inside the recorded instance
    mask or the rendered silhouette (alpha >= 1/2), where the objects' own PSNR is taken."""
    appearance = particles.appearance
    renderer = get_registry().create(
        "renderer", appearance.renderer, dict(getattr(appearance, "renderer_options", {}) or {})
    )
    backgrounds = getattr(appearance, "background", None) or {}
    n_objects = max(scene.object_ids)
    positions = traj.positions.detach().float().cpu()
    n = min(traj.n_frames, scene.n_frames)
    predicted, recorded, regions = [], [], []
    with torch.no_grad():
        for t in range(n):
            gaussians = appearance.binding.gaussian_frames(positions[t])
            views, targets, masks = [], [], []
            for cam in scene.cameras_at(t):
                bg = backgrounds.get(cam.id)
                bg = torch.zeros(cam.height, cam.width, 3) if bg is None else bg.float().cpu()
                out = renderer.render(gaussians, cam, frame=0, n_objects=n_objects, background=bg)
                views.append(out.rgb.clamp(0.0, 1.0).cpu())
                targets.append(torch.from_numpy(scene.rgb(cam.id, t).astype(np.float32) / 255.0))
                recorded_mask = torch.from_numpy(scene.mask(cam.id, t) > 0)
                masks.append(recorded_mask | (out.alpha.cpu() >= 0.5))
            predicted.append(torch.stack(views).permute(0, 3, 1, 2))
            recorded.append(torch.stack(targets).permute(0, 3, 1, 2))
            regions.append(torch.stack(masks))
    return predicted, recorded, regions
