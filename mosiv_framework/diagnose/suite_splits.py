"""Diagnosis suites with a development and a test split: thresholds are chosen on one and
scored once on the other.

``mosiv diagnose-suite OUT --source genesis --split dev|test``: scenes the Genesis engine
records (scene source ``genesis``, recipes/diagnose_genesis.yaml) and a run identifies with
MOSIV's own simulator, so every scene also carries the model difference between two MPM
implementations. Each split holds two entries of every library body force Genesis can conceal
(linear and quadratic drag, wind, gravity), two of each out-of-library field
(``conceal_fields``: vortex, attractor; the right verdict there is "unexplained" or
"discrepancy", and the discovered law is scored against the field), and six controls with
nothing concealed. The splits have the same effects on scenes of disjoint seeds (different
shapes, materials' parameters, layouts and cameras).

What an entry may set is the effect and the scene's seed and materials: never a recipe setting
or a library restriction chosen for its hidden effect, since a user diagnosing a recording does
not know that effect.
"""

from __future__ import annotations

from pathlib import Path

from mosiv_framework.conceal_fields import OUT_OF_LIBRARY_KINDS
from mosiv_framework.errors import ConfigError

SOURCES = ("synth", "genesis")
SPLITS = ("dev", "test")
#: first seed of each split (entries count up from it); the ranges are disjoint
SPLIT_SEEDS = {"dev": 3000, "test": 5000}
#: the recipe each source's split suite runs with
SPLIT_RECIPES = {
    "genesis": Path(__file__).resolve().parents[2] / "recipes" / "diagnose_genesis.yaml",
}
#: material pairs, taken in turn by entry position whatever the effect (Genesis' Liquid and
#: Snow are left out: MOSIV's newtonian law is not Genesis' Liquid, and Genesis' snow
#: hardening has no counterpart, so they would measure the model difference, not the effect)
GENESIS_PAIRS = ("elastic,elastic", "elastic,plasticine", "plasticine,sand", "elastic,sand")
#: two specs per concealed kind: a clear strength and another direction or a weaker one
GENESIS_EFFECTS = {
    "linear_drag": ("linear_drag:coefficient=1.5", "linear_drag:coefficient=2.5"),
    "quadratic_drag": ("quadratic_drag:coefficient=1.0", "quadratic_drag:coefficient=2.5"),
    "wind": ("wind:acceleration=1.5,0,0", "wind:acceleration=0,2.5,0"),
    "gravity": ("gravity:acceleration=0,0,-12", "gravity:acceleration=0,0,-7.5"),
    "vortex": ("vortex:strength=12", "vortex:strength=-8,radial=4"),
    "attractor": ("attractor:strength=3", "attractor:strength=2.5,position=0.1,0,0.3"),
}
N_CONTROLS = 6


def genesis_split(split: str) -> list:
    """The entries of one split of the Genesis suite (``suite.Entry``), in a fixed order."""
    from mosiv_framework.diagnose.suite import Entry

    check_split("genesis", split)
    seed = SPLIT_SEEDS[split]
    specs = [(kind, level, spec) for kind, pair in GENESIS_EFFECTS.items()
             for level, spec in enumerate(pair)]  # fmt: skip
    specs += [("control", i, "") for i in range(N_CONTROLS)]
    out = []
    for i, (kind, level, spec) in enumerate(specs):
        # out-of-library entries are named "outside-..." (``suite.entry_group``)
        name = f"outside-{kind}-{level}" if kind in OUT_OF_LIBRARY_KINDS else f"{kind}-{level}"
        out.append(Entry(name, spec, GENESIS_PAIRS[i % len(GENESIS_PAIRS)], seed + i))
    return out


def check_split(source: str, split: str | None, *, small: bool = False) -> None:
    """Refuse a source or split the suites do not have, with the valid ones; the Genesis suite
    needs a split and has no small form, the synth suite has no splits."""
    if source not in SOURCES:
        raise ConfigError(f"--source {source!r}: valid: {', '.join(SOURCES)}")
    if source == "synth":
        if split is not None:
            raise ConfigError(
                "--split: only the genesis suite has splits (--source genesis --split dev|test)"
            )
        return
    if split not in SPLITS:
        raise ConfigError(
            f"--source {source}: give --split {' or '.join(SPLITS)} (got {split!r}): choose "
            "thresholds on dev, score once on test"
        )
    if small:
        raise ConfigError(f"--small: the {source} suite has no small form; leave --small out")


def split_entries(source: str, split: str | None, *, small: bool) -> list | None:
    """The entries of ``source``'s ``split``, or None for the synth suite (``suite_entries``)."""
    check_split(source, split, small=small)
    return genesis_split(split) if source == "genesis" else None
