"""benchmarks/identify_suite.py: rows of pairs run in parallel merge into one table, and one
tiny pair on CPU with the wide ranges and the centre start."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from mosiv_framework.testing.scripts import load_script

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "benchmarks" / "identify_suite.py"


def _suite():
    # the script imports its sibling modules when it runs, as from benchmarks/
    return load_script(SCRIPT, keep_path=True)


def test_parallel_parts_replace_their_scenes_rows_and_keep_the_others():
    suite = _suite()
    earlier = [
        {"scene": "scene-00-elastic-plasticine", "pair": "E-P", "code": "old"},
        {"scene": "scene-04-plasticine-sand", "pair": "P-S", "code": "old"},
        {"scene": "scene-09-sand-sand", "code": "format before pairs"},  # dropped: old format
    ]
    parts = [
        [{"scene": "scene-04-plasticine-sand", "pair": "P-S", "code": "new"}],
        [{"scene": "scene-02-elastic-sand", "pair": "E-S", "code": "new"}],
    ]
    rows = suite.merge_parts(earlier, parts)
    assert [r["scene"] for r in rows] == [
        "scene-00-elastic-plasticine",
        "scene-02-elastic-sand",
        "scene-04-plasticine-sand",
    ]
    assert [r["code"] for r in rows] == ["old", "new", "new"]


def test_a_pair_keeps_its_scene_seed_whichever_pairs_are_selected():
    """Parallel parts run one pair each; the pair's scene must be the one the serial suite
    would generate, so its index (and seed) comes from the paper's order, not the selection."""
    suite = _suite()
    assert suite.select_pairs(pairs="P-S", scenes=None) == [(4, "P-S")]
    assert suite.select_pairs(pairs="S-S,E-P", scenes=None) == [(9, "S-S"), (0, "E-P")]


#: a tiny scene and identification (seconds on CPU): grid 16, 6 frames of which 4 observed
TINY = [
    "scene.source.resolution=24",
    "scene.source.n_cameras=2",
    "scene.source.n_frames=6",
    "scene.source.observed_frames=4",
    "scene.source.collision_frame=2",
    "scene.source.particle_spacing=0.02",
    "scene.source.simulator_options.grid=16",
    "simulator.grid=16",
    "lifter.voxel_size=0.02",
    "identify.velocity_iterations=1",
    "identify.param_iterations=1",
    "losses.chamfer.max_points=128",
    "evaluate.emd_samples=64",
    "evaluate.render_videos=false",
]


def test_wide_ranges_and_the_centre_start_in_one_command(tmp_path):
    """One pair with --ranges wide --start centre: the scene is drawn from the wide table into a
    folder of its own, identification starts at the centre of each law's bounds, and the table
    and RESULTS section say so; a rerun with the paper settings into that folder is refused."""
    from mosiv_synth.materials import WIDE_RANGES, range_bounds, range_table

    from mosiv_framework.laws import get_law
    from mosiv_framework.pipeline.params import GROUND_FRICTION, centre_value

    suite = _suite()
    out, results = tmp_path / "out", tmp_path / "RESULTS.md"
    results.write_text(
        "# Results\n\n## Identification (oracle reconstructor)\n\nhand-written\n\n"
        "## Identification on Genesis scenes\n\nkept\n"
    )
    recipe = ROOT / "recipes" / "quickstart.yaml"
    settings = ["--ranges", "wide", "--start", "centre", "--global-candidates", "2"]
    argv = ["--recipe", str(recipe), "--pairs", "E-P", "--out", str(out), *settings]
    assert suite.main([*argv, "--write-results", str(results), *TINY]) == 0

    folder = out / "scene-00-elastic-plasticine-wide"  # never the paper-range scene's folder
    truth = json.loads((folder / "scene" / "gt" / "params.json").read_text())
    assert truth["ranges"] == "wide" and truth["range_table"] == range_table("wide")
    for obj in truth["objects"]:
        for name, value in obj["params"].items():
            lower, upper = range_bounds(WIDE_RANGES[obj["material"]][name])
            assert lower <= value <= upper, (obj["material"], name, value)

    # the start: the global stage's record of the start (candidate -1) holds every identified
    # parameter at the centre of its law's bounds, not at the law default
    run = folder / "gradient"
    history = json.loads((run / "identify" / "history.json").read_text())["entries"]
    (start,) = [h for h in history if h.get("phase") == "global" and h["candidate"] == -1]
    assert [h["phase"] for h in history].count("global") == 3  # the start and 2 candidates
    values = start["values"]
    assert values["ground_friction"] == pytest.approx(centre_value(GROUND_FRICTION), rel=1e-5)
    for key, obj in values["objects"].items():
        law = get_law(obj["family"])
        for name, value in obj["params"].items():
            if key == "1" and name == "rho":
                assert value == 1000.0  # the density gauge, not identified
                continue
            assert value == pytest.approx(centre_value(law.param(name)), rel=1e-5), name
        assert law.param("E").default != pytest.approx(obj["params"]["E"], rel=0.01)

    table = json.loads((out / "table.json").read_text())
    assert table["settings"] == {"ranges": "wide", "start": "centre", "global_candidates": 2}
    assert table["targets"]["E_pct"]["at_most"] == 15.0
    (row,) = table["rows"]
    assert row["ranges"] == "wide" and row["substeps"] == 40 and "error" not in row["gradient"]
    text = " ".join((out / "table.md").read_text().split())  # the prose is wrapped
    assert "wide ranges" in text and "centre of each law's bounds" in text
    assert "Targets, those of the paper-range suite" in text

    written = results.read_text()
    head = "## Identification on own-synth scenes, wide ranges, centre start"
    assert "hand-written" in written and written.index(head) < written.index(
        "## Identification on G"
    )
    assert "--ranges wide --start centre --global-candidates 2" in written
    assert str(tmp_path) not in written

    # the same folder with the paper ranges and the recipe's start: refused before any run
    with pytest.raises(SystemExit, match="wide ranges, start at the centre"):
        suite.main(["--recipe", str(recipe), "--pairs", "E-P", "--out", str(out), *TINY])
    # identification keeps the substeps a scene was made with where the recipe has fewer
    overrides = [f"scene.path={folder / 'scene'}", *TINY, "simulator.substeps=20"]
    assert suite.scene_substeps(recipe, overrides, ranges="wide") == ["simulator.substeps=40"]
    with pytest.raises(SystemExit, match="drawn from the 'wide' ranges"):
        suite.scene_substeps(recipe, overrides, ranges="paper")


def test_the_sweep_and_the_seed_are_settings_of_a_table_only_when_set():
    suite = _suite()
    recipe = ROOT / "recipes" / "quickstart.yaml"
    plain = suite.suite_settings(recipe, [])
    assert plain == suite.LEGACY_SETTINGS  # a table written before either existed still merges
    swept = suite.suite_settings(recipe, ["identify.global_polish=6"], seed=1000)
    assert swept == {**plain, "global_polish": 6, "seed": 1000}
    from identify_suite_table import _seed_words, describe_settings

    assert "a scan of 6 values along each parameter" in describe_settings(swept)
    assert "scan" not in describe_settings(plain)
    assert _seed_words(swept) == "1000 + the pair's index"
    assert _seed_words(plain) == "the pair's index"
