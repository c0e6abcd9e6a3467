"""Entry point of the mosiv-synth plugin: registers the ``synth`` scene source.

Importing this module stays cheap: trimesh, scikit-image and the simulator backend load only
when a scene is generated.
"""

from __future__ import annotations

from mosiv_framework.registry import Component, hookimpl
from mosiv_synth.options import SynthOptions


def make_source(**options):
    """Build a SynthSource from keyword options (validated by SynthOptions)."""
    from mosiv_synth.generate import SynthSource

    return SynthSource(SynthOptions(**options))


@hookimpl
def mosiv_scene_sources(register):
    register(
        Component(
            "scene_source",
            "synth",
            factory=make_source,
            options=SynthOptions,
            description="benchmark generator: 2-3 procedural objects collide mid-air, "
            "simulated by a registered MPM backend, rendered with masks and ground truth",
        )
    )
