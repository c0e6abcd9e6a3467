"""Real recordings in, results out: a scene through ``mosiv data capture`` and ``mosiv data
import`` identifies as the scene itself does, and recipes are honest about what a scene needs.

The round trip (benchmarks/capture_roundtrip.py --quick, which this test drives) runs
recipes/video_quickstart.yaml with the short schedule of tests/test_pipeline_video.py on the
tiny synthetic scene, then on the same scene written in centimetres with y up through a barrel
lens with one camera starting a frame late and a clean plate per camera, and imported back
(materials, units, up, ground and the late camera's offset given: the thrown objects move from
the first frame, so there is no motion onset to estimate offsets from; lens undone, masks and
domain from the classical segmenter's hull with the plates as its background). The imported scene's reference ground truth is the capture's, mapped by
import.json's alignment and matched to the import's object ids by mask overlap, so both runs
are scored the same way and compared object by object.

The targets (E within 10 %, future CD within 20 % of the direct run) are for the paper
size on a GPU (benchmarks/capture_roundtrip.py without --quick). The tiny CPU version cannot
test them: at this size from-video identification barely fixes E (docs/RESULTS.md, "A
recording through a rig and back"). MEASURED on the 2-core development machine, idle, code
bf4783c (clean plates, the noise threshold, the rim trimmed): E 3.89e4 and 3.77e4 Pa direct,
5.25e4 and 5.19e4 Pa imported (true 4.75e4 and 5.17e4 Pa), 35-38 % apart, so no E bound is set
here; future Chamfer distance 3,753 mm^2 direct and 6,961 mm^2 imported (1.9x); 78 s for the
whole round trip. CI checks what the tiny version does support: the reference reaches the
imported frame exactly (camera centres), both runs identify every object within the law's
bounds, and the imported future CD stays within MAX_FUTURE_CD_RATIO of the direct one.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from mosiv_framework.capture.reference import reference_transform
from mosiv_framework.cli.main import main
from mosiv_framework.errors import ConfigError
from mosiv_framework.recipes import load_recipe
from mosiv_framework.scene import read_scene, write_example_scene
from mosiv_framework.testing.scripts import load_script

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "benchmarks" / "capture_roundtrip.py"
QUICKSTART = ROOT / "recipes" / "quickstart.yaml"

#: imported / direct future Chamfer distance; MEASURED 1.9 (see the module docstring)
MAX_FUTURE_CD_RATIO = 6.0
#: the bounds of E (Pa) every law here identifies within
E_BOUNDS = (1e3, 1e7)


def load_benchmark():
    # the benchmark imports its sibling scripts when it runs, as from benchmarks/
    return load_script(SCRIPT, register=True, keep_path=True)


# ------------------------------------------------------------------------ honest recipes
def test_a_missing_scene_is_an_error_unless_the_recipe_generates_it(tmp_path, capsys):
    typo = tmp_path / "scnee"
    argv = ["run", str(QUICKSTART), f"scene.path={typo}", f"output.dir={tmp_path / 'run'}"]
    assert main([*argv, "scene.generate=never"]) == 2
    err = capsys.readouterr().err
    assert f"scene.path '{typo}' does not exist" in err, err
    assert "scene.generate=if-missing" in err and "synth" in err, err
    assert not typo.exists() and not (tmp_path / "run").exists()


def test_generate_takes_if_missing_or_never_and_if_missing_needs_a_source(tmp_path):
    with pytest.raises(ConfigError, match="scene.generate='sometimes'"):
        load_recipe(QUICKSTART, ["scene.generate=sometimes"])
    with pytest.raises(ConfigError, match="needs scene.source"):
        load_recipe(QUICKSTART, ["scene.source=null"])
    # the shipped recipe generates its synthetic scene where none exists yet
    recipe = load_recipe(QUICKSTART, [f"scene.path={tmp_path / 's'}"])
    assert recipe.scene.generate == "if-missing"


def test_a_ground_truth_recipe_refuses_a_scene_without_gt(tmp_path, capsys):
    scene = write_example_scene(tmp_path / "recording", n_frames=4, n_cameras=2, size=16)
    shutil.rmtree(scene / "gt")  # as every imported recording: no ground truth
    argv = ["run", str(QUICKSTART), f"scene.path={scene}", f"output.dir={tmp_path / 'run'}"]
    assert main(argv) == 3  # a scene error
    err = capsys.readouterr().err
    assert "no ground truth" in err and "reconstructor 'oracle'" in err, err
    assert "recipes/video_quickstart.yaml" in err and "recipes/video_paper.yaml" in err, err
    assert not (tmp_path / "run").exists()


# ---------------------------------------------------------------------------- round trip
def test_imported_capture_identifies_like_the_scene(tmp_path):
    bench = load_benchmark()
    result = bench.roundtrip(tmp_path, bench.QUICK_RECIPE, bench.QUICK, bench.QUICK_SEGMENTER)
    print(bench.table(result))
    (tmp_path / "result.json").write_text(json.dumps(result, indent=2))
    # the transform that carried the reference maps every original camera centre onto the
    # imported one: the reference lives in the frame the imported run was scored in
    capture = json.loads((tmp_path / "capture" / "capture.json").read_text())
    record = json.loads((tmp_path / "imported" / "import.json").read_text())
    linear, offset = reference_transform(capture, record)
    original, imported = read_scene(tmp_path / "scene"), read_scene(tmp_path / "imported")
    for cam in original.cameras:
        centre = linear @ cam.camera_center.numpy() + offset
        np.testing.assert_allclose(imported.camera(cam.id).camera_center.numpy(), centre, atol=1e-6)
    assert result["imported"]["future_cd_mm2"] is not None
    comparison = result["comparison"]
    assert set(comparison["E_rel_to_direct"]) == set(result["direct"]["objects"])
    for run in ("direct", "imported"):
        for oid, obj in result[run]["objects"].items():
            assert E_BOUNDS[0] <= obj["E"] <= E_BOUNDS[1], (run, oid, result)
    ratio = result["imported"]["future_cd_mm2"] / result["direct"]["future_cd_mm2"]
    assert ratio < MAX_FUTURE_CD_RATIO, result


def test_table_sets_the_import_against_the_run_to_run_spread():
    """With --spread-seed the table adds the reseeded direct run's differences: the yardstick
    for the imported run's (compare() gives both)."""
    bench = load_benchmark()

    def run(e1, e2, cd):
        objects = {"1": {"E": e1, "E_rel_error": None}, "2": {"E": e2, "E_rel_error": None}}
        return {"objects": objects, "future_cd_mm2": cd}

    direct, imported, again = run(1e4, 2e4, 100.0), run(1.2e4, 2e4, 150.0), run(1e4, 3e4, 50.0)
    result = {
        "direct": direct,
        "imported": imported,
        "comparison": bench.compare(direct, imported),
        "spread": {"reconstructor_seed": 3, "direct": again},
    }
    result["spread"]["comparison"] = bench.compare(direct, again)
    assert result["comparison"]["E_rel_to_direct"] == pytest.approx({"1": 0.2, "2": 0.0})
    lines = bench.table(result).splitlines()
    assert lines[-2] == "future CD (mm^2): direct 100, imported 150 (+50.0%)"
    assert lines[-1] == (
        "direct again (reconstructor seed 3): E rel. diff 1 0, 2 0.5; future CD 50 (-50.0%)"
    )


