"""Lifter ``nerf-particles``: simulation particles sampled from the frame-0 field's density.

A jittered lattice of spacing h covers the field's box; a lattice point becomes a particle where
the field's total opacity over one spacing, 1 - exp(-sigma h), exceeds ``threshold``, and it
belongs to the object whose density is largest there. Each particle has rest volume h^3 and
carries the field's density and colour at its position (PAC-NeRF's Eulerian-to-Lagrangian
step). ``ParticleSet.appearance`` gets a ``NerfAppearance`` whose binding turns a particle state
into the GaussianFrames the ``nerf-grid`` renderer draws, so the evaluation renders simulated
frames the way identification's ``nerf-photometric`` loss does.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import torch

from mosiv_framework.errors import ConfigError
from mosiv_framework.interfaces import Lifter
from mosiv_framework.types import GaussianFrames, ParticleSet, Reconstruction
from mosiv_nerf.field import VoxelField
from mosiv_nerf.options import NerfParticlesOptions
from mosiv_nerf.renderer import particle_opacity

log = logging.getLogger(__name__)
Tensor = torch.Tensor


@dataclass
class ParticleBinding:
    """The frame-0 appearance of each particle: colors [N, 3], opacities [N] (over one spacing),
    radii [N] (half the spacing, m), object_ids [N]."""

    colors: Tensor
    opacities: Tensor
    radii: Tensor
    object_ids: Tensor

    def gaussian_frames(self, positions: Tensor) -> GaussianFrames:
        """The particles at states [T, N, 3] (or one state [N, 3]) as the renderer's input."""
        if positions.ndim == 2:
            positions = positions[None]
        dev, dtype = positions.device, positions.dtype
        return GaussianFrames(
            means=positions,
            radii=self.radii.to(dev, dtype).expand(positions.shape[0], -1),
            colors=self.colors.to(dev, dtype),
            opacities=self.opacities.to(dev, dtype),
            object_ids=self.object_ids.to(dev),
        )


@dataclass
class NerfAppearance:
    """What ``nerf-particles`` attaches to ``ParticleSet.appearance`` (read by attribute by the
    evaluation's image metrics and by the ``nerf-photometric`` loss)."""

    binding: ParticleBinding
    background: dict[str, Tensor] | None = None
    renderer: str = "nerf-grid"
    renderer_options: dict[str, object] = field(default_factory=dict)
    report: dict[str, object] = field(default_factory=dict)


def sample_particles(
    nerf: VoxelField, spacing: float, *, threshold: float, jitter: float, generator
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """(positions [N, 3], object_ids [N], sigma [N], colors [N, 3]) on a jittered lattice of
    ``spacing`` inside the field's box where its opacity over one spacing exceeds
    ``threshold``."""
    box = nerf.box
    extent = box.hi - box.lo
    counts = [max(1, int(float(e) / spacing)) for e in extent]
    axes = [
        box.lo[d] + spacing * (0.5 + torch.arange(n, dtype=box.lo.dtype, device=box.lo.device))
        for d, n in enumerate(counts)
    ]
    x, y, z = torch.meshgrid(*axes, indexing="ij")
    points = torch.stack([x, y, z], dim=-1).reshape(-1, 3)
    shake = torch.rand(points.shape, generator=generator, device=generator.device)
    points = points + (shake.to(points) - 0.5) * jitter * spacing
    with torch.no_grad():
        sigma_k, rgb = nerf.sample(points)
    sigma = sigma_k.sum(dim=0)
    keep = particle_opacity(sigma, spacing) > threshold
    owner = sigma_k.argmax(dim=0)
    ids = torch.tensor(nerf.object_ids, device=points.device)[owner]
    return points[keep], ids[keep], sigma[keep], rgb[keep]


class NerfParticlesLifter(Lifter):
    """Lifter ``nerf-particles``; keyword options are those of NerfParticlesOptions."""

    def __init__(self, **options):
        self.options = NerfParticlesOptions(**options)

    def lift(self, reconstruction: Reconstruction, scene) -> ParticleSet:
        opts = self.options
        state = reconstruction.extras.get("nerf_field")
        if state is None:
            raise ConfigError(
                "lifter nerf-particles needs the frame-0 field of reconstructor nerf-field "
                "(Reconstruction.extras['nerf_field'])"
            )
        nerf = VoxelField.from_state(state)
        spacing = opts.spacing or nerf.box.cell
        generator = torch.Generator().manual_seed(opts.seed)
        pos, ids, sigma, rgb = sample_particles(
            nerf, spacing, threshold=opts.threshold, jitter=opts.jitter, generator=generator
        )
        volumes = torch.full_like(sigma, spacing**3)
        pos, ids, sigma, rgb, volumes = self._cap(pos, ids, sigma, rgb, volumes, generator)
        missing = sorted(set(scene.object_ids) - set(ids.unique().tolist()))
        if missing:
            raise ConfigError(
                f"lifter nerf-particles: no particle for object(s) {missing}: the field's "
                f"density never exceeds threshold={opts.threshold} there; lower the threshold "
                "or fit the field longer"
            )
        counts = {int(k): int((ids == k).sum()) for k in scene.object_ids}
        log.info("nerf-particles: %s particles per object at spacing %.4g m", counts, spacing)
        # each particle keeps the density it had; the renderer reads it back from its opacity
        # over one spacing, which a subset's larger volume would change, so use that volume
        side = volumes ** (1.0 / 3.0)
        binding = ParticleBinding(rgb, particle_opacity(sigma, side), side / 2.0, ids)
        appearance = NerfAppearance(
            binding=binding,
            background=reconstruction.background,
            renderer=opts.renderer,
            renderer_options=dict(opts.renderer_options),
            report={"particles": counts, "spacing_m": spacing},
        )
        return ParticleSet(pos, volumes, ids, dict(scene.materials), appearance=appearance)

    def _cap(self, pos, ids, sigma, rgb, volumes, generator):
        """At most ``max_particles_per_object`` per object, volumes scaled to keep its total."""
        cap = self.options.max_particles_per_object
        if cap == 0:
            return pos, ids, sigma, rgb, volumes
        keep = []
        volumes = volumes.clone()
        for k in ids.unique().tolist():
            idx = torch.nonzero(ids == k).flatten()
            if idx.numel() > cap:
                volumes[idx] *= idx.numel() / cap
                idx = idx[torch.randperm(idx.numel(), generator=generator)[:cap]]
            keep.append(idx)
        order = torch.cat(keep).sort().values
        return pos[order], ids[order], sigma[order], rgb[order], volumes[order]
