"""The ``gaussians`` lifter: frame-0 Gaussians of every object -> simulation particles.

Stage II of the pipeline (docs/ARCHITECTURE.md; paper section 3.3), one module per step:
``carve`` (samples consistent with masks and rendered depth), ``density`` (coarse-to-fine
interior grid), ``emit`` (particles on a shared grid, disjoint supports) and ``bind`` (the
Gaussians follow the particles). A reconstruction without Gaussians (the oracle) gets Gaussians
seeded from its frame-0 points (``seed``). Renderers come from the registry, never by import.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field, replace

import torch

from mosiv_framework.interfaces import Lifter
from mosiv_framework.registry import get_registry
from mosiv_framework.types import GaussianFrames, ParticleSet, Reconstruction
from mosiv_lift.bind import GaussianBinding, bind_gaussians
from mosiv_lift.carve import carve_object, mask_hull_box, recorded_masks
from mosiv_lift.density import refine_density
from mosiv_lift.emit import emit_particles
from mosiv_lift.options import TRAINED_AGREEMENT, GaussiansLifterOptions
from mosiv_lift.seed import default_point_radius, gaussians_from_points

log = logging.getLogger(__name__)


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

    def _carve_masks_only(self, k, scene, masks, generator, carved):
        """(carving, density grid) of object ``k`` from the recorded masks alone, in the box of
        its visual hull; ValueError naming the object if the masks hold nothing either.
        The masks are not dilated here: dilation is slack for the depth test, and without one
        it would inflate the hull (a 1-pixel dilation tripled a 64-pixel object's volume)."""
        opts = replace(self.options, virtual_views=0, mask_dilation_px=0)
        box = mask_hull_box(k, scene, masks, options=opts)
        if box is not None:
            none = torch.zeros(0)  # no Gaussians: with virtual_views=0 only the masks carve
            carved = carve_object(
                none, none, none, none, object_id=k, scene=scene, masks=masks,
                renderer=None, options=opts, generator=generator, box=box,
            )  # fmt: skip
            grid = _refine(carved, opts)
            if grid.occupied.any():
                return carved, grid
        raise ValueError(
            f"object {k}: neither its Gaussians nor its recorded masks of frame 0 mark any cell "
            f"({int(carved.kept.sum())} carving samples kept); check that the masks of frame 0 "
            "show the object, or loosen mask_views_missed / depth_tolerance"
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
        carving = _Carving(
            scene=scene,
            masks=recorded_masks(scene),
            renderer=renderer,
            generator=torch.Generator().manual_seed(opts.seed),
            agreement=agreement,
            trained=reconstruction.gaussians is not None,
        )
        grids, surfaces, report = {}, {}, {"objects": {}}
        for k in reconstruction.object_list:
            grids[k], surfaces[k], report["objects"][k] = self._lift_object(k, gaussians, carving)
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

    def _lift_object(self, k: int, gaussians: GaussianFrames, carving: _Carving):
        """Object ``k``'s density grid, the surface that settles its contested cells, and its
        entry of the lift report."""
        opts = self.options
        mine = gaussians.object_ids == k
        if not mine.any():
            raise ValueError(f"the reconstruction has no Gaussians of object {k}")
        means = gaussians.means[0][mine]
        widen = opts.widen_radius
        if widen is None:  # close the gaps between trained Gaussians (options.py)
            trained = carving.trained
            widen = default_point_radius({k: means}) if trained and len(means) > 1 else 0.0
        carved = carve_object(
            means,
            gaussians.radii[0][mine],
            gaussians.colors[mine],
            gaussians.opacities[mine],
            object_id=k,
            scene=carving.scene,
            masks=carving.masks,
            renderer=carving.renderer,
            options=opts,
            generator=carving.generator,
            agreement=carving.agreement,
            widen=widen,
        )
        grid = _refine(carved, opts) if carved.kept.any() else None
        fallback = None
        if grid is None or not grid.occupied.any():
            # the Gaussians' depth test left no cell more inside than outside (Gaussians of this
            # object sitting elsewhere, or too few of them: a paper-size sand-sand scene); the
            # recorded masks of frame 0 still bound the object
            fallback = (
                f"lifted from the recorded masks alone: the Gaussians' depth test kept "
                f"{int(carved.kept.sum())} of {carved.samples.shape[0]} samples, too few to fill "
                "any cell"
            )
            log.warning("object %s: %s", k, fallback)
            carved, grid = self._carve_masks_only(
                k, carving.scene, carving.masks, carving.generator, carved
            )
        entry = {
            "samples": int(carved.samples.shape[0]),
            "kept": int(carved.kept.sum()),
            "cells": int(grid.occupied.sum()),
            "widen_radius": float(widen),
        }
        if fallback is not None:
            entry["fallback"] = fallback
        # the surface that settles contested cells: the Gaussians, or when they could not be
        # trusted, the centres of the cells the masks gave the object
        surface = means if fallback is None else _cell_centres(grid)
        return grid, surface, entry


@dataclass
class _Carving:
    """What carving every object of one lift shares: the scene, its recorded masks of frame 0,
    the renderer, one random generator (drawn from object after object), the agreement the
    virtual views need, and whether the Gaussians were trained (not seeded from points)."""

    scene: object
    masks: object
    renderer: object
    generator: torch.Generator
    agreement: float
    trained: bool


def _refine(carved, options):
    return refine_density(
        carved.samples,
        carved.kept,
        carved.box,
        levels=options.levels,
        prior_weight=options.prior_weight,
    )


def _cell_centres(grid) -> torch.Tensor:
    """[M, 3] world positions (m) of the centres of ``grid``'s occupied cells."""
    index = torch.nonzero(grid.occupied).double() + 0.5
    return (grid.box.world_lower + index * grid.box.cell).float()
