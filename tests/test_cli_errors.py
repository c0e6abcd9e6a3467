"""Every user-facing error of `mosiv` is one message naming what is wrong, with its own exit
status (docs/CLI.md), no traceback, and no file or folder made or changed where the command was
asked to read; Ctrl-C ends with one line naming the folder a rerun resumes from."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from mosiv_framework import errors
from mosiv_framework.cli.main import build_parser, main
from mosiv_framework.pipeline.formats import FormatError
from mosiv_framework.scene.example import write_example_scene

DOCS = Path(__file__).resolve().parents[1] / "docs" / "CLI.md"


@pytest.fixture(autouse=True)
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


def write_recipe(folder: Path, scene: Path, out: Path, **identify) -> Path:
    """A tiny recipe: the example scene (generated into ``scene`` if missing), oracle points,
    warp-mpm on CPU; nothing heavy runs unless the pipeline gets past the scene."""
    recipe = {
        "scene": {
            "path": str(scene),
            "generate": "if-missing",
            "source": {"name": "example", "n_frames": 6, "n_cameras": 2, "size": 24},
        },
        "reconstructor": {"name": "oracle", "max_points": 200},
        "lifter": {"name": "gt-points", "max_particles_per_object": 200},
        "simulator": {"name": "warp-mpm", "grid": 16, "substeps": 20, "device": "cpu"},
        "losses": {"chamfer": {"weight": 1.0, "max_points": 200}},
        "identify": {"velocity_iterations": 3, "param_iterations": 2, **identify},
        "evaluate": {"emd_samples": 64, "video_size": 48},
        "output": {"dir": str(out)},
    }
    path = folder / "tiny.yaml"
    path.write_text(yaml.safe_dump(recipe))
    return path


def fails(capsys, argv: list[str], code: int) -> str:
    """Run ``mosiv ARGV`` in this process; check its exit status and that stderr holds one
    error line and no traceback; returns that line."""
    capsys.readouterr()
    assert main(argv) == code
    err = capsys.readouterr().err
    assert "Traceback" not in err
    lines = [line for line in err.splitlines() if line.startswith("mosiv ")]
    assert len(lines) == 1, err
    return lines[0]


def snapshot(folder: Path) -> dict[str, bytes]:
    """Every file under ``folder`` (without following links) with its content."""
    return {
        str(p.relative_to(folder)): p.read_bytes()
        for p in sorted(folder.rglob("*"))
        if p.is_file() and not p.is_symlink()
    }


# ------------------------------------------------------------------------ recipe and usage
@pytest.mark.parametrize(
    "override, named",
    [("output.dir=${nope.x}", "nope.x"), ("output.dir=${foo:bar}", "unknown resolver 'foo'")],
)
def test_recipe_interpolation_errors_are_one_message(capsys, tmp_path, override, named):
    recipe = write_recipe(tmp_path, tmp_path / "scene", tmp_path / "run")
    before = snapshot(tmp_path)
    for command in (["run"], ["recipe", "show"], ["recipe", "validate"]):
        line = fails(capsys, [*command, str(recipe), override], errors.EXIT_USAGE)
        assert "output.dir" in line and named in line and str(recipe) in line
    assert snapshot(tmp_path) == before and sorted(os.listdir(tmp_path)) == ["tiny.yaml"]


def test_several_problems_are_counted_and_listed_one_per_line(capsys, tmp_path):
    recipe = write_recipe(tmp_path, tmp_path / "scene", tmp_path / "run")
    capsys.readouterr()
    argv = ["recipe", "validate", str(recipe), "simulator.name=nope", "lifter.name=nada"]
    assert main(argv) == errors.EXIT_USAGE
    err = capsys.readouterr().err
    head, *items = err.strip().splitlines()
    assert head == f"mosiv recipe: error: {len(items)} problems:" and len(items) >= 2
    assert all(item.startswith("- ") for item in items)
    assert any("'nope'" in item for item in items) and any("'nada'" in item for item in items)


# ---------------------------------------------------------------------- folders to be read
@pytest.mark.parametrize("command", ["eval", "simulate", "diagnose"])
def test_a_missing_run_folder_is_named_and_not_created(command, capsys, tmp_path):
    missing = tmp_path / "no-such-run"
    line = fails(capsys, [command, str(missing)], errors.EXIT_USAGE)
    assert str(missing) in line and "does not exist" in line and "mosiv run" in line
    assert not missing.exists()


@pytest.mark.parametrize("command", ["eval", "simulate", "diagnose"])
def test_a_run_folder_that_is_a_file_is_named_and_left_alone(command, capsys, tmp_path):
    afile = tmp_path / "notes.txt"
    afile.write_text("not a run\n")
    line = fails(capsys, [command, str(afile)], errors.EXIT_USAGE)
    assert str(afile) in line and "is a file, not a folder" in line
    assert afile.read_text() == "not a run\n" and os.listdir(tmp_path) == ["notes.txt"]


def test_replaying_a_missing_suite_is_an_error_and_creates_nothing(capsys, tmp_path):
    missing = tmp_path / "suite"
    line = fails(capsys, ["diagnose-suite", str(missing), "--replay"], errors.EXIT_USAGE)
    assert str(missing) in line and "does not exist" in line
    assert not missing.exists()


def test_scene_path_that_is_a_file_is_a_scene_error(capsys, tmp_path):
    afile = tmp_path / "scene.txt"
    afile.write_text("x")
    recipe = write_recipe(tmp_path, afile, tmp_path / "run")
    line = fails(capsys, ["run", str(recipe)], errors.EXIT_SCENE)
    assert f"scene.path={str(afile)!r}" in line and "not a scene folder" in line
    assert "scene.json" in line  # what would be valid
    assert afile.read_text() == "x" and not (tmp_path / "run").exists()


@pytest.fixture(scope="module")
def example_scene(tmp_path_factory) -> Path:
    return write_example_scene(tmp_path_factory.mktemp("ex") / "scene", n_frames=6, n_cameras=2)


@pytest.mark.parametrize("kind", ["folder", "symlink loop"])
def test_a_broken_frame_is_named_by_run_and_data_check(kind, capsys, tmp_path, example_scene):
    import shutil

    scene = shutil.copytree(example_scene, tmp_path / "scene", symlinks=True)
    frame = scene / "rgb" / sorted(os.listdir(scene / "rgb"))[0] / "0001.png"
    frame.unlink()
    frame.mkdir() if kind == "folder" else frame.symlink_to(frame.name)
    before = snapshot(scene)
    recipe = write_recipe(tmp_path, scene, tmp_path / "run")
    line = fails(capsys, ["run", str(recipe)], errors.EXIT_SCENE)
    assert str(frame) in line and "expected a PNG file" in line
    assert main(["data", "check", str(scene)]) == errors.EXIT_FINDING
    out = capsys.readouterr().out
    assert str(frame.relative_to(scene)) in out and "expected a PNG file" in out
    assert snapshot(scene) == before and (frame.is_dir() or frame.is_symlink())


# ----------------------------------------------------------------------- folders to write
def test_output_dir_that_is_a_file_or_under_one_is_refused(capsys, tmp_path):
    afile = tmp_path / "taken"
    afile.write_text("keep")
    for out in (afile, afile / "run"):
        recipe = write_recipe(tmp_path, tmp_path / "scene", out)
        line = fails(capsys, ["run", str(recipe)], errors.EXIT_OUTPUT)
        assert f"output.dir={str(out)!r}" in line and "not a folder" in line
    assert afile.read_text() == "keep" and not (tmp_path / "scene").exists()


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into read-only folders")
def test_output_dir_in_a_read_only_folder_is_refused(capsys, tmp_path):
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o555)
    try:
        recipe = write_recipe(tmp_path, tmp_path / "scene", locked / "run")
        line = fails(capsys, ["run", str(recipe)], errors.EXIT_OUTPUT)
        assert str(locked) in line and "not writable" in line
        assert os.listdir(locked) == []
    finally:
        locked.chmod(0o755)


def test_a_permission_error_deep_inside_names_the_path(capsys, tmp_path, monkeypatch):
    import mosiv_framework.pipeline as pipeline

    denied = tmp_path / "run" / "recipe.yaml"

    def refuse(recipe, *, run_dir, force):
        raise PermissionError(13, "Permission denied", str(denied))

    monkeypatch.setattr(pipeline, "run_pipeline", refuse)
    recipe = write_recipe(tmp_path, tmp_path / "scene", tmp_path / "run")
    line = fails(capsys, ["run", str(recipe)], errors.EXIT_OUTPUT)
    assert str(denied) in line and "permission denied" in line


@pytest.mark.parametrize(
    "argv",
    [
        ["data", "synth", "OUT", "--source", "example"],
        ["data", "suite", "OUT", "--source", "example", "--only", "E-P"],
        ["diagnose-suite", "OUT", "--small"],
    ],
    ids=lambda argv: " ".join(argv[:2]),
)
def test_generators_refuse_an_output_that_is_a_file(argv, capsys, tmp_path):
    afile = tmp_path / "out"
    afile.write_text("keep")
    line = fails(capsys, [str(afile) if a == "OUT" else a for a in argv], errors.EXIT_OUTPUT)
    assert str(afile) in line and "not a folder" in line and afile.read_text() == "keep"


# ---------------------------------------------------- every error kind, and everything else
@pytest.mark.parametrize(
    "error",
    [
        errors.ConfigError("bad option"),
        errors.SceneFormatError("bad scene"),
        errors.SimulationDiverged(object_id=1, frame=2, substep=3, reason="nan", advice="halve"),
        errors.StageNotAvailable("no reconstructor"),
        errors.OutputError("refused"),
        FormatError("unknown format"),
    ],
    ids=lambda e: type(e).__name__,
)
def test_each_error_kind_ends_with_its_documented_status(error, capsys, tmp_path, monkeypatch):
    import mosiv_framework.pipeline as pipeline

    def raise_it(recipe, *, run_dir, force):
        raise error

    monkeypatch.setattr(pipeline, "run_pipeline", raise_it)
    recipe = write_recipe(tmp_path, tmp_path / "scene", tmp_path / "run")
    line = fails(capsys, ["run", str(recipe)], error.exit_code)
    assert line == f"mosiv run: error: {str(error).removeprefix('- ')}"
    assert error.exit_code in documented_codes() and error.exit_code not in (0, 1, 70, 130)


def test_an_unexpected_error_is_one_line_pointing_to_verbose(capsys, tmp_path, monkeypatch):
    import mosiv_framework.pipeline as pipeline

    def bug(recipe, *, run_dir, force):
        raise ZeroDivisionError("division by zero")

    monkeypatch.setattr(pipeline, "run_pipeline", bug)
    recipe = write_recipe(tmp_path, tmp_path / "scene", tmp_path / "run")
    line = fails(capsys, ["-q", "run", str(recipe)], errors.EXIT_INTERNAL)
    assert "internal error: ZeroDivisionError: division by zero" in line
    assert f"`mosiv -v run {recipe}`" in line  # -q dropped: it cannot go with -v
    assert main(["-v", "run", str(recipe)]) == errors.EXIT_INTERNAL
    err = capsys.readouterr().err
    assert "Traceback" in err and "in bug" in err


# ------------------------------------------------------------------------------- Ctrl-C
def test_ctrl_c_inside_a_lazy_import_still_reads_as_an_interruption(capsys, tmp_path, monkeypatch):
    """Python 3.11 wraps an exception raised while a class is being set up in a RuntimeError:
    a Ctrl-C that lands in a lazy import (torch's at the first optimiser step) arrives so."""
    import mosiv_framework.pipeline as pipeline

    class Field:
        def __set_name__(self, owner, name):
            raise KeyboardInterrupt

    def lazy_import(recipe, *, run_dir, force):
        type("EqualityConstraint", (), {"_parents": Field()})

    monkeypatch.setattr(pipeline, "run_pipeline", lazy_import)
    recipe = write_recipe(tmp_path, tmp_path / "scene", tmp_path / "run")
    assert main(["run", str(recipe)]) == errors.EXIT_INTERRUPTED
    err = capsys.readouterr().err
    assert "internal error" not in err
    assert err.strip().splitlines()[-1].startswith("mosiv run: interrupted; rerun the same command")


def _default_sigint() -> None:
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def test_ctrl_c_ends_with_one_line_naming_the_run_folder(tmp_path):
    pytest.importorskip("mosiv_warp_mpm")
    run_dir = tmp_path / "run"
    recipe = write_recipe(tmp_path, tmp_path / "scene", run_dir, param_iterations=2000)
    proc = subprocess.Popen(
        [sys.executable, "-m", "mosiv_framework.cli.main", "run", str(recipe)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        # a shell starts background jobs with SIGINT ignored, and children inherit that (Python
        # then installs no handler): give the run the disposition a terminal's Ctrl-C meets
        preexec_fn=_default_sigint,
    )
    seen, deadline = [], time.monotonic() + 300
    while time.monotonic() < deadline:  # the identify stage has begun: earlier ones are done
        line = proc.stderr.readline()
        seen.append(line)
        if "identifying" in line or not line:
            break
    time.sleep(1.0)
    proc.send_signal(signal.SIGINT)
    _, rest = proc.communicate(timeout=120)
    err = "".join(seen) + rest
    # 130, or killed by SIGINT, which a shell reports as 130 as well: when the interrupt was
    # raised inside code a C extension ran (torch's lazy imports at the first optimiser step),
    # CPython notes it as unhandled even though mosiv caught it, and after a normal shutdown
    # re-raises SIGINT on itself (seen in 1 of 6 runs under load, strace: kill(self, SIGINT))
    assert proc.returncode in (errors.EXIT_INTERRUPTED, -signal.SIGINT), err
    assert "Traceback" not in err
    said = [line for line in err.splitlines() if "interrupted" in line]
    assert said == [
        "mosiv run: interrupted; rerun the same command to resume from the last finished "
        f"stage (run folder: {run_dir})"
    ]
    assert err.rstrip().splitlines()[-1] == said[0]
    assert (run_dir / "stages" / "lift.json").is_file()  # what the rerun resumes after


# --------------------------------------------------------------------------------- docs
def documented_codes() -> dict[int, str]:
    """Exit status -> meaning, from the exit-status table of docs/CLI.md."""
    rows = re.findall(r"^\| `(\d+)` \| ([^|]+) \|", DOCS.read_text(), flags=re.M)
    return {int(code): meaning.strip() for code, meaning in rows}


def test_docs_list_every_exit_status_and_every_command():
    assert set(documented_codes()) == set(errors.EXIT_CODES)
    text = DOCS.read_text()
    sub = next(a for a in build_parser()._actions if a.dest == "command")
    missing = [name for name in sub.choices if f"`mosiv {name}" not in text]
    assert missing == []


def test_building_the_parser_loads_no_heavy_library():
    """``mosiv --help`` and every command's parsing stay fast: building the parser imports
    neither torch nor the capture package's pycolmap and imageio (they load when a command
    runs). Checked in a fresh interpreter, where nothing was imported before."""
    import subprocess
    import sys

    probe = (
        "import sys\n"
        "from mosiv_framework.cli.main import build_parser\n"
        "build_parser()\n"
        "heavy = ('torch', 'pycolmap', 'imageio', 'warp', 'taichi')\n"
        "print(sorted(m for m in sys.modules if m.split('.')[0] in heavy))\n"
    )
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]", out.stdout
