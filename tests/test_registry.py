"""The plugin registry: discovery, guards, clashes, disabling, option validation, light imports."""

from __future__ import annotations

import json
import subprocess
import sys
import types
from dataclasses import dataclass, field

import pytest

from mosiv_framework.errors import ConfigError
from mosiv_framework.registry import Component, Registry, hookimpl


def test_installed_plugins_register_their_components():
    registry = Registry().load_entry_points(disabled=[])
    assert "core" in registry.plugins
    assert {"chamfer", "scene-chamfer", "silhouette", "scene-silhouette"} <= set(
        registry.names("loss")
    )
    assert set(registry.names("constitutive_law")) == {
        "elastic",
        "plasticine",
        "sand",
        "newtonian",
        "non_newtonian",
        "snow",
        "elastic_corotated",
        "plasticine_corotated",
    }
    assert {"linear_drag", "quadratic_drag", "wind", "gravity"} <= set(
        registry.names("physics_term")
    )
    assert registry.get("loss", "chamfer").distribution == "mosiv-framework"


def test_example_plugin_is_discovered_and_broken_one_reported(with_test_plugins):
    registry = Registry().load_entry_points(disabled=[])
    assert registry.plugins["example"].distribution == "mosiv-example-plugin"
    assert registry.plugins["example"].version == "0.0.1"
    loss = registry.create("loss", "centroid", {"weight": 2.0})
    assert loss.weight == 2.0
    # the broken plugin is reported by name with its error, and did not stop the others
    [broken] = [b for b in registry.broken if b.name == "broken"]
    assert broken.distribution == "mosiv-broken-plugin"
    assert "not-installed-anywhere" in broken.error
    assert "core" in registry.plugins


def test_disable_plugins_by_environment(with_test_plugins, monkeypatch):
    monkeypatch.setenv("MOSIV_DISABLE_PLUGINS", "broken, mosiv-example-plugin")
    registry = Registry().load_entry_points()
    assert "example" not in registry.plugins
    assert not [b for b in registry.broken if b.name == "broken"]
    assert set(registry.disabled) == {"broken", "example"}


class _Plugin:
    def __init__(self, name):
        self.name = name

    @hookimpl
    def mosiv_losses(self, register):
        register(Component("loss", "same-name", factory=dict, description=self.name))


def test_name_clash_reports_both_distributions():
    registry = Registry()
    registry.add_plugin(_Plugin("a"), name="a", distribution="dist-a")
    registry.add_plugin(_Plugin("b"), name="b", distribution="dist-b")
    [conflict] = registry.conflicts
    assert "dist-a" in conflict.message() and "dist-b" in conflict.message()
    with pytest.raises(ConfigError, match="dist-a.*dist-b"):
        registry.get("loss", "same-name")


def test_hook_that_raises_is_reported_not_fatal():
    class Raising:
        @hookimpl
        def mosiv_simulators(self, register):
            raise RuntimeError("backend misconfigured")

    registry = Registry()
    registry.add_plugin(Raising(), name="raising", distribution="dist-raising")
    [broken] = registry.broken
    assert broken.name == "raising" and "backend misconfigured" in broken.error


def test_register_rejects_wrong_kind_and_non_records():
    class WrongKind:
        @hookimpl
        def mosiv_losses(self, register):
            register(Component("simulator", "x", factory=dict))

    registry = Registry()
    registry.add_plugin(WrongKind(), name="wrong")
    assert "mosiv_losses" in registry.broken[0].error
    with pytest.raises(ValueError, match="unknown component kind"):
        Component("shader", "x", factory=dict)


@dataclass
class _Options:
    grid: int = 64
    mode: str = "a"

    def __post_init__(self):
        if self.mode not in ("a", "b"):
            raise ValueError(f"mode must be 'a' or 'b', got {self.mode!r}")


