"""The plugin registers `taichi-mpm` through the `mosiv` entry-point group without importing
taichi; options are validated with clear errors."""

import subprocess
import sys
from importlib.metadata import entry_points

import pytest

from mosiv_framework.errors import ConfigError


def test_entry_point_in_group_mosiv():
    eps = {ep.name: ep.value for ep in entry_points(group="mosiv")}
    assert eps.get("taichi-mpm") == "mosiv_taichi_mpm.plugin"


def test_importing_plugin_does_not_import_taichi():
    code = (
        "import sys, mosiv_taichi_mpm.plugin as p\n"
        "comps = []\n"
        "p.mosiv_simulators(comps.append)\n"
        "assert comps[0].name == 'taichi-mpm' and comps[0].kind == 'simulator', comps\n"
        "assert 'taichi' not in sys.modules, 'plugin import pulled in taichi'\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True)


def test_registry_lists_simulator():
    from mosiv_framework.registry import get_registry

    assert "taichi-mpm" in get_registry().names("simulator")


@pytest.mark.parametrize(
    "bad",
    [{"grid": 4}, {"substeps": 0}, {"device": "tpu"}, {"contact": "sticky"}],
)
def test_invalid_options_rejected(bad):
    from mosiv_taichi_mpm.options import TaichiMPMOptions

    with pytest.raises(ConfigError) as err:
        TaichiMPMOptions(**bad)
    assert next(iter(bad)) in str(err.value)
