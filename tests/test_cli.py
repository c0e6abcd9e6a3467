"""The command line: every command exists, unbuilt stages say so, data check exit codes."""

from __future__ import annotations

import subprocess
import sys

import pytest

from mosiv_framework.cli.main import build_parser, main


def test_every_design_command_is_present():
    parser = build_parser()
    sub = next(a for a in parser._actions if a.dest == "command")
    assert {"run", "plugins", "recipe", "data", "eval", "simulate", "diagnose", "bench"} <= set(
        sub.choices
    )


@pytest.mark.parametrize("command", ["eval", "simulate", "diagnose"])
def test_unbuilt_stages_say_so(command, capsys, tmp_path):
    assert main([command, str(tmp_path)]) == 2
    assert "does not provide yet" in capsys.readouterr().err


def test_console_script_runs():
    out = subprocess.run(
        [sys.executable, "-m", "mosiv_framework.cli.main", "--help"],
        capture_output=True,
        text=True,
        check=True,
    )
    assert "mosiv" in out.stdout and "plugins" in out.stdout


def test_data_synth_with_unknown_source_lists_sources(capsys, tmp_path):
    assert main(["data", "synth", str(tmp_path / "s"), "--source", "nope"]) == 2
    assert "valid scene_source names" in capsys.readouterr().err
