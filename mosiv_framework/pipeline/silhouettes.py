"""Silhouettes of simulated particles, so the silhouette losses (paper eq. 3) can run.

Simulated states are point sets; the silhouette losses compare per-object alpha images with the
recorded instance masks. ``splat_alpha`` draws each particle as an isotropic Gaussian footprint
of its own size through a scene camera and turns the summed footprint density into a soft
occupancy, differentiable in the particle positions. ``SilhouetteObjective`` wraps the recipe's
weighted losses and attaches simulated and recorded silhouettes to the geometry it compares.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from mosiv_framework.losses import WeightedSum
from mosiv_framework.scene.cameras import Camera
from mosiv_framework.types import GeometryFrames, ParticleSet

#: registered loss names that compare silhouettes rather than points
SILHOUETTE_LOSSES = ("silhouette", "scene-silhouette")


def splat_alpha(points: torch.Tensor, radius: float, camera: Camera, size: int) -> torch.Tensor:
    """Soft silhouette [size, size] in [0, 1] of ``points`` [N, 3] (m) seen by ``camera``.

    Each point is a sphere of ``radius`` (m), drawn as a 2D Gaussian of standard deviation
    sigma = f r / z pixels (its projected radius); alpha = 1 - exp(-sum_i G_i(pixel)), the
    occupancy of a Poisson field of footprints: ~1 where footprints pile up inside an object,
    falling off smoothly at its outline. The image is the camera's, resampled to size x size.
    """
    su, sv = size / camera.width, size / camera.height  # the image resampled to size x size
    uv, z = camera.project(points)
    front = z > 1e-6
    uv, z = uv[front], z[front]
    sigma_u = (camera.fx * su * radius / z).clamp(min=0.5)[:, None]  # at least half a pixel
    sigma_v = (camera.fy * sv * radius / z).clamp(min=0.5)[:, None]
    centres = torch.arange(size, dtype=points.dtype, device=points.device)[None, :] + 0.5
    # separable Gaussians: exp(-(du^2 + dv^2) / 2 s^2) = exp(-du^2 / 2 s^2) exp(-dv^2 / 2 s^2)
    gu = torch.exp(-((centres - uv[:, :1] * su) ** 2) / (2 * sigma_u**2))
    gv = torch.exp(-((centres - uv[:, 1:] * sv) ** 2) / (2 * sigma_v**2))
    density = gv.T @ gu  # [rows v, columns u]
    return 1.0 - torch.exp(-density)


def particle_radius(particles: ParticleSet, object_id: int) -> float:
    """Radius (m) of a sphere with the mean rest volume of one object's particles."""
    volumes = particles.volumes[particles.object_ids == object_id]
    return float((3.0 * volumes.mean() / (4.0 * math.pi)) ** (1.0 / 3.0))


def mask_alpha(masks: torch.Tensor, size: int) -> torch.Tensor:
    """Recorded masks [..., H, W] in {0, 1} resampled to [..., size, size] by area averaging."""
    shape = masks.shape
    flat = masks.reshape(-1, 1, shape[-2], shape[-1]).float()
    out = F.interpolate(flat, size=(size, size), mode="area")
    return out.reshape(*shape[:-2], size, size)


class SilhouetteObjective:
    """The recipe's weighted losses with per-object silhouettes attached on both sides.

    Recorded masks (``scene.load_masks``) are the target silhouettes; simulated ones are splats
    of the simulated particles (``splat_alpha``) through the same cameras, at ``size`` pixels.
    Masks are loaded once per frame and kept.
    """

    def __init__(self, objective: WeightedSum, *, scene, particles: ParticleSet, size: int = 48):
        self.objective = objective
        self.terms = objective.terms
        self.weights = objective.weights
        self.scene = scene
        self.size = size
        self.radius = {k: particle_radius(particles, k) for k in particles.object_list}
        self._masks: dict[int, torch.Tensor] = {}

    def _target(self, frames: list[int], objects: list[int]) -> dict[int, torch.Tensor]:
        for f in frames:
            if f not in self._masks:  # [C, K, size, size]
                self._masks[f] = mask_alpha(self.scene.load_masks(frames=[f])[0], self.size)
        index = {o.id: i for i, o in enumerate(self.scene.objects)}
        return {k: torch.stack([self._masks[f][:, index[k]] for f in frames]) for k in objects}

    def render(self, geometry: GeometryFrames) -> dict[int, torch.Tensor]:
        """Object id -> [F, C, size, size] simulated alpha for every frame and camera."""
        out = {}
        for k in geometry.object_list:
            out[k] = torch.stack(
                [
                    torch.stack(
                        [
                            splat_alpha(pts, self.radius[k], cam, self.size)
                            for cam in self.scene.cameras
                        ]
                    )
                    for pts in geometry.points[k]
                ]
            )
        return out

    def evaluate(self, predicted: GeometryFrames, target: GeometryFrames):
        predicted = GeometryFrames(predicted.frames, predicted.points, self.render(predicted))
        device = next(iter(predicted.silhouettes.values())).device
        masks = self._target(target.frames, target.object_list)
        target = GeometryFrames(
            target.frames, target.points, {k: m.to(device) for k, m in masks.items()}
        )
        return self.objective.evaluate(predicted, target)

    def __call__(self, predicted: GeometryFrames, target: GeometryFrames) -> torch.Tensor:
        return self.evaluate(predicted, target)[0]
