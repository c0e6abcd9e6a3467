"""The typed record a plugin hands to ``register`` for each component it provides."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

#: The component kinds, one hookspec each (see hookspecs.py).
KINDS: tuple[str, ...] = (
    "reconstructor",
    "lifter",
    "simulator",
    "constitutive_law",
    "loss",
    "renderer",
    "physics_term",
    "scene_source",
    "segmenter",
    "bench_peer",
)


@dataclass(frozen=True)
class Component:
    """One registered component.

    kind: one of KINDS; name: unique within the kind (what recipes refer to);
    factory: called with the validated options as keyword arguments, returns the component;
    options: a dataclass type whose fields are the component's options (its config schema), or
    None for a component without options; description: one line for ``mosiv plugins``.
    ``distribution`` is filled in by the registry with the plugin that registered it.
    """

    kind: str
    name: str
    factory: Callable[..., Any]
    options: type | None = None
    description: str = ""
    distribution: str = field(default="", compare=False)

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"unknown component kind {self.kind!r}; valid kinds: {list(KINDS)}")
        if not self.name or not isinstance(self.name, str):
            raise ValueError(f"a {self.kind} component needs a non-empty string name")
        if self.options is not None and "name" in getattr(self.options, "__dataclass_fields__", {}):
            # recipes write {name: <component>, <option>: ...}: an option called "name" would
            # shadow the component's name
            raise ValueError(
                f"{self.kind} {self.name!r}: its options may not have a field called 'name'"
            )
