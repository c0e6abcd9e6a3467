"""benchmarks/genesis_contact_geometry.py: onset, closest approach and last distance of the
bodies, in the recording and in the rollout of its truth.

The distances are checked on point sets whose gaps are known exactly; the onset on a body
that flies free and one knocked off its parabola. On a scene that mosiv-synth made with
warp-mpm (multi-field contact, own laws, grid 24, 30 substeps) the rollout of the truth at
those settings is the recording itself, so its numbers must equal the recording's; another
contact mode gives other numbers. The rerun, the table and the RESULTS section are tested on
the same rows.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from mosiv_framework.pipeline.run import generate_scene
from mosiv_framework.recipes import load_recipe
from mosiv_framework.testing.pytest_plugin import require_simulator
from mosiv_framework.testing.scripts import load_script
from mosiv_framework.types import World

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "benchmarks" / "genesis_contact_geometry.py"
RECIPE = ROOT / "recipes" / "diagnose_small.yaml"


@pytest.fixture(scope="module")
def bench():
    return load_script(SCRIPT)


def _cube(centre, n=4, size=0.1):
    axis = torch.linspace(-size / 2, size / 2, n)
    grid = torch.stack(torch.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3)
    return grid + torch.tensor(centre)


def test_pair_distances_are_the_gaps_between_the_nearest_points(bench):
    """Two cubes of side 0.1 m whose centres lie 0.3 m apart along x: 0.2 m between their
    faces; a third cube 0.15 m above the first: 0.05 m, the smallest pair."""
    a, b = _cube([0.0, 0.0, 0.0]), _cube([0.3, 0.0, 0.0])
    two = {1: torch.stack([a, a]), 2: torch.stack([b, b + torch.tensor([0.1, 0.0, 0.0])])}
    torch.testing.assert_close(
        torch.from_numpy(bench.pair_distances(two)), torch.tensor([0.2, 0.3], dtype=torch.float64)
    )
    three = {**two, 3: torch.stack([a + torch.tensor([0.0, 0.0, 0.15])] * 2)}
    torch.testing.assert_close(
        torch.from_numpy(bench.pair_distances(three)),
        torch.tensor([0.05, 0.05], dtype=torch.float64),
    )


def test_onset_is_the_first_frame_a_centroid_leaves_its_parabola(bench):
    """Two bodies in free fall (g = -9.8 z, 10 fps): none departs (no onset); the
    second stopped dead from frame 5 on: onset 5."""
    world = World((-1.0, -1.0, 0.0), (2.0, 1.0, 2.0), fps=10.0)
    t = torch.arange(10, dtype=torch.float32)[:, None, None] / world.fps
    fall = torch.tensor([0.5, 0.0, 1.0]) * t + 0.5 * torch.tensor(world.gravity) * t**2
    bodies = {1: _cube([0.0, 0.0, 1.0]) + fall, 2: _cube([1.0, 0.0, 1.0]) + fall}
    assert bench.onset(bodies, world) is None
    stopped = bodies[2].clone()
    stopped[5:] = stopped[4]
    assert bench.onset({1: bodies[1], 2: stopped}, world) == 5


@pytest.fixture(scope="module")
def measured(bench, tmp_path_factory):
    require_simulator("warp-mpm")
    root = tmp_path_factory.mktemp("geometry")
    overrides = [
        f"scene.path={root / 'suite' / 'E-E'}",
        "scene.source.n_frames=9",
        "scene.source.observed_frames=6",
        "scene.source.collision_frame=4",
        "scene.generate=if-missing",
    ]
    generate_scene(load_recipe(RECIPE, overrides).scene)
    argv = ["--scenes", str(root / "suite"), "--out", str(root / "out"), "--recipe", str(RECIPE)]
    argv += ["--contacts", "multi_field", "single_field", "--grids", "24", "--substeps", "30"]
    argv += ["--device", "cpu"]
    assert bench.main(argv) == 0
    rows = json.loads((root / "out" / "contact_geometry.json").read_text())["rows"]
    return root, argv, rows


def test_the_generators_own_rollout_measures_as_its_recording(measured):
    _, _, rows = measured
    by_config = {r["config"]: r for r in rows}
    assert sorted(by_config) == ["multi_field/g24/s30", "single_field/g24/s30"]
    own, other = by_config["multi_field/g24/s30"], by_config["single_field/g24/s30"]
    truth = own["genesis"]
    assert truth["onset"] < 9 and truth["window"] == [truth["onset"], min(truth["onset"] + 3, 8)]
    for name in ("closest_mm", "last_mm"):
        assert own["rollout"][name] == pytest.approx(truth[name], abs=1e-3), name
    assert own["rollout"]["onset"] == truth["onset"]
    moved = abs(other["rollout"]["last_mm"] - truth["last_mm"])
    moved += abs(other["rollout"]["closest_mm"] - truth["closest_mm"])
    assert moved > 0.1, other


def test_a_rerun_measures_nothing_again_and_writes_the_section(measured, bench):
    root, argv, rows = measured
    notes = root / "RESULTS.md"
    notes.write_text("# Results\n\n## From video\n\nkept\n")
    data = "the tiny own-synth scene"
    assert bench.main([*argv, "--write-results", str(notes), "--data", data]) == 0
    assert json.loads((root / "out" / "contact_geometry.json").read_text())["rows"] == rows
    text = notes.read_text()
    assert "## Contact geometry on Genesis scenes" in text and "## From video" in text
    assert f"- Data: {data}." in text
    assert "| multi_field/g24/s30 | 1 | 0 | 0 | 1 | 1 |" in text


def test_pairs_need_as_many_grids_as_substep_counts(bench, tmp_path):
    argv = ["--scenes", str(tmp_path), "--out", str(tmp_path / "o"), "--grids", "48", "96"]
    with pytest.raises(SystemExit, match="2 grids and 1 substep counts"):
        bench.main([*argv, "--substeps", "400", "--pairs"])


def test_a_rollout_without_onset_or_a_zero_distance_is_left_out_of_the_medians(bench):
    """Summary medians skip a row whose rollout shows no contact (onset None) and a ratio to a
    Genesis distance of 0; the table shows "-" for the missing onset."""
    truth = {"onset": 7, "closest_mm": 10.0, "last_mm": 100.0, "window": [7, 10]}
    rows = [
        {"scene": "A", "config": "c", "genesis": truth,
         "rollout": {"onset": 9, "closest_mm": 20.0, "last_mm": 300.0}},
        {"scene": "B", "config": "c", "genesis": {**truth, "last_mm": 0.0},
         "rollout": {"onset": None, "closest_mm": 5.0, "last_mm": 50.0}},
        {"scene": "C", "config": "c", "genesis": truth, "diverged": "object 1, frame 3"},
    ]  # fmt: skip
    (s,) = bench.summary(rows)
    assert (s["scenes"], s["diverged"], s["onset_shift"]) == (3, 1, 2)
    assert s["closest_ratio"] == pytest.approx(1.25) and s["last_ratio"] == pytest.approx(3.0)
    table = bench.markdown(rows)
    assert "| B | 7 / 10 / 0 | - / 5 / 50 |" in table and "| C | 7 / 10 / 100 | diverged |" in table


def test_pairs_take_each_grid_with_its_substep_count(bench):
    args = bench.parse_args(
        ["--scenes", "S", "--out", "O", "--contacts", "single_field", "--grids", "48", "96",
         "--substeps", "400", "600", "--pairs"]
    )  # fmt: skip
    assert [bench.config_key(c) for c in bench.configurations(args)] == [
        "single_field/g48/s400",
        "single_field/g96/s600",
    ]
    args.pairs = False
    assert len(bench.configurations(args)) == 4
