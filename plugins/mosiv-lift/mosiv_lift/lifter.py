"""The ``gaussians`` lifter: frame-0 Gaussians of every object -> simulation particles.

Stage II of the pipeline (DESIGN.md section 5.2, paper section 3.3), one module per step:
``carve`` (samples consistent with masks and rendered depth), ``density`` (coarse-to-fine
interior grid), ``emit`` (particles on a shared grid, disjoint supports) and ``bind`` (the
Gaussians follow the particles). A reconstruction without Gaussians (the oracle) gets Gaussians
seeded from its frame-0 points (``seed``). Renderers come from the registry, never by import.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch

from mosiv_framework.interfaces import Lifter
from mosiv_framework.registry import get_registry
from mosiv_framework.types import GaussianFrames, ParticleSet, Reconstruction
from mosiv_lift.bind import GaussianBinding, bind_gaussians
from mosiv_lift.carve import carve_object, recorded_masks
from mosiv_lift.density import refine_density
from mosiv_lift.emit import emit_particles
from mosiv_lift.options import TRAINED_AGREEMENT, GaussiansLifterOptions
from mosiv_lift.seed import default_point_radius, gaussians_from_points


@dataclass
class LiftedAppearance:
    """What the ``gaussians`` lifter attaches to its ParticleSet (``ParticleSet.appearance``).

    binding: the frame-0 Gaussians bound to the particles (render simulated states with it);
    masses: [N] kg, density times rest volume (ParticleSet has no mass field; simulators take
    rho from the parameters); background: camera id -> [H, W, 3] static background of the
    reconstruction, when it has one; report: counts of the lift (samples, cells, conflicts);
    renderer, renderer_options: the registered renderer (and its options) the Gaussians were
    carved with, so later stages (evaluation PSNR/SSIM) draw them the same way.
    """

    binding: GaussianBinding
    masses: torch.Tensor
    background: dict[str, torch.Tensor] | None = None
    report: dict[str, object] = field(default_factory=dict)
    renderer: str = ""
    renderer_options: dict[str, object] = field(default_factory=dict)


class GaussiansLifter(Lifter):
    """Lifter ``gaussians``; keyword options are those of GaussiansLifterOptions."""

    def __init__(self, **options):
        self.options = GaussiansLifterOptions(**options)

    def _renderer(self):
        return get_registry().create(
            "renderer", self.options.renderer, dict(self.options.renderer_options)
        )

    def frame0_gaussians(self, reconstruction: Reconstruction, scene, renderer) -> GaussianFrames:
        """The reconstruction's frame-0 Gaussians, or Gaussians seeded from its frame-0 points."""
        if reconstruction.gaussians is not None:
            g = reconstruction.gaussians
            return GaussianFrames(
                g.means[:1].detach().float().cpu(),
                g.radii[:1].detach().float().cpu(),
                g.colors.detach().float().cpu(),
                g.opacities.detach().float().cpu(),
                g.object_ids.detach().cpu(),
            )
        points = {
            k: reconstruction.points[k][0].detach().float().cpu()
            for k in reconstruction.object_list
        }
        radius = self.options.point_radius or default_point_radius(points)
        return gaussians_from_points(points, scene, renderer, radius=radius)

    def lift(self, reconstruction: Reconstruction, scene) -> ParticleSet:
        opts = self.options
        materials = scene.materials
        unknown = sorted(set(reconstruction.object_list) - set(materials))
        if unknown:
            raise ValueError(
                f"reconstruction has objects {unknown} that scene.json does not declare "
                f"(scene objects: {sorted(materials)})"
            )
        renderer = self._renderer()
        gaussians = self.frame0_gaussians(reconstruction, scene, renderer)
        agreement = opts.virtual_agreement
        if agreement is None:
            agreement = 1.0 if reconstruction.gaussians is None else TRAINED_AGREEMENT
        generator = torch.Generator().manual_seed(opts.seed)
        masks = recorded_masks(scene)
        grids, surfaces, report = {}, {}, {"objects": {}}
        for k in reconstruction.object_list:
            mine = gaussians.object_ids == k
            if not mine.any():
                raise ValueError(f"the reconstruction has no Gaussians of object {k}")
            means = gaussians.means[0][mine]
            widen = opts.widen_radius
            if widen is None:  # close the gaps between trained Gaussians (options.py)
                trained = reconstruction.gaussians is not None
                widen = default_point_radius({k: means}) if trained and len(means) > 1 else 0.0
            carved = carve_object(
                means,
                gaussians.radii[0][mine],
                gaussians.colors[mine],
                gaussians.opacities[mine],
                object_id=k,
                scene=scene,
                masks=masks,
                renderer=renderer,
                options=opts,
                generator=generator,
                agreement=agreement,
                widen=widen,
            )
            if not carved.kept.any():
                raise ValueError(
                    f"object {k}: no carving sample is consistent with the masks and rendered "
                    "depth; check that the Gaussians and masks of frame 0 agree, or loosen "
                    "mask_views_missed / depth_tolerance"
                )
            grids[k] = refine_density(
                carved.samples,
                carved.kept,
                carved.box,
                levels=opts.levels,
                prior_weight=opts.prior_weight,
            )
            surfaces[k] = means
            report["objects"][k] = {
                "samples": int(carved.samples.shape[0]),
                "kept": int(carved.kept.sum()),
                "cells": int(grids[k].occupied.sum()),
                "widen_radius": float(widen),
            }
        emission = emit_particles(
            grids,
            surfaces,
            domain_lower=scene.domain_lower,
            domain_upper=scene.domain_upper,
            cell=opts.cell_size,
            sub_lattice=opts.sub_lattice,
            densities={k: opts.density_of(k) for k in reconstruction.object_list},
        )
        report["contested_cells"] = emission.contested_cells
        report["removed_particles"] = emission.removed_particles
        binding = bind_gaussians(
            gaussians,
            emission.positions,
            emission.object_ids,
            neighbors=opts.bind_neighbors,
            power=opts.bind_power,
        )
        appearance = LiftedAppearance(
            binding=binding,
            masses=emission.masses,
            background=reconstruction.background,
            report=report,
            renderer=opts.renderer,
            renderer_options=dict(opts.renderer_options),
        )
        return ParticleSet(
            emission.positions,
            emission.volumes,
            emission.object_ids,
            {k: materials[k] for k in reconstruction.object_list},
            appearance=appearance,
        )
