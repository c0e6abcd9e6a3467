"""The plugin is discovered through its entry point and imports Warp only when used."""

from __future__ import annotations

import subprocess
import sys
from importlib.metadata import entry_points


def test_entry_point_registered() -> None:
    eps = {ep.name: ep.value for ep in entry_points(group="mosiv")}
    assert eps.get("warp-mpm") == "mosiv_warp_mpm.plugin"


def test_plugin_import_does_not_import_warp() -> None:
    code = (
        "import sys, mosiv_warp_mpm.plugin as p\n"
        "seen = []\n"
        "p.mosiv_simulators(seen.append)\n"
        "assert seen[0].name == 'warp-mpm' and seen[0].kind == 'simulator'\n"
        "assert 'warp' not in sys.modules, 'warp imported at plugin import'\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True)
