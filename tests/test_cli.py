"""The command line: every command exists, stages refuse non-run folders clearly, data check exit codes."""

from __future__ import annotations

import json
import os
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
def test_stages_on_a_folder_that_is_not_a_run_name_what_is_missing(command, capsys, tmp_path):
    assert main([command, str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert str(tmp_path) in err and "recipe.yaml" in err


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


def test_data_check_cli_reports_all_three_problems(tmp_path):
    import json

    import imageio.v3 as iio
    import numpy as np

    from mosiv_framework.scene.example import write_example_scene

    scene = write_example_scene(tmp_path / "scene", n_frames=4, n_cameras=3, size=24)
    ok = subprocess.run(["mosiv", "data", "check", str(scene)], capture_output=True, text=True)
    assert ok.returncode == 0 and "1 problem" not in ok.stdout
    (scene / "rgb" / "cam_01" / "0002.png").unlink()  # a removed frame
    mask_path = scene / "masks" / "cam_00" / "0001.png"
    mask = iio.imread(mask_path)
    mask[0, 0] = 7  # an object id scene.json does not declare
    iio.imwrite(mask_path, mask.astype(np.uint8))
    cams = json.loads((scene / "cameras.json").read_text())
    cams["cameras"][2]["world_to_camera"][0][0] = 2.0  # a scaled, non-rigid extrinsic
    (scene / "cameras.json").write_text(json.dumps(cams))
    bad = subprocess.run(["mosiv", "data", "check", str(scene)], capture_output=True, text=True)
    assert bad.returncode == 1
    assert "rgb/cam_01/0002.png" in bad.stdout
    assert "masks/cam_00/0001.png" in bad.stdout and "[7]" in bad.stdout
    assert "cameras.json" in bad.stdout and "rigid" in bad.stdout


@pytest.fixture
def restore_logging(monkeypatch):
    """main() configures the root logger and $MOSIV_LOG_LEVEL; put both back afterwards."""
    import logging

    root = logging.getLogger()
    saved = (list(root.handlers), root.level, logging.getLogger("mosiv_framework").level)
    monkeypatch.delenv("MOSIV_LOG_LEVEL", raising=False)
    yield
    root.handlers[:] = saved[0]
    root.setLevel(saved[1])
    logging.getLogger("mosiv_framework").setLevel(saved[2])


def _log_after(argv, capsys):
    """Run ``mosiv ARGV`` in this process, then log one record of each level from the core, a
    plugin and another library; returns (stdout, stderr) of it all."""
    import logging

    capsys.readouterr()
    assert main(argv) == 0
    for name in ("mosiv_framework.pipeline", "mosiv_gauss.train", "otherlib"):
        for level in (logging.DEBUG, logging.INFO, logging.WARNING):
            logging.getLogger(name).log(level, "%s %s", name, logging.getLevelName(level))
    return capsys.readouterr()


def test_log_levels_of_the_global_flags(capsys, restore_logging, monkeypatch):
    from mosiv_framework.registry import manager

    default = _log_after(["plugins", "--json"], capsys)
    json.loads(default.out)  # logs never mix into a command's output
    assert "[mosiv] mosiv_framework.pipeline INFO" in default.err
    assert "[mosiv] mosiv_gauss.train INFO" in default.err
    assert "[mosiv] warning: otherlib WARNING" in default.err
    assert "DEBUG" not in default.err and "otherlib INFO" not in default.err

    quiet = _log_after(["-q", "plugins", "--json"], capsys)
    assert "INFO" not in quiet.err
    assert "[mosiv] warning: mosiv_gauss.train WARNING" in quiet.err

    monkeypatch.setattr(manager, "_REGISTRY", None)  # loaded again, now at DEBUG
    verbose = _log_after(["-v", "plugins", "--json"], capsys)
    # at DEBUG each line names its logger; other libraries stay at WARNING and up
    assert "[mosiv] mosiv_gauss.train: mosiv_gauss.train DEBUG" in verbose.err
    assert "mosiv_framework.registry.manager: plugin 'core'" in verbose.err
    assert "otherlib DEBUG" not in verbose.err and "otherlib INFO" not in verbose.err


def test_quiet_and_verbose_exclude_each_other(capsys):
    with pytest.raises(SystemExit) as exit_:
        main(["-q", "-v", "plugins"])
    assert exit_.value.code == 2
    assert "not allowed with argument" in capsys.readouterr().err


def test_worker_processes_log_at_the_parent_level(monkeypatch):
    import logging

    from mosiv_framework.logs import level_from_flags

    monkeypatch.setenv("MOSIV_LOG_LEVEL", "warning")
    assert level_from_flags() == logging.WARNING  # the default when no flag is given
    assert level_from_flags(verbose=1) == logging.DEBUG
    code = (
        "import logging, sys\n"
        "from mosiv_framework.logs import configure_from_environment\n"
        "configure_from_environment()\n"
        "logging.getLogger('mosiv_framework.x').info('hidden')\n"
        "logging.getLogger('mosiv_framework.x').warning('shown')\n"
    )
    env = {**os.environ, "MOSIV_LOG_LEVEL": "WARNING"}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True)
    assert out.returncode == 0 and out.stdout == ""
    assert out.stderr == "[mosiv] warning: shown\n"


def test_version_lists_the_core_and_installed_plugins(capsys):
    from importlib import metadata

    with pytest.raises(SystemExit) as exit_:
        main(["--version"])
    assert exit_.value.code == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0] == f"mosiv-framework {metadata.version('mosiv-framework')}"
    listed = dict(line.split() for line in lines[1:])
    expected = {
        ep.dist.name: ep.dist.version
        for ep in metadata.entry_points(group="mosiv")
        if ep.dist is not None and ep.dist.name != "mosiv-framework"
    }
    assert listed == expected


def test_version_includes_a_plugin_installed_later(with_test_plugins):
    env = {**os.environ, "PYTHONPATH": str(with_test_plugins)}
    out = subprocess.run(
        [sys.executable, "-m", "mosiv_framework.cli.main", "--version"],
        env=env,
        capture_output=True,
        text=True,
        check=True,
    )
    assert "  mosiv-example-plugin 0.0.1" in out.stdout.splitlines()
