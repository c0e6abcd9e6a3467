"""pluggy hook specifications: one hook per component kind.

A plugin module (named by an entry point in the group ``mosiv``) implements any of these with
``@hookimpl`` and calls ``register(Component(...))`` once per component it provides::

    from mosiv_framework.registry import Component, hookimpl

    @hookimpl
    def mosiv_losses(register):
        register(Component("loss", "my-loss", factory=MyLoss, description="..."))
"""

from __future__ import annotations

from collections.abc import Callable

import pluggy

PROJECT = "mosiv"
hookspec = pluggy.HookspecMarker(PROJECT)
hookimpl = pluggy.HookimplMarker(PROJECT)

Register = Callable[[object], None]


class MosivHookSpecs:
    @hookspec
    def mosiv_reconstructors(self, register: Register) -> None:
        """Register Reconstructor components (video -> dynamic Gaussians)."""

    @hookspec
    def mosiv_lifters(self, register: Register) -> None:
        """Register Lifter components (reconstruction -> simulation particles)."""

    @hookspec
    def mosiv_simulators(self, register: Register) -> None:
        """Register Simulator components (differentiable MPM backends)."""

    @hookspec
    def mosiv_constitutive_laws(self, register: Register) -> None:
        """Register ConstitutiveLaw components (material families)."""

    @hookspec
    def mosiv_losses(self, register: Register) -> None:
        """Register Loss components (identification objectives)."""

    @hookspec
    def mosiv_renderers(self, register: Register) -> None:
        """Register Renderer components (Gaussians -> images)."""

    @hookspec
    def mosiv_physics_terms(self, register: Register) -> None:
        """Register PhysicsTerm components (optional extra physical effects)."""

    @hookspec
    def mosiv_scene_sources(self, register: Register) -> None:
        """Register SceneSource components (scene generators and converters)."""

    @hookspec
    def mosiv_segmenters(self, register: Register) -> None:
        """Register Segmenter components (multi-view video -> instance masks)."""

    @hookspec
    def mosiv_bench_peers(self, register: Register) -> None:
        """Register BenchPeer components (other simulators timed by ``mosiv bench sim --peer``)."""


#: component kind -> the hook that registers it
HOOK_OF_KIND: dict[str, str] = {
    "reconstructor": "mosiv_reconstructors",
    "lifter": "mosiv_lifters",
    "simulator": "mosiv_simulators",
    "constitutive_law": "mosiv_constitutive_laws",
    "loss": "mosiv_losses",
    "renderer": "mosiv_renderers",
    "physics_term": "mosiv_physics_terms",
    "scene_source": "mosiv_scene_sources",
    "segmenter": "mosiv_segmenters",
    "bench_peer": "mosiv_bench_peers",
}
