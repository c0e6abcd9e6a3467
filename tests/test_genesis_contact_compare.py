"""benchmarks/genesis_contact_compare.py: pairing two runs' rows and counting which mode wins."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from mosiv_framework.testing.scripts import load_script

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "genesis_contact_compare.py"


@pytest.fixture(scope="module")
def compare_module():
    return load_script(SCRIPT)


def _row(scene: str, e_errors: list[float], angle: float, observed: float, future: float) -> dict:
    objects = {
        str(i + 1): {"family": "elastic", "params": {"E": {"error": e}}}
        for i, e in enumerate(e_errors)
    }
    objects[str(len(e_errors) + 1)] = {
        "family": "sand",
        "params": {"E": {"error": 50.0}, "friction_angle": {"error": angle}},
    }
    return {
        "scene": scene,
        "objects": objects,
        "observed_cd_mm2": observed,
        "future_cd_mm2": future,
        "device": "test",
        "code": "abc1234",
    }


def _write(folder: Path, rows: list[dict], parts: bool) -> Path:
    for row in rows:
        path = (
            folder
            / ("parts" if parts else "")
            / (f"{row['scene']}.json" if parts else f"scene_{row['scene']}.json")
        )
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(row))
    return folder


def test_only_shared_scenes_are_compared_and_wins_are_counted(tmp_path, compare_module):
    first = _write(
        tmp_path / "a",
        [_row("E-S", [40.0], 10.0, 100.0, 900.0), _row("S-S", [1.0], 1.0, 1.0, 1.0)],
        parts=False,
    )
    second = _write(tmp_path / "b", [_row("E-S", [20.0], 12.0, 50.0, 1200.0)], parts=True)
    runs = compare_module.read_rows(first), compare_module.read_rows(second)
    records = compare_module.compare(*runs)
    assert {r["scene"] for r in records} == {"E-S"}
    assert [r["E"] for r in records] == [(40.0, 20.0), (50.0, 50.0)]
    assert records[1]["family_param"] == (10.0, 12.0)
    text = compare_module.tallies(records, ("multi", "single"))
    assert "observed CD on 1 of 1 scenes" in text
    assert "future CD on 0 of 1 scenes" in text
    assert "E error on 1 of 2 objects" in text  # a tie is not a win
    assert "family-parameter error on 0 of 1 objects" in text


def test_section_names_the_scenes_left_out_and_replaces_itself(tmp_path, compare_module):
    first = _write(tmp_path / "a", [_row("E-S", [40.0], 10.0, 100.0, 900.0)], parts=True)
    second = _write(
        tmp_path / "b",
        [_row("E-S", [20.0], 12.0, 50.0, 1200.0), _row("P-P", [5.0], 2.0, 3.0, 4.0)],
        parts=True,
    )
    results = tmp_path / "RESULTS.md"
    results.write_text("# Results\n\n## From video\n\ntext\n")
    for _ in range(2):
        assert compare_module.main([str(first), str(second), "--write-results", str(results)]) == 0
    text = results.read_text()
    assert text.count(f"## {compare_module.SECTION}") == 1
    assert "not compared: P-P" in text
    assert text.index(compare_module.SECTION) < text.index("## From video")


def test_a_folder_without_rows_is_refused(tmp_path, compare_module):
    (tmp_path / "empty").mkdir()
    with pytest.raises(SystemExit, match="no parts/SCENE.json"):
        compare_module.read_rows(tmp_path / "empty")


def test_a_section_keeps_its_hand_written_reading_when_regenerated(tmp_path, compare_module):
    first = _write(tmp_path / "a", [_row("E-S", [40.0], 10.0, 100.0, 900.0)], parts=True)
    second = _write(tmp_path / "b", [_row("E-S", [20.0], 12.0, 50.0, 1200.0)], parts=True)
    results = tmp_path / "RESULTS.md"
    results.write_text("# Results\n\n## From video\n\ntext\n")
    compare_module.main([str(first), str(second), "--write-results", str(results)])
    marker = compare_module.KEEP_MARKER
    text = results.read_text().replace(
        "\n## From video", f"\n{marker}\n**Reading.** kept words.\n\n## From video"
    )
    results.write_text(text)
    second_rows = [_row("E-S", [5.0], 12.0, 50.0, 1200.0)]
    _write(tmp_path / "b", second_rows, parts=True)
    compare_module.main([str(first), str(second), "--write-results", str(results)])
    text = results.read_text()
    assert "40 / 5 |" in text  # the numbers are the new ones
    assert text.count(marker) == 1 and "**Reading.** kept words." in text
    assert text.index("kept words") < text.index("## From video")


def test_the_committed_held_out_tail_table_is_the_one_its_data_makes(compare_module):
    """docs/RESULTS.md's held-out-tail table and tallies come from the rows kept under
    benchmarks/data, not from hand edits: regenerating them from those rows gives the same text."""
    root = SCRIPT.parents[1]
    data = root / "benchmarks" / "data" / "genesis_identify_holdout"
    runs = (
        compare_module.read_rows(data / "all_frames"),
        compare_module.read_rows(data / "last_3_held_out"),
    )
    assert len(runs[0]) == len(runs[1]) == 13
    records = compare_module.compare(*runs)
    labels = ("all observed frames", "last 3 held out")
    results = (root / "docs" / "RESULTS.md").read_text()
    section = results[results.index("## Held-out tail on Genesis scenes") :]
    section = section[: section.index(compare_module.KEEP_MARKER)]
    assert compare_module.markdown(records, labels) in section
    assert " ".join(compare_module.tallies(records, labels).split()) in " ".join(section.split())


def test_the_data_line_names_the_scenes_given(tmp_path, compare_module):
    first = _write(tmp_path / "a", [_row("E-S", [40.0], 10.0, 100.0, 900.0)], parts=True)
    second = _write(tmp_path / "b", [_row("E-S", [20.0], 12.0, 50.0, 1200.0)], parts=True)
    results = tmp_path / "RESULTS.md"
    results.write_text("# Results\n")
    argv = [str(first), str(second), "--write-results", str(results)]
    compare_module.main(argv + ["--data", "4 development scenes, seeds 7000-7007"])
    assert "- Data: 4 development scenes, seeds 7000-7007." in results.read_text()


def test_the_section_names_the_days_the_runs_ended(tmp_path, compare_module):
    first = _write(
        tmp_path / "a", [{**_row("E-S", [40.0], 10.0, 100.0, 900.0), "date": "2026-11-29"}], True
    )
    second = _write(
        tmp_path / "b", [{**_row("E-S", [20.0], 12.0, 50.0, 1200.0), "date": "2026-11-30"}], True
    )
    results = tmp_path / "RESULTS.md"
    results.write_text("# Results\n")
    assert compare_module.main([str(first), str(second), "--write-results", str(results)]) == 0
    assert "Date 2026-11-29 to 2026-11-30." in results.read_text()
