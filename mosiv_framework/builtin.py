"""The core's own plugin: constitutive laws, losses, physics terms, the example scene source
and the classical segmenter.

Registered through the same entry point mechanism as any third-party plugin (``core`` in the
group ``mosiv``), so the core has no privileged path.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from mosiv_framework.interfaces import SceneSource
from mosiv_framework.registry import Component, hookimpl


@hookimpl
def mosiv_constitutive_laws(register):
    from mosiv_framework.laws import LAWS

    for law in LAWS.values():
        register(
            Component(
                "constitutive_law",
                law.name,
                factory=lambda law=law: law,
                description=law.description,
            )
        )


@hookimpl
def mosiv_losses(register):
    from mosiv_framework.losses import BUILTIN_LOSSES

    for name, cls, options, description in BUILTIN_LOSSES:
        register(Component("loss", name, factory=cls, options=options, description=description))


@hookimpl
def mosiv_physics_terms(register):
    from mosiv_framework.terms import BUILTIN_TERMS

    for term in BUILTIN_TERMS:
        register(
            Component(
                "physics_term",
                term.name,
                factory=lambda term=term: term,
                description=term.description,
            )
        )


@hookimpl
def mosiv_reconstructors(register):
    from mosiv_framework.oracle import OracleOptions, OracleReconstructor

    register(
        Component(
            "reconstructor",
            "oracle",
            factory=OracleReconstructor,
            options=OracleOptions,
            description="ground-truth points with optional i.i.d./shared noise (ablations, tests)",
        )
    )


@dataclass
class ExampleSceneOptions:
    """Options of the analytic two-sphere example scene (a format fixture, not a benchmark).

    n_frames: frames of the clip; n_cameras: cameras on a ring around the scene; size: image
    width = height (pixels); seed: varies the spheres' start positions and throw velocities.
    """

    n_frames: int = 4
    n_cameras: int = 4
    size: int = 32
    seed: int = 0


class ExampleSceneSource(SceneSource):
    """Writes the small analytic two-sphere scene of ``mosiv_framework.scene.example``."""

    def __init__(self, **options):
        self.options = options

    def generate(self, out_dir: Path) -> Path:
        from mosiv_framework.scene.example import write_example_scene

        return Path(write_example_scene(out_dir, **self.options))


@hookimpl
def mosiv_scene_sources(register):
    register(
        Component(
            "scene_source",
            "example",
            factory=ExampleSceneSource,
            options=ExampleSceneOptions,
            description="two analytic spheres on ballistic paths (format fixture)",
        )
    )


@hookimpl
def mosiv_segmenters(register):
    from mosiv_framework.segment import ClassicalOptions, ClassicalSegmenter

    register(
        Component(
            "segmenter",
            "classical",
            factory=ClassicalSegmenter,
            options=ClassicalOptions,
            description="background subtraction + voxel visual hull + tracking (static cameras)",
        )
    )
