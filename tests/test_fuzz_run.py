"""``mosiv run`` on every malformed scene of tests/test_scene_validation.py and every malformed
recipe of tests/test_recipe_fuzz.py (their generators, imported, not copied): the run refuses
each with its exit status (3 for a scene, 2 for a recipe), one message on stderr naming the
offending file or key, no traceback, every input file as it was and no run folder.

The run is the user's: the quickstart recipe with ``scene.path`` and ``output.dir`` given on the
command line, as its header suggests. The stages are replaced by a stub that fails the test
if reached: every refusal must come from the checks made before the first stage, which is also
what keeps each case well under a second.
"""

from __future__ import annotations

import hashlib
import importlib.util
import logging
import shutil
from pathlib import Path

import pytest

import mosiv_framework.pipeline.run as pipeline_run
from mosiv_framework.cli.main import main
from mosiv_framework.errors import EXIT_SCENE, EXIT_USAGE
from mosiv_framework.scene import write_example_scene

TESTS = Path(__file__).parent
QUICKSTART = TESTS.parent / "recipes" / "quickstart.yaml"


def _sibling(name: str):
    """A test module of this folder, loaded under a private name (pytest imports test modules
    with importlib, so they are not importable by name); its tests are not collected again."""
    spec = importlib.util.spec_from_file_location(f"_fuzz_run_{name}", TESTS / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


SCENES = _sibling("test_scene_validation")
RECIPES = _sibling("test_recipe_fuzz")
SCENE_CASE = {case.id: case.values for case in SCENES.CASES}


@pytest.fixture(autouse=True)
def restore_logging(monkeypatch):
    """main() configures the root logger and $MOSIV_LOG_LEVEL; put both back afterwards."""
    root = logging.getLogger()
    saved = (list(root.handlers), root.level, logging.getLogger("mosiv_framework").level)
    monkeypatch.delenv("MOSIV_LOG_LEVEL", raising=False)
    yield
    root.handlers[:] = saved[0]
    root.setLevel(saved[1])
    logging.getLogger("mosiv_framework").setLevel(saved[2])


@pytest.fixture
def stages(monkeypatch) -> list[str]:
    """The stages replaced by a stub recording that they were reached (metrics of nothing)."""
    reached: list[str] = []

    def stub(recipe, plain, scene, progress, warnings, *, started):
        reached.append(str(scene.root))
        return {"observed": {"cd_mm2": 0.0}, "future": None}

    monkeypatch.setattr(pipeline_run, "run_stages", stub)
    return reached


@pytest.fixture(scope="module")
def pristine(tmp_path_factory) -> Path:
    return write_example_scene(
        tmp_path_factory.mktemp("fuzz-run") / "scene",
        n_frames=SCENES.N_FRAMES,
        n_cameras=2,
        size=16,
    )


@pytest.fixture(scope="module", autouse=True)
def quickstart_unchanged():
    before = hashlib.sha256(QUICKSTART.read_bytes()).hexdigest()
    yield
    assert hashlib.sha256(QUICKSTART.read_bytes()).hexdigest() == before


def copy_scene(pristine: Path, where: Path) -> Path:
    return Path(shutil.copytree(pristine, where, symlinks=True))


def refused(capsys, argv: list[str], code: int) -> str:
    """Run ``mosiv ARGV`` in this process; check its exit status, that stderr holds one error
    message (``mosiv run: error: `` on its first line; a parser's message may go on over more)
    and log records only besides, and no traceback. Returns the message."""
    capsys.readouterr()
    status = main(argv)
    out, err = capsys.readouterr()
    assert status == code, err
    assert "Traceback" not in out + err and "internal error" not in err, err
    message = [line for line in err.splitlines() if not line.startswith("[mosiv] ")]
    assert message and message[0].startswith("mosiv run: error: "), err
    assert sum("error:" in line for line in message) == 1, err
    return "\n".join(message)


def run_argv(recipe: Path, scene: Path, out: Path, *overrides: str) -> list[str]:
    return ["run", str(recipe), f"scene.path={scene}", f"output.dir={out}", *overrides]


# --------------------------------------------------------------------------- the control
def test_the_pristine_scene_reaches_the_stages(pristine, tmp_path, stages, capsys):
    """Without this the cases below could pass for a reason that is not their fault. The
    quickstart generates a scene where none exists; a scene given on the command line, as its
    header suggests, is read and left as it was."""
    scene = copy_scene(pristine, tmp_path / "scene")
    before = SCENES.snapshot(scene)
    out = tmp_path / "out"
    assert main(run_argv(QUICKSTART, scene, out)) == 0, capsys.readouterr().err
    assert stages == [str(scene)] and SCENES.snapshot(scene) == before
    assert (out / "run.json").is_file() and (out / "recipe.yaml").is_file()


# -------------------------------------------------------------------- malformed scenes
@pytest.mark.parametrize(("mutate", "expected"), SCENES.CASES)
def test_run_refuses_a_malformed_scene(mutate, expected, pristine, tmp_path, stages, capsys):
    scene = copy_scene(pristine, tmp_path / "scene")
    mutate(scene)
    out = tmp_path / "out"
    before = SCENES.snapshot(tmp_path)
    message = refused(capsys, run_argv(QUICKSTART, scene, out), EXIT_SCENE)
    file = expected.split(": ")[0]
    assert expected in message and str(scene / file) in message, message
    assert stages == []
    # the scene, the other inputs and the place of the run folder: all as before
    assert SCENES.snapshot(tmp_path) == before
    assert not out.exists() and not (tmp_path / SCENES.PICKLE_MARKER).exists()


def test_the_users_cases_are_in_the_scene_set():
    for case in ("points-7-of-10-frames", "points-nan", "points-pickled"):
        assert case in SCENE_CASE
    assert len(SCENE_CASE) >= 40


# ------------------------------------------------------------------- malformed recipes
RECIPE_CASES = [c[0] for c in RECIPES.VALUE_CASES + RECIPES.TEXT_CASES]


@pytest.mark.parametrize("case", RECIPE_CASES)
def test_run_refuses_a_malformed_recipe(case, pristine, tmp_path, stages, capsys, monkeypatch):
    """The recipe names a valid scene: a recipe wrongly accepted would reach the stages."""
    monkeypatch.setenv("MOSIV_FUZZ_SECRET", RECIPES.SECRET)
    monkeypatch.chdir(tmp_path)  # relative paths a recipe might name land here, and are seen
    copy_scene(pristine, tmp_path / "scene")  # where RECIPES.base_recipe points scene.path
    data, needle = next((d, n) for c, d, n in RECIPES._cases(tmp_path) if c == case)
    path = tmp_path / f"{case}.yaml"
    path.write_bytes(data)
    before = SCENES.snapshot(tmp_path)
    message = refused(capsys, ["run", str(path)], EXIT_USAGE)
    assert needle in message and str(path) in message, message
    assert RECIPES.SECRET not in message
    assert stages == []
    assert SCENES.snapshot(tmp_path) == before
    assert not (tmp_path / "run").exists()


def test_enough_recipe_cases():
    assert len(RECIPE_CASES) >= 20


# --------------------------------------------------------- settings users ran into, on run
@pytest.mark.parametrize(
    ("override", "needle"),
    [
        ("identify.horizon_full_at=-1", "identify.horizon_full_at=-1"),
        ("evaluate.emd_samples=0", "evaluate.emd_samples=0: must be in [1, 8192]"),
        ("scene.path=${oc.env:MOSIV_FUZZ_SECRET}", "'oc.env' resolver"),
        ("output.dir=runs/${oc.env:MOSIV_FUZZ_SECRET}", "'oc.env' resolver"),
    ],
)
def test_bad_overrides_stop_run_before_anything(
    override, needle, pristine, tmp_path, stages, capsys, monkeypatch
):
    monkeypatch.setenv("MOSIV_FUZZ_SECRET", RECIPES.SECRET)
    monkeypatch.chdir(tmp_path)
    scene = copy_scene(pristine, tmp_path / "scene")
    before = SCENES.snapshot(tmp_path)
    argv = run_argv(QUICKSTART, scene, tmp_path / "out", override)
    message = refused(capsys, argv, EXIT_USAGE)
    assert needle in message and override.split("=")[0] in message, message
    assert RECIPES.SECRET not in message
    assert stages == [] and SCENES.snapshot(tmp_path) == before


def test_few_substeps_on_the_quickstart_name_the_cap(tmp_path, stages, capsys):
    """simulator.substeps=8 would cap E at 4,800 Pa on the quickstart's generated scene, ten
    times below its truth: an error before the scene is even generated."""
    scene, out = tmp_path / "scene", tmp_path / "out"
    argv = run_argv(QUICKSTART, scene, out, "simulator.substeps=8")
    message = refused(capsys, argv, EXIT_USAGE)
    assert "simulator.substeps=8 caps E of objects 1 (elastic), 2 (plasticine) at 4,800" in message
    assert "simulator.substeps >= " in message  # and says what is enough
    assert list(tmp_path.iterdir()) == []


def test_few_substeps_on_a_given_scene_name_the_cap(pristine, tmp_path, stages, capsys):
    """Without a scene.source the cap is checked against the scene read from disk."""
    scene = copy_scene(pristine, tmp_path / "scene")
    before = SCENES.snapshot(tmp_path)
    overrides = ("scene.source=null", "scene.generate=never", "simulator.substeps=8")
    argv = run_argv(QUICKSTART, scene, tmp_path / "out", *overrides)
    message = refused(capsys, argv, EXIT_USAGE)
    assert "simulator.substeps=8 caps E of object" in message and " Pa" in message, message
    assert stages == [] and SCENES.snapshot(tmp_path) == before
