"""Registers the lifters of this distribution with the MOSIV registry."""

from __future__ import annotations

from mosiv_framework.registry import Component, hookimpl


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
