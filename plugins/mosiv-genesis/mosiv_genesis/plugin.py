"""Entry point of mosiv-genesis: registers the ``genesis`` scene source and bench peer.

Importing it never imports Genesis (a large engine, installed with ``mosiv-genesis[engine]``);
the engine loads when a scene is generated or a bench runs, and its absence is a clear error
then.
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


def make_bench_peer():
    """The Genesis bench peer (``mosiv bench sim --peer genesis``)."""
    from mosiv_genesis.bench import GenesisPeer

    return GenesisPeer()


@hookimpl
def mosiv_bench_peers(register):
    register(
        Component(
            "bench_peer",
            "genesis",
            factory=make_bench_peer,
            description="Genesis' MPM timed on the bench workload (same particles, elastic "
            "law, grid, substeps), forward only; needs genesis-world",
        )
    )
