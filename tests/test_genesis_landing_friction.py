"""benchmarks/genesis_landing_friction.py: the landings of each scene's observed frames, the
estimate against the truth, and the RESULTS section.

Run on the committed Genesis fixture scene (two bodies that meet in the air and do not reach
the table within its frames: nothing to read) and on rows whose readings are known.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from mosiv_framework.testing.scripts import load_script

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "benchmarks" / "genesis_landing_friction.py"
FIXTURE = ROOT / "plugins" / "mosiv-genesis" / "tests" / "data" / "contact_scene"


@pytest.fixture(scope="module")
def bench():
    return load_script(SCRIPT)


def test_a_scene_without_a_landing_reads_nothing_and_the_section_says_so(bench, tmp_path):
    shutil.copytree(FIXTURE, tmp_path / "suite" / "P-P")
    notes = tmp_path / "RESULTS.md"
    notes.write_text("# Results\n\n## From video\n\nkept\n")
    argv = ["--scenes", str(tmp_path / "suite"), "--out", str(tmp_path / "out")]
    argv += ["--clearances", "1", "2", "--noise", "centroid:2", "centroid:2", "--seeds", "2"]
    assert bench.main([*argv, "--write-results", str(notes), "--data", "one fixture"]) == 0
    rows = json.loads((tmp_path / "out" / "landing_friction.json").read_text())["rows"]
    assert len(rows) == 1 and rows[0]["estimate"] is None and rows[0]["landings"] == []
    assert rows[0]["by_clearance"] == {"1": None, "2": None}
    # a level given twice is read once, two seeds each
    assert [(n["kind"], n["mm"], n["seed"]) for n in rows[0]["noisy"]] == [
        ("centroid", 2.0, 0), ("centroid", 2.0, 1)
    ]  # fmt: skip
    assert rows[0]["truth"] == pytest.approx(0.1)
    text = notes.read_text()
    assert "## Ground friction from the landings on Genesis scenes" in text
    assert "## From video" in text and "- Data: one fixture." in text
    assert "| suite | P-P | plasticine, plasticine | - | - | 0.1 |" in text
    assert "suite: no landing read on any of the 1 scenes." in text
    assert "| suite | centroid 2 | 0 of 2 | - |" in text
    assert "2 noisy copies of each scene's points per level" in text


def test_the_summary_compares_each_estimate_with_its_truth(bench):
    def row(scene, estimate, ratios):
        landings = [{"object": k + 1, "frame": 9, "ratio": r} for k, r in enumerate(ratios)]
        return {"suite": "dev", "scene": scene, "materials": ["elastic"], "estimate": estimate,
                "truth": 0.1, "landings": landings}  # fmt: skip

    rows = [row("A", 0.05, [0.05, 0.02]), row("B", 0.09, [0.09]), row("C", None, [])]
    for r, closer in zip(rows, (0.05, 0.3, 0.12), strict=True):
        r["by_clearance"] = {"1": closer, "2": None}
    text = bench.markdown(rows)
    assert "| dev | 1 | 3 of 3 | median 1.20, range 0.50-3.00 |" in text
    assert "| dev | 2 | 0 of 3 | - |" in text
    assert "| dev | A | elastic | 1: 9, 0.050; 2: 9, 0.020 | 0.050 | 0.1 |" in text
    assert "dev: read on 2 of 3 scenes, estimate / truth median 0.70, range 0.50-0.90." in text


def test_centroid_noise_moves_a_body_rigidly_and_point_noise_point_by_point(bench):
    import torch

    cloud = torch.rand(6, 50, 3, dtype=torch.float64)
    points = {1: cloud, 2: cloud + 1.0}
    rigid = bench.perturbed(points, "centroid", 2.0, seed=0)
    shift = rigid[1] - cloud
    assert torch.allclose(shift, shift[:, :1].expand_as(shift))  # one offset per frame
    assert shift[:, 0].std() > 0  # differing between frames
    # 2 mm per coordinate: the offsets' spread over 6 frames x 3 coordinates is about 2e-3 m
    assert 0.5e-3 < float(shift[:, 0].std()) < 4e-3
    assert not torch.allclose(rigid[2] - points[2], shift)  # each body its own jitter
    loose = bench.perturbed(points, "points", 2.0, seed=0)
    offsets = loose[1] - cloud
    assert float((offsets - offsets[:, :1]).abs().max()) > 1e-4  # points move apart
    assert 1.5e-3 < float(offsets.std()) < 2.5e-3  # 2 mm over 900 draws
    # the same seed gives the same copy; no noise gives the points back
    assert torch.equal(bench.perturbed(points, "points", 2.0, seed=0)[1], loose[1])
    assert torch.equal(bench.perturbed(points, "centroid", 0.0, seed=3)[2], points[2])
    with pytest.raises(ValueError, match="points, centroid"):
        bench.perturbed(points, "wind", 1.0, seed=0)


def test_each_scene_draws_its_own_noise(bench, tmp_path):
    first = bench.scene_seed(tmp_path / "dev" / "E-P", 0)
    assert first == bench.scene_seed(tmp_path / "dev" / "E-P", 0)  # the same on every run
    assert first != bench.scene_seed(tmp_path / "test" / "E-P", 0)
    assert first != bench.scene_seed(tmp_path / "dev" / "E-S", 0)
    assert first != bench.scene_seed(tmp_path / "dev" / "E-P", 1)


def test_a_seed_count_below_one_is_refused(bench):
    import argparse

    assert bench.positive_count("3") == 3
    for text in ("0", "-2", "two"):
        with pytest.raises(argparse.ArgumentTypeError, match="whole number >= 1"):
            bench.positive_count(text)


@pytest.mark.parametrize(
    "text", ["wind:2", "centroid:x", "centroid:-1", "centroid", "centroid:nan", "points:inf"]
)
def test_a_bad_noise_level_names_what_is_valid(bench, text):
    import argparse

    with pytest.raises(argparse.ArgumentTypeError, match="KIND one of points, centroid"):
        bench.parse_noise(text)
    assert bench.parse_noise("points:2.5") == ("points", 2.5)


def test_the_noise_table_counts_readings_per_level_against_the_clean_ones(bench):
    def row(scene, estimate, noisy):
        return {"suite": "dev", "scene": scene, "materials": ["elastic"], "estimate": estimate,
                "truth": 0.1, "landings": [], "noisy": noisy}  # fmt: skip

    def reading(kind, mm, seed, estimate):
        return {"kind": kind, "mm": mm, "seed": seed, "estimate": estimate}

    rows = [
        row("A", 0.05, [reading("centroid", 2.0, 0, 0.2), reading("centroid", 2.0, 1, None)]),
        row("B", None, [reading("centroid", 2.0, 0, 0.1), reading("centroid", 2.0, 1, 0.05)]),
    ]
    text = bench.markdown(rows)
    assert "| dev | none (one reading a scene) | 1 of 2 | median 0.50, range 0.50-0.50 |" in text
    # three of four readings found a landing: 2.0, 1.0 and 0.5 times the truth
    assert "| dev | centroid 2 | 3 of 4 | median 1.00, range 0.50-2.00 |" in text
    assert "noise" not in bench.markdown([{**r, "noisy": []} for r in rows])
