"""Entry point of the mosiv-nerf plugin (the CoupNeRF* baseline): registers the ``nerf-field``
reconstructor, the ``nerf-particles`` lifter, the ``nerf-grid`` renderer and the
``nerf-photometric`` loss. Torch-heavy modules are imported only when a component is built."""

from __future__ import annotations

from mosiv_framework.registry import Component, hookimpl
from mosiv_nerf.options import (
    NerfFieldOptions,
    NerfGridOptions,
    NerfParticlesOptions,
    NerfPhotometricOptions,
)


def make_field_reconstructor(**options):
    from mosiv_nerf.reconstructor import NerfFieldReconstructor

    return NerfFieldReconstructor(**options)


def make_particles_lifter(**options):
    from mosiv_nerf.lifter import NerfParticlesLifter

    return NerfParticlesLifter(**options)


def make_grid_renderer(**options):
    from mosiv_nerf.renderer import NerfGridRenderer

    return NerfGridRenderer(**options)


def make_photometric_loss(**options):
    from mosiv_nerf.loss import NerfPhotometricLoss

    return NerfPhotometricLoss(**options)


@hookimpl
def mosiv_reconstructors(register):
    register(
        Component(
            "reconstructor",
            "nerf-field",
            factory=make_field_reconstructor,
            options=NerfFieldOptions,
            description="CoupNeRF* stage I: frame-0 voxel radiance field, one density per "
            "object, fitted to images and masks by volume rendering; hull points per frame",
        )
    )


@hookimpl
def mosiv_lifters(register):
    register(
        Component(
            "lifter",
            "nerf-particles",
            factory=make_particles_lifter,
            options=NerfParticlesOptions,
            description="particles on a jittered lattice where the nerf-field density is "
            "opaque, each carrying its density and colour",
        )
    )


@hookimpl
def mosiv_renderers(register):
    register(
        Component(
            "renderer",
            "nerf-grid",
            factory=make_grid_renderer,
            options=NerfGridOptions,
            description="particles splatted to a voxel grid (MPM B-spline P2G) and "
            "volume-rendered: rgb, alpha, depth, per-object alpha",
        )
    )


@hookimpl
def mosiv_losses(register):
    register(
        Component(
            "loss",
            "nerf-photometric",
            factory=make_photometric_loss,
            options=NerfPhotometricOptions,
            description="CoupNeRF* objective: nerf-grid renders of the simulated particles vs "
            "recorded images (L1) and masks (per-object L1)",
        )
    )
