"""benchmarks/free_flight.py on the committed tiny Genesis scene: with the gap of a fine grid
alone free flight runs one frame past the collision Genesis recorded, with the centroids it
stops there, and the ballistic initial velocity comes closer to the truth."""

from __future__ import annotations

import json
from pathlib import Path

from mosiv_framework.testing.scripts import load_script

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "benchmarks" / "free_flight.py"
TINY = ROOT / "plugins" / "mosiv-genesis" / "tests" / "data" / "tiny_scene"


def _bench():
    return load_script(SCRIPT)


def test_the_centroids_end_free_flight_at_the_recorded_collision(tmp_path):
    bench = _bench()
    scenes = tmp_path / "scenes"
    scenes.mkdir()
    (scenes / "E-E").symlink_to(TINY, target_is_directory=True)
    results = tmp_path / "RESULTS.md"
    results.write_text("# Results\n\n## From video\n\ntext\n")
    rows_file = tmp_path / "rows.json"
    argv = ["--scenes", str(scenes), "--grid", "96", "--json", str(rows_file)]
    assert bench.main(argv + ["--write-results", str(results)]) == 0
    (row,) = json.loads(rows_file.read_text())
    gap, centroids = row["rules"]["gap"], row["rules"]["centroids"]
    assert row["collision_frame"] == 3
    assert gap["frames"] == 4 and centroids["frames"] == 3
    for k in ("1", "2"):
        assert centroids["v0_error"][k] < 0.5 < gap["v0_error"][k]
    text = results.read_text()
    assert f"## {bench.SECTION}" in text and text.index(bench.SECTION) < text.index("## From video")
    assert "--scenes SCENES" in text  # no machine path in the command
    # grid 32's gap (two cells, 5 cm) already stops at the collision: both rules agree
    assert bench.main(["--scenes", str(scenes), "--grid", "32", "--json", str(rows_file)]) == 0
    (row,) = json.loads(rows_file.read_text())
    assert row["rules"]["gap"]["frames"] == row["rules"]["centroids"]["frames"] == 3
