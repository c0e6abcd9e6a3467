"""Discovers plugins, collects the components they register, and builds them from options.

Each entry point of the group ``mosiv`` is loaded in its own guard: a plugin that fails to
import, or whose hook raises, is recorded as broken with its error and the others still load.
Set ``MOSIV_DISABLE_PLUGINS=name1,name2`` (entry-point or distribution names) to skip plugins.
"""

from __future__ import annotations

import dataclasses
import os
import traceback
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from importlib import metadata
from types import ModuleType
from typing import Any

import pluggy

from mosiv_framework.errors import ConfigError
from mosiv_framework.registry.hookspecs import HOOK_OF_KIND, PROJECT, MosivHookSpecs
from mosiv_framework.registry.records import KINDS, Component

ENTRY_POINT_GROUP = "mosiv"
DISABLE_ENV = "MOSIV_DISABLE_PLUGINS"


@dataclass
class PluginInfo:
    """A loaded plugin: its entry-point name, distribution, version and components."""

    name: str
    distribution: str
    version: str
    module: str
    components: list[Component] = field(default_factory=list)


@dataclass
class BrokenPlugin:
    """A plugin that could not be loaded or whose registration hook raised."""

    name: str
    distribution: str
    error: str
    traceback: str = ""


@dataclass
class Conflict:
    """Two distributions registered the same component name for one kind."""

    kind: str
    name: str
    kept: str
    rejected: str

    def message(self) -> str:
        return (
            f"{self.kind} {self.name!r} is registered by both {self.kept!r} and "
            f"{self.rejected!r}; uninstall or disable one of them ({DISABLE_ENV})"
        )


def _disabled_from_env() -> set[str]:
    raw = os.environ.get(DISABLE_ENV, "")
    return {part.strip() for part in raw.split(",") if part.strip()}


