"""Discovers plugins, collects the components they register, and builds them from options.

Each entry point of the group ``mosiv`` is loaded in its own guard: a plugin that fails to
import, implements a hook no spec declares (a misspelled ``mosiv_loss`` for ``mosiv_losses``),
or whose hook raises, is recorded as broken with its error and the others still load.
Set ``MOSIV_DISABLE_PLUGINS=name1,name2`` (entry-point or distribution names) to skip plugins.
"""

from __future__ import annotations

import dataclasses
import difflib
import logging
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

logger = logging.getLogger(__name__)

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


def unknown_hooks_message(unknown: list[str]) -> str:
    """Why a plugin with hooks no spec declares was not loaded, with the valid hook names."""
    valid = sorted(HOOK_OF_KIND.values())
    parts = []
    for hook_name in unknown:
        close = difflib.get_close_matches(hook_name, valid, n=1)
        parts.append(f"{hook_name!r}" + (f" (did you mean {close[0]!r}?)" if close else ""))
    noun = "hook" if len(unknown) == 1 else "hooks"
    return f"unknown {noun} {', '.join(parts)}; valid hooks: {', '.join(valid)}"


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
                self._record_broken(
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
        except Exception as exc:  # e.g. a hook whose arguments do not match its spec
            self._record_broken(BrokenPlugin(name, distribution, f"{type(exc).__name__}: {exc}"))
            return None
        problem = self._check_pending(module)
        if problem is not None:
            # a misspelled hook would otherwise register nothing without a word; the whole
            # plugin is set aside so a half-registered plugin cannot pass for a working one
            self._pm.unregister(module)
            self._record_broken(BrokenPlugin(name, distribution, problem))
            return None
        info = PluginInfo(name, distribution, version, getattr(module, "__name__", repr(module)))
        for kind, hook_name in HOOK_OF_KIND.items():
            for impl in getattr(self._pm.hook, hook_name).get_hookimpls():
                if impl.plugin is not module:
                    continue
                try:
                    impl.function(register=self._register_callback(info, kind))
                except Exception as exc:
                    self._record_broken(
                        BrokenPlugin(
                            name,
                            distribution,
                            f"{hook_name} raised {type(exc).__name__}: {exc}",
                            traceback.format_exc(),
                        )
                    )
        self.plugins[name] = info
        logger.debug(
            "plugin %r (%s %s) registered %d component(s)",
            name,
            distribution,
            version,
            len(info.components),
        )
        return info

    def _check_pending(self, module: object) -> str | None:
        """pluggy's ``check_pending``: None, or why ``module`` implements hooks that no spec
        declares (all of them, with the valid hook names).

        Plugins that failed are unregistered at once, so whatever ``check_pending`` finds was
        brought in by ``module``.
        """
        try:
            self._pm.check_pending()
        except pluggy.PluginValidationError:
            pass
        else:
            return None
        unknown = sorted(
            hook_name
            for hook_name, caller in vars(self._pm.hook).items()
            if not hook_name.startswith("_")
            and not caller.has_spec()
            and any(i.plugin is module and not i.optionalhook for i in caller.get_hookimpls())
        )
        return unknown_hooks_message(unknown)

    def _record_broken(self, broken: BrokenPlugin) -> None:
        self.broken.append(broken)
        logger.warning(
            "plugin %r (%s) is broken and was not loaded: %s",
            broken.name,
            broken.distribution,
            broken.error,
        )

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

    def find(self, spec: str) -> Component:
        """The component named by ``spec``: ``KIND:NAME``, or a NAME that only one kind has.

        Raises ConfigError: for an unknown name, listing the closest ``KIND:NAME`` matches; for
        a name several kinds share, listing those kinds.
        """
        kind, sep, name = spec.partition(":")
        if sep:
            if kind not in KINDS:
                raise ConfigError(
                    f"unknown component kind {kind!r} in {spec!r}; valid kinds: {', '.join(KINDS)}"
                )
            return self.get(kind, name)
        matches = [c for kind in KINDS for c in self.components(kind) if c.name == spec]
        if len(matches) == 1:
            return matches[0]
        if matches:
            kinds = ", ".join(c.kind for c in matches)
            raise ConfigError(
                f"{spec!r} names a component of several kinds ({kinds}); write KIND:NAME, "
                f"e.g. {matches[0].kind}:{spec}"
            )
        every = [c for kind in KINDS for c in self.components(kind)]
        close = difflib.get_close_matches(spec, sorted({c.name for c in every}), n=5, cutoff=0.5)
        hint = ", ".join(f"{c.kind}:{c.name}" for n in close for c in every if c.name == n)
        hint = hint or "none close"
        msg = f"no component is named {spec!r}; closest: {hint} (mosiv plugins lists them all)"
        if self.broken:
            msg += "; broken plugins: " + ", ".join(f"{b.name} ({b.error})" for b in self.broken)
        raise ConfigError(msg)

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
