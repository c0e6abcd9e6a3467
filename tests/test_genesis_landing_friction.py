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
    argv += ["--clearances", "1", "2"]
    assert bench.main([*argv, "--write-results", str(notes), "--data", "one fixture"]) == 0
    rows = json.loads((tmp_path / "out" / "landing_friction.json").read_text())["rows"]
    assert len(rows) == 1 and rows[0]["estimate"] is None and rows[0]["landings"] == []
    assert rows[0]["by_clearance"] == {"1": None, "2": None}
    assert rows[0]["truth"] == pytest.approx(0.1)
    text = notes.read_text()
    assert "## Ground friction from the landings on Genesis scenes" in text
    assert "## From video" in text and "- Data: one fixture." in text
    assert "| suite | P-P | plasticine, plasticine | - | - | 0.1 |" in text
    assert "suite: no landing read on any of the 1 scenes." in text


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