def test_parts_merge_into_the_comparison_and_a_missing_part_is_named(tmp_path):
    """The round trip in parts (one GPU call each, several at once): merge() assembles the
    finished parts and names the part that has not finished."""
    bench = load_benchmark()

    def run(e1, cd):
        return {"objects": {"1": {"E": e1, "E_rel_error": None}}, "future_cd_mm2": cd}

    parts = tmp_path / "parts"
    parts.mkdir()
    (parts / "direct.json").write_text(json.dumps(run(1e4, 100.0)))
    (parts / "capture.json").write_text(json.dumps({"rig": bench.Rig().record()}))
    with pytest.raises(FileNotFoundError, match="part 'imported' has not finished"):
        bench.merge(tmp_path, bench.QUICK_RECIPE, [])
    (parts / "imported.json").write_text(json.dumps(run(1.5e4, 130.0)))
    result = bench.merge(tmp_path, bench.QUICK_RECIPE, [])
    assert result["spread"] is None and result["rig"]["background_plate"] is True
    assert result["comparison"]["E_rel_to_direct"] == pytest.approx({"1": 0.5})
    assert result["comparison"]["future_cd_rel_to_direct"] == pytest.approx(0.3)
    (parts / "reseeded.json").write_text(
        json.dumps({"reconstructor_seed": 1, "direct": run(2e4, 50.0)})
    )
    spread = bench.merge(tmp_path, bench.QUICK_RECIPE, [])["spread"]
    assert spread["comparison"]["E_rel_to_direct"] == pytest.approx({"1": 1.0})
    with pytest.raises(ValueError, match="part 'everything'"):
        bench.run_part("everything", tmp_path, bench.QUICK_RECIPE, [])
    with pytest.raises(ValueError, match="--spread-seed"):
        bench.run_part("reseeded", tmp_path, bench.QUICK_RECIPE, [])


