"""Entry point of mosiv-genesis: registers the ``genesis`` scene source.

Importing it never imports Genesis (a large engine, installed with ``mosiv-genesis[engine]``);
the engine loads when a scene is generated, and its absence is a clear ConfigError then.
"""

from __future__ import annotations

from mosiv_framework.registry import Component, hookimpl
from mosiv_genesis.options import GenesisOptions


def make_source(**options):
    """Build a GenesisSource from keyword options (validated by GenesisOptions)."""
    from mosiv_genesis.source import GenesisSource

    return GenesisSource(GenesisOptions(**options))


@hookimpl
def mosiv_scene_sources(register):
    register(
        Component(
            "scene_source",
            "genesis",
            factory=make_source,
            options=GenesisOptions,
            description="Genesis-engine MPM scenes (Elastic, ElastoPlastic, Liquid, Sand, Snow) "
            "with the paper's collision protocol; needs genesis-world",
        )
    )
