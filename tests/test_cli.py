"""The command line: every command exists, stages refuse non-run folders clearly, data check exit codes."""

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