def test_unknown_name_lists_valid_choices_and_options_are_validated():
    class Provider:
        @hookimpl
        def mosiv_simulators(self, register):
            register(Component("simulator", "toy", factory=lambda **o: o, options=_Options))

    registry = Registry()
    registry.add_plugin(Provider(), name="provider")
    with pytest.raises(ConfigError, match="valid simulator names: toy"):
        registry.get("simulator", "nope")
    assert registry.create("simulator", "toy", {"grid": 32}) == {"grid": 32, "mode": "a"}
    with pytest.raises(ConfigError) as err:
        registry.create("simulator", "toy", {"grdi": 1, "grid": "many"})
    text = str(err.value)
    assert (
        "no option 'grdi'" in text and "valid options: grid, mode" in text and "grid='many'" in text
    )
    with pytest.raises(ConfigError, match="mode must be 'a' or 'b'"):
        registry.create("simulator", "toy", {"mode": "c"})


def test_import_is_light():
    """Neither importing the core nor loading every plugin imports a backend."""
    code = (
        "import sys, mosiv_framework, mosiv_framework.interfaces, mosiv_framework.recipes\n"
        "from mosiv_framework.registry import get_registry\n"
        "get_registry()\n"
        "heavy = sorted(m for m in sys.modules if m.split('.')[0] in ('warp', 'taichi'))\n"
        "print(heavy)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


def test_plugins_command_json_lists_plugins_and_broken(with_test_plugins, capsys, monkeypatch):
    from mosiv_framework.cli.main import main
    from mosiv_framework.registry import manager

    monkeypatch.setattr(manager, "_REGISTRY", Registry().load_entry_points(disabled=[]))
    assert main(["plugins", "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    dists = {p["distribution"] for p in report["plugins"]}
    assert {"mosiv-framework", "mosiv-example-plugin"} <= dists
    assert [b["name"] for b in report["broken"]] == ["broken"]


def test_option_called_name_is_rejected():
    @dataclass
    class Shadowing:
        name: str = ""

    with pytest.raises(ValueError, match="may not have a field called 'name'"):
        Component("scene_source", "x", factory=dict, options=Shadowing)


def _module_plugin(name: str, **hooks) -> types.ModuleType:
    """A plugin module built in the test, as an entry point would load it."""
    module = types.ModuleType(name)
    for hook_name, fn in hooks.items():
        fn.__name__ = hook_name
        setattr(module, hook_name, hookimpl(fn))
    return module


def test_misspelled_hook_makes_a_broken_plugin_and_the_others_still_load(capsys, monkeypatch):
    def register_loss(register):
        register(Component("loss", "never-registered", factory=dict))

    def register_good(register):
        register(Component("loss", "good-loss", factory=dict))

    registry = Registry()
    typo = _module_plugin("typo_plugin", mosiv_loss=register_loss)
    assert registry.add_plugin(typo, name="typo", distribution="mosiv-typo") is None
    registry.add_plugin(_module_plugin("good_plugin", mosiv_losses=register_good), name="good")
    [broken] = registry.broken
    assert broken.name == "typo" and broken.distribution == "mosiv-typo"
    assert "unknown hook 'mosiv_loss'" in broken.error
    assert "did you mean 'mosiv_losses'" in broken.error
    assert "valid hooks: mosiv_bench_peers, mosiv_constitutive_laws, mosiv_lifters" in broken.error
    assert registry.names("loss") == ["good-loss"] and "typo" not in registry.plugins
    # unregistered at once: the next plugin's check does not trip over the typo again
    assert len(registry.broken) == 1

    from mosiv_framework.cli.main import main
    from mosiv_framework.registry import manager

    monkeypatch.setattr(manager, "_REGISTRY", registry)
    assert main(["plugins"]) == 0
    out = capsys.readouterr().out
    assert "BROKEN mosiv-typo (plugin 'typo'): unknown hook 'mosiv_loss'" in out


def test_optional_unknown_hook_is_allowed():
    class Optional:
        @hookimpl(optionalhook=True)
        def mosiv_future_hook(self, register):
            pass

    registry = Registry()
    assert registry.add_plugin(Optional(), name="optional") is not None
    assert registry.broken == []


def _two_kinds_registry() -> Registry:
    class Provider:
        @hookimpl
        def mosiv_losses(self, register):
            register(Component("loss", "shared", factory=dict))
            register(Component("loss", "chamfer-like", factory=dict))

        @hookimpl
        def mosiv_simulators(self, register):
            register(Component("simulator", "shared", factory=dict))
            register(Component("simulator", "toy", factory=dict, options=_Options))

    registry = Registry()
    registry.add_plugin(Provider(), name="provider")
    return registry


def test_find_by_kind_and_name_unique_name_ambiguous_and_unknown():
    registry = _two_kinds_registry()
    assert registry.find("toy").kind == "simulator"
    assert registry.find("loss:shared").kind == "loss"
    with pytest.raises(ConfigError, match=r"several kinds \(simulator, loss\).*KIND:NAME"):
        registry.find("shared")
    with pytest.raises(ConfigError, match="closest: loss:chamfer-like"):
        registry.find("chamfer-lik")
    with pytest.raises(ConfigError, match="unknown component kind 'shader'"):
        registry.find("shader:toy")
    with pytest.raises(ConfigError, match="valid simulator names: shared, toy"):
        registry.find("simulator:nope")


@dataclass(frozen=True)
class _BaseDocOptions:
    """grid: cells along the longest side; substeps (1/frame): steps per video frame.

    Grouped:
        lr_a, lr_b: learning rates
    """

    grid: int = 64
    substeps: int = 100
    lr_a: float = 0.1
    lr_b: float = 0.2


@dataclass(frozen=True)
class _DocOptions(_BaseDocOptions):
    """A subclass documents its own fields; the base's come from the base's docstring."""

    #: seeds every random draw
    seed: int = 0
    sizes: tuple[int, ...] = (1, 2)
    path: str = field(default="out", metadata={"doc": "where results go"})
    undocumented: bool = False


def test_option_schema_takes_docs_from_docstrings_comments_metadata_and_bases():
    from mosiv_framework.registry.optiondoc import option_schema

    schema = {e["name"]: e for e in option_schema(_DocOptions)}
    assert list(schema) == [
        "grid", "substeps", "lr_a", "lr_b", "seed", "sizes", "path", "undocumented"
    ]  # fmt: skip
    assert schema["grid"] == {
        "name": "grid",
        "type": "int",
        "default": 64,
        "doc": "cells along the longest side",
    }
    assert schema["substeps"]["doc"] == "(1/frame) steps per video frame"
    assert schema["lr_a"]["doc"] == schema["lr_b"]["doc"] == "learning rates"
    assert schema["seed"]["doc"] == "seeds every random draw"
    assert schema["path"]["doc"] == "where results go"
    assert schema["sizes"]["type"] == "tuple[int, ...]" and schema["sizes"]["default"] == (1, 2)
    assert schema["undocumented"]["doc"] == ""


def test_plugins_options_command_text_json_and_errors(capsys, monkeypatch):
    from mosiv_framework.cli.main import main
    from mosiv_framework.registry import manager

    registry = _two_kinds_registry()
    monkeypatch.setattr(manager, "_REGISTRY", registry)
    assert main(["plugins", "--options", "simulator:toy"]) == 0
    out = capsys.readouterr().out
    assert "simulator 'toy'" in out
    assert "grid: int, default 64" in out and "mode: str, default 'a'" in out
    assert main(["plugins", "--options", "toy", "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["kind"] == "simulator" and report["name"] == "toy"
    assert [(o["name"], o["default"]) for o in report["options"]] == [("grid", 64), ("mode", "a")]
    assert main(["plugins", "--options", "loss:chamfer-like"]) == 0
    assert "takes no options" in capsys.readouterr().out
    assert main(["plugins", "--options", "toi"]) == 2
    assert "closest: simulator:toy" in capsys.readouterr().err
    assert main(["plugins", "--options", "shared"]) == 2
    assert "several kinds (simulator, loss)" in capsys.readouterr().err


def test_installed_components_document_every_shared_mpm_option():
    from mosiv_framework.registry.optiondoc import option_schema

    registry = Registry().load_entry_points(disabled=[])
    for name in registry.names("simulator"):
        docs = {e["name"]: e["doc"] for e in option_schema(registry.get("simulator", name).options)}
        assert all(docs[k] for k in ("grid", "substeps", "device", "contact")), (name, docs)
