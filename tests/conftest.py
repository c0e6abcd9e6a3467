"""Shared fixtures of the core test suite."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

TESTS = Path(__file__).parent


@pytest.fixture(scope="session")
def test_plugins_site(tmp_path_factory) -> Path:
    """The example and the deliberately broken plugin, really installed into a private folder.

    The folder is put on sys.path by the tests that need it, so the user's environment never
    sees the broken plugin.
    """
    site = tmp_path_factory.mktemp("plugin-site")
    for name in ("example", "broken"):
        subprocess.run(
            [
                sys.executable,
                "-m",
                "pip",
                "install",
                "-q",
                "--no-deps",
                "--no-build-isolation",
                "--no-compile",
                "--target",
                str(site),
                str(TESTS / "plugins" / name),
            ],
            check=True,
        )
    return site


@pytest.fixture
def with_test_plugins(test_plugins_site, monkeypatch):
    monkeypatch.syspath_prepend(str(test_plugins_site))
    return test_plugins_site
