"""benchmarks/genesis_wheels.py: the wheels the GPU machine needs for Genesis follow the
requirements of what is installed here, leave out the image's packages and the ones already
staged, and pin the versions installed here."""

from __future__ import annotations

import importlib
import importlib.metadata as metadata
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture
def wheels(monkeypatch):
    monkeypatch.syspath_prepend(str(ROOT / "benchmarks"))
    return importlib.import_module("genesis_wheels")


def test_the_closure_follows_requirements_and_leaves_out_the_image(wheels):
    # kornia needs kornia_rs (not on the GPU image), torch and numpy (on it)
    closure = wheels.requirement_closure("kornia")
    assert closure["kornia"] == metadata.version("kornia")
    assert closure["kornia-rs"] == metadata.version("kornia_rs")
    assert "torch" not in closure and "numpy" not in closure
    assert not set(closure) & (wheels.GPU_IMAGE | wheels.NOT_IMPORTED)


def test_a_package_not_installed_here_is_named(wheels):
    with pytest.raises(SystemExit, match="no-such-package-here is not installed here"):
        wheels.requirement_closure("no-such-package-here")


def test_names_already_staged_are_skipped(wheels, tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(wheels, "requirement_closure", lambda root: {"trimesh": "4.0", "av": "1"})
    (tmp_path / "trimesh-4.5.0-py3-none-any.whl").write_bytes(b"")
    assert wheels.main(["--skip-present", str(tmp_path)]) == 0
    assert capsys.readouterr().out.split() == ["av==1"]
