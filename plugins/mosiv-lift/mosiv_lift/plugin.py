"""Registers the lifters of this distribution with the MOSIV registry."""

from __future__ import annotations

from mosiv_framework.registry import Component, hookimpl
from mosiv_lift.options import GaussiansLifterOptions


def make_gaussians_lifter(**options):
    """Build a GaussiansLifter from keyword options (validated by GaussiansLifterOptions)."""
    from mosiv_lift.lifter import GaussiansLifter

    return GaussiansLifter(**options)


@hookimpl
def mosiv_lifters(register):
    from mosiv_lift.points import PointsLifter, PointsLifterOptions

    register(
        Component(
            "lifter",
            "gt-points",
            factory=PointsLifter,
            options=PointsLifterOptions,
            description="particles straight from the reconstruction's frame-0 points (oracle, tests)",
        )
    )
    register(
        Component(
            "lifter",
            "gaussians",
            factory=make_gaussians_lifter,
            options=GaussiansLifterOptions,
            description="space carving of each object's frame-0 Gaussians against masks and "
            "rendered depth, coarse-to-fine density grid, particles on a shared grid with "
            "disjoint supports, Gaussians bound to the particles",
        )
    )