def test_the_import_leaves_the_late_camera_out_or_trims_every_camera():
    """--late-cameras: under trim the import's frame 0 is the scene's frame ``late`` and the
    observed window one shorter by as much; under drop the late camera is left out and the
    frames are the scene's own."""
    bench = load_benchmark()
    assert bench.frame_shift(2, "trim") == 2 and bench.frame_shift(2, "drop") == 0
    assert bench.frame_shift(2, "keep") == 0
    common = dict(materials="elastic,sand", ground_height=0.0, late=2, segmenter=[])
    for policy, observed in (("trim", 13), ("drop", 15)):
        argv = bench.import_argv(
            Path("cap"), Path("imp"), observed=observed, late_cameras=policy, **common
        )
        assert argv[argv.index("--late-cameras") + 1] == policy
        assert argv[argv.index("--observed") + 1] == str(observed)
        assert argv[argv.index("--offsets") + 1] == f"{bench.LATE[0]}:-2"
    assert bench.Rig(late_cameras="drop").record()["late_cameras"] == "drop"


def test_the_paper_size_import_table_is_the_one_its_data_holds():
    """docs/RESULTS.md's paper-size table (rig and back) carries, for the direct run and the
    keep and drop imports, the future Chamfer, its ratio to the direct run, the E of each
    object and the contact the identification chose, as kept under benchmarks/data."""
    root = Path(__file__).resolve().parents[1]
    data = root / "benchmarks" / "data" / "capture_roundtrip_paper"
    results = (root / "docs" / "RESULTS.md").read_text()

    def row_of(start: str) -> str:
        return next(line for line in results.splitlines() if line.startswith(start))

    for name in ("keep", "drop"):
        record = json.loads((data / f"roundtrip_{name}.json").read_text())
        imported, direct = record["imported"], record["direct"]
        ratio = imported["future_cd_mm2"] / direct["future_cd_mm2"]
        row = row_of(f"| {name}:")
        assert f"| {imported['future_cd_mm2']:,.0f} ({ratio:.2g}x) /" in row
        for obj in imported["objects"].values():
            assert f"{obj['E']:,.0f} Pa ({100 * obj['E_rel_error']:.0f}" in row
        metrics = json.loads((data / f"imported_{name}_metrics.json").read_text())
        assert f"| {metrics['params']['contact']['mode']} (" in row
        direct_row = row_of("| direct |")
        assert f"| {direct['future_cd_mm2']:,.0f} (1.0x) /" in direct_row
        for obj in direct["objects"].values():
            assert f"{obj['E']:,.0f} Pa ({100 * obj['E_rel_error']:.0f})" in direct_row


def test_the_late_camera_policy_table_is_the_one_its_data_holds():
    """docs/RESULTS.md's table of the three --late-cameras policies carries, per seed, the
    future Chamfer of the direct runs and of each policy's import as kept in
    benchmarks/data/capture_roundtrip_quick/late_cameras.json, and the policy the development
    seeds choose is the import's default."""
    from mosiv_framework.capture.importer import ImportSettings

    root = Path(__file__).resolve().parents[1]
    data = json.loads(
        (root / "benchmarks" / "data" / "capture_roundtrip_quick" / "late_cameras.json").read_text()
    )
    text = (root / "docs" / "RESULTS.md").read_text()
    for seed, row in data["seeds"].items():
        cells = [row["direct"], row["reseeded"]] + [
            row[p]["future_cd_mm2"] for p in ("trim", "drop", "keep")
        ]
        kind = "development" if int(seed) in data["dev"] else "test"
        line = f"| {seed} ({kind}) | " + " | ".join(f"{c:,.0f}" for c in cells) + " |"
        assert line in text, line
    means = data["dev_mean_future_cd_mm2"]
    chosen = min(means, key=means.get)
    assert ImportSettings(out=Path("o"), frames_dir=Path("f")).late_cameras == chosen
