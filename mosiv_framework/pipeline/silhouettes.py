"""Silhouettes of simulated particles, so the silhouette losses (paper eq. 3) can run.

Simulated states are point sets; the silhouette losses compare per-object alpha images with the
recorded instance masks. ``splat_alpha`` draws each particle as a smooth square footprint of its
own size through a scene camera and turns the summed footprint density into a soft occupancy
below pixel scale, area-averaged to the image like the masks, differentiable in the particle
positions. ``SilhouetteObjective`` wraps the recipe's
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


#: most sub-pixels per pixel side when a splat is supersampled (bounds time and memory)
MAX_SUPERSAMPLE = 8
#: elements of the [images, N, sub-pixels] footprint profiles built at once (bounds memory)
SPLAT_BATCH_ELEMENTS = 1 << 25
#: width of a footprint's edge, in sub-pixels: sharp enough that the tails of a deep column of
#: particles barely move the outline, soft enough to carry gradients
EDGE_SUBPIXELS = 0.25


def splat_supersample(radius_px: float) -> int:
    """Sub-pixels per pixel side so that a footprint of ``radius_px`` pixels spans at least
    two sub-pixels: the occupancy is then resolved below the pixel and only its area average
    reaches the image, as in the recorded masks (``mask_alpha``)."""
    return int(min(MAX_SUPERSAMPLE, max(1, math.ceil(2.0 / max(radius_px, 1e-6)))))


def _box_profile(offset: torch.Tensor, half_width: torch.Tensor) -> torch.Tensor:
    """A smooth 1D box: ~1 for |offset| < half_width, falling to 0 over EDGE_SUBPIXELS."""
    return torch.sigmoid((half_width - offset) / EDGE_SUBPIXELS) * torch.sigmoid(
        (half_width + offset) / EDGE_SUBPIXELS
    )


def splat_alpha(
    points: torch.Tensor,
    radius: float,
    camera: Camera,
    size: int,
    *,
    supersample: int | None = None,
) -> torch.Tensor:
    """Soft silhouette [..., size, size] in [0, 1] of ``points`` [..., N, 3] (m) seen by
    ``camera``; leading dimensions (e.g. frames) are images drawn in one batch.

    Each point stands for a particle of radius ``radius`` (m) and is drawn as a smooth square
    of half-width f r / z (its projected radius; at least one sub-pixel); the occupancy is
    alpha = 1 - exp(-sum_i B_i), that of a Poisson field of footprints. It is evaluated on a
    grid ``supersample`` times finer than the image (None: enough that the median footprint
    spans two sub-pixels, ``splat_supersample``) and area-averaged down to it, as the recorded
    masks are. Footprints have sharp edges because a column of particles sums their tails:
    wide Gaussian tails, or a nonlinearity applied at pixel scale, push the outline outward by
    up to a pixel, which doubles the area of an object a few pixels wide. A square of
    half-width r (r the equal-volume sphere radius, 0.62 lattice spacings) has about the mean
    outline of a lattice cell seen from a random direction. The image is the camera's,
    resampled to size x size.
    """
    batch, n = points.shape[:-2], points.shape[-2]
    pts = points.reshape(-1, n, 3)
    su, sv = size / camera.width, size / camera.height  # the image resampled to size x size
    uv, z = camera.project(pts.reshape(-1, 3))
    uv, z = uv.reshape(pts.shape[0], n, 2), z.reshape(pts.shape[0], n)
    front = z > 1e-6  # points behind the camera draw nothing
    z = torch.where(front, z, torch.ones_like(z))
    radius_px = camera.fx * su * radius / z  # projected radius in output pixels
    if supersample is None:
        median = float(radius_px[front].detach().median()) if bool(front.any()) else 1.0
        supersample = splat_supersample(median)
    s = int(supersample)
    fine = size * s
    half_u = (radius_px * s).clamp(min=1.0)[..., None]  # in sub-pixels
    half_v = (camera.fy * sv * s * radius / z).clamp(min=1.0)[..., None]
    centres = torch.arange(fine, dtype=points.dtype, device=points.device) + 0.5
    images = []
    step = max(1, SPLAT_BATCH_ELEMENTS // max(1, n * fine))  # images per batch
    for i in range(0, pts.shape[0], step):
        sl = slice(i, i + step)
        keep = front[sl, :, None].to(points.dtype)
        # separable footprint B(du, dv) = b(du) b(dv): each image is one matrix product
        bu = _box_profile(centres - uv[sl, :, :1] * su * s, half_u[sl]) * keep
        bv = _box_profile(centres - uv[sl, :, 1:] * sv * s, half_v[sl])
        images.append(1.0 - torch.exp(-(bv.transpose(1, 2) @ bu)))  # [b, rows v, columns u]
    alpha = torch.cat(images)
    if s > 1:
        alpha = F.avg_pool2d(alpha[:, None], s)[:, 0]
    return alpha.reshape(*batch, size, size)


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
    Masks are loaded once per frame and kept on the device of the rollouts. A view the scene
    did not record (a camera that started late) is empty on both sides, so it adds nothing.
    """

    def __init__(self, objective: WeightedSum, *, scene, particles: ParticleSet, size: int = 48):
        self.objective = objective
        self.terms = objective.terms
        self.weights = objective.weights
        self.scene = scene
        self.size = size
        self.radius = {k: particle_radius(particles, k) for k in particles.object_list}
        self._masks: dict[int, torch.Tensor] = {}
        self._views = None if scene.every_view_recorded else scene.view_mask()  # [T, C]

    def _target(self, frames: list[int], objects: list[int], device) -> dict[int, torch.Tensor]:
        for f in frames:
            if f not in self._masks:  # [C, K, size, size], kept on the rollouts' device
                alpha = mask_alpha(self.scene.load_masks(frames=[f], missing="zeros")[0], self.size)
                self._masks[f] = alpha.to(device)
            elif self._masks[f].device != torch.device(device):
                self._masks[f] = self._masks[f].to(device)
        index = {o.id: i for i, o in enumerate(self.scene.objects)}
        return {k: torch.stack([self._masks[f][:, index[k]] for f in frames]) for k in objects}

    def render(self, geometry: GeometryFrames) -> dict[int, torch.Tensor]:
        """Object id -> [F, C, size, size] simulated alpha for every frame and camera."""
        out = {}
        for k in geometry.object_list:
            frames = torch.stack(list(geometry.points[k]))  # [F, N, 3]: all frames at once
            out[k] = torch.stack(
                [splat_alpha(frames, self.radius[k], cam, self.size) for cam in self.scene.cameras],
                dim=1,
            )
        return out

    def evaluate(self, predicted: GeometryFrames, target: GeometryFrames):
        drawn = self.render(predicted)
        if self._views is not None:
            recorded = self._views[list(predicted.frames)]  # [F, C]
            drawn = {k: a * recorded[:, :, None, None].to(a.device) for k, a in drawn.items()}
        predicted = GeometryFrames(predicted.frames, predicted.points, drawn)
        device = next(iter(predicted.silhouettes.values())).device
        masks = self._target(target.frames, target.object_list, device)
        target = GeometryFrames(target.frames, target.points, masks)
        return self.objective.evaluate(predicted, target)

    def __call__(self, predicted: GeometryFrames, target: GeometryFrames) -> torch.Tensor:
        return self.evaluate(predicted, target)[0]
