"""Plugin registry: hook specifications, the Component record, and the plugin manager."""

from mosiv_framework.registry.hookspecs import hookimpl, hookspec
from mosiv_framework.registry.manager import (
    BrokenPlugin,
    Conflict,
    PluginInfo,
    Registry,
    get_registry,
    validate_options,
)
from mosiv_framework.registry.records import KINDS, Component

__all__ = [
    "KINDS",
    "BrokenPlugin",
    "Component",
    "Conflict",
    "PluginInfo",
    "Registry",
    "get_registry",
    "hookimpl",
    "hookspec",
    "validate_options",
]
