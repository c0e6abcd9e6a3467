"""The built-in constitutive laws of MOSIV, one module per family.

Their equations: docs/PHYSICS.md, Constitutive laws.

``LAWS`` maps each family name (as written in scene.json) to a ready instance; ``get_law`` looks
one up with an error that lists the valid names.
"""

from __future__ import annotations

from mosiv_framework.laws.base import OBJECT_PARAMS, ConstitutiveLaw, ParamSpec, lame_parameters
from mosiv_framework.laws.elastic import Elastic
from mosiv_framework.laws.elastic_corotated import ElasticCorotated
from mosiv_framework.laws.newtonian import Newtonian
from mosiv_framework.laws.non_newtonian import NonNewtonian
from mosiv_framework.laws.plasticine import Plasticine
from mosiv_framework.laws.plasticine_corotated import PlasticineCorotated
from mosiv_framework.laws.sand import Sand
from mosiv_framework.laws.snow import Snow

__all__ = [
    "FAMILIES",
    "LAWS",
    "OBJECT_PARAMS",
    "ConstitutiveLaw",
    "Elastic",
    "ElasticCorotated",
    "Newtonian",
    "NonNewtonian",
    "ParamSpec",
    "Plasticine",
    "PlasticineCorotated",
    "Sand",
    "Snow",
    "get_law",
    "lame_parameters",
]

#: material family names in scene-format order (the backends' law ids); the corotated variants
#: come last so that the earlier ids keep their meaning
FAMILIES: tuple[str, ...] = (
    "elastic",
    "plasticine",
    "sand",
    "newtonian",
    "non_newtonian",
    "snow",
    "elastic_corotated",
    "plasticine_corotated",
)

LAWS: dict[str, ConstitutiveLaw] = {
    law.name: law
    for law in (
        Elastic(),
        Plasticine(),
        Sand(),
        Newtonian(),
        NonNewtonian(),
        Snow(),
        ElasticCorotated(),
        PlasticineCorotated(),
    )
}
assert tuple(LAWS) == FAMILIES, "LAWS must list the families in scene-format order"


class UnknownLawError(KeyError, ValueError):
    """An unknown material family name (catchable as KeyError or ValueError)."""

    def __str__(self) -> str:  # KeyError would print the message with quotes around it
        return str(self.args[0])


def get_law(name: str) -> ConstitutiveLaw:
    """The built-in law called ``name``; raises UnknownLawError listing the valid families."""
    try:
        return LAWS[name]
    except KeyError:
        raise UnknownLawError(
            f"unknown material family {name!r}; valid families: {', '.join(FAMILIES)}"
        ) from None