class Registry:
    """All components of the installed plugins, by kind and name."""

    def __init__(self) -> None:
        self.plugins: dict[str, PluginInfo] = {}
        self.broken: list[BrokenPlugin] = []
        self.disabled: list[str] = []
        self.conflicts: list[Conflict] = []
        self._components: dict[str, dict[str, Component]] = {kind: {} for kind in KINDS}
        self._pm = pluggy.PluginManager(PROJECT)
        self._pm.add_hookspecs(MosivHookSpecs)

    # -- loading ------------------------------------------------------------------------------
    def load_entry_points(self, *, disabled: Iterable[str] | None = None) -> Registry:
        """Load every entry point of the group ``mosiv``, each in its own guard."""
        skip = set(disabled) if disabled is not None else _disabled_from_env()
        for ep in sorted(metadata.entry_points(group=ENTRY_POINT_GROUP), key=lambda e: e.name):
            dist = ep.dist.name if ep.dist is not None else "?"
            version = ep.dist.version if ep.dist is not None else "?"
            if ep.name in skip or dist in skip:
                self.disabled.append(ep.name)
                continue
            try:
                module = ep.load()
            except Exception as exc:  # a broken plugin must not take the others down
                self.broken.append(
                    BrokenPlugin(
                        ep.name, dist, f"{type(exc).__name__}: {exc}", traceback.format_exc()
                    )
                )
                continue
            self.add_plugin(module, name=ep.name, distribution=dist, version=version)
        return self

    def add_plugin(
        self, module: ModuleType | object, *, name: str, distribution: str = "", version: str = ""
    ) -> PluginInfo | None:
        """Register one plugin object (module or instance with hookimpls) and collect its components."""
        distribution = distribution or name
        try:
            self._pm.register(module, name=name)
        except Exception as exc:
            self.broken.append(BrokenPlugin(name, distribution, f"{type(exc).__name__}: {exc}"))
            return None
        info = PluginInfo(name, distribution, version, getattr(module, "__name__", repr(module)))
        for kind, hook_name in HOOK_OF_KIND.items():
            for impl in getattr(self._pm.hook, hook_name).get_hookimpls():
                if impl.plugin is not module:
                    continue
                try:
                    impl.function(register=self._register_callback(info, kind))
                except Exception as exc:
                    self.broken.append(
                        BrokenPlugin(
                            name,
                            distribution,
                            f"{hook_name} raised {type(exc).__name__}: {exc}",
                            traceback.format_exc(),
                        )
                    )
        self.plugins[name] = info
        return info

    def _register_callback(self, info: PluginInfo, kind: str):
        def register(component: Component) -> None:
            if not isinstance(component, Component):
                raise TypeError(
                    f"register() takes a mosiv Component record, got {type(component)!r}"
                )
            if component.kind != kind:
                raise ValueError(
                    f"component {component.name!r} of kind {component.kind!r} was registered "
                    f"from the {kind!r} hook ({HOOK_OF_KIND[kind]})"
                )
            component = dataclasses.replace(component, distribution=info.distribution)
            existing = self._components[kind].get(component.name)
            if existing is not None:
                self.conflicts.append(
                    Conflict(kind, component.name, existing.distribution, component.distribution)
                )
                return
            self._components[kind][component.name] = component
            info.components.append(component)

        return register

    # -- lookup -------------------------------------------------------------------------------
    def names(self, kind: str) -> list[str]:
        self._check_kind(kind)
        return sorted(self._components[kind])

    def components(self, kind: str) -> list[Component]:
        self._check_kind(kind)
        return [self._components[kind][n] for n in self.names(kind)]

    def get(self, kind: str, name: str) -> Component:
        """The component ``name`` of ``kind``; the error lists valid names and broken plugins."""
        self._check_kind(kind)
        for conflict in self.conflicts:
            if conflict.kind == kind and conflict.name == name:
                raise ConfigError(conflict.message())
        if name not in self._components[kind]:
            raise ConfigError(self.unknown_name_message(kind, name))
        return self._components[kind][name]

    def unknown_name_message(self, kind: str, name: object) -> str:
        valid = ", ".join(self.names(kind)) or "none installed"
        msg = f"unknown {kind} {name!r}; valid {kind} names: {valid}"
        if self.broken:
            msg += "; broken plugins: " + ", ".join(f"{b.name} ({b.error})" for b in self.broken)
        return msg

    def _check_kind(self, kind: str) -> None:
        if kind not in self._components:
            raise ValueError(f"unknown component kind {kind!r}; valid kinds: {list(KINDS)}")

    # -- construction -------------------------------------------------------------------------
    def create(self, kind: str, name: str, options: Mapping[str, Any] | None = None) -> Any:
        """Validate ``options`` against the component's schema and call its factory."""
        component = self.get(kind, name)
        validated = validate_options(component, dict(options or {}))
        return component.factory(**validated)


def validate_options(component: Component, options: Mapping[str, Any]) -> dict[str, Any]:
    """Check options against the component's schema; returns them with defaults filled in.

    Raises ConfigError listing every problem: unknown keys (with the valid ones), values of the
    wrong type, and whatever the options dataclass's own ``__post_init__`` rejects.
    """
    from omegaconf import OmegaConf
    from omegaconf.errors import OmegaConfBaseException

    where = f"{component.kind} {component.name!r}"
    if component.options is None:
        if options:
            raise ConfigError(f"{where} takes no options, got {sorted(options)}")
        return {}
    valid = [f.name for f in dataclasses.fields(component.options)]
    problems = [
        f"{where} has no option {key!r}; valid options: {', '.join(valid)}"
        for key in options
        if key not in valid
    ]
    base = OmegaConf.structured(component.options)
    merged = base
    for key in (k for k in options if k in valid):
        try:
            merged = OmegaConf.merge(merged, {key: options[key]})
        except OmegaConfBaseException as exc:
            problems.append(f"{where} option {key}={options[key]!r}: {_first_line(exc)}")
    if problems:
        raise ConfigError(problems)
    try:
        instance = OmegaConf.to_object(merged)
    except (ValueError, TypeError, OmegaConfBaseException) as exc:
        raise ConfigError(f"{where}: {_first_line(exc)}") from exc
    return {f.name: getattr(instance, f.name) for f in dataclasses.fields(instance)}


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return text[0] if text else type(exc).__name__


_REGISTRY: Registry | None = None


def get_registry(*, reload: bool = False) -> Registry:
    """The process-wide registry of installed plugins, loaded on first use."""
    global _REGISTRY
    if _REGISTRY is None or reload:
        _REGISTRY = Registry().load_entry_points()
    return _REGISTRY
