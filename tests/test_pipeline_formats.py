"""Format versions of run files: written by the writers, checked by the readers."""

from __future__ import annotations

import json

import pytest

from mosiv_framework.pipeline import formats
from mosiv_framework.pipeline.rundir import RunDir


def test_a_file_without_the_field_or_of_a_known_format_is_read(tmp_path):
    rd = RunDir(tmp_path)
    rd.save_json("identified.json", {"objects": {}})  # the first layout: no field
    assert rd.load_json("identified.json") == {"objects": {}}
    rd.save_json("identified.json", formats.stamped(formats.IDENTIFIED, {"objects": {}}))
    assert rd.load_json("identified.json") == {"format": formats.IDENTIFIED, "objects": {}}


@pytest.mark.parametrize(
    "name, value, supported",
    [
        ("metrics.json", "mosiv-metrics/2", formats.METRICS),
        ("identified.json", "mosiv-metrics/1", formats.IDENTIFIED),  # another file's format
        ("stages/lift.json", "mosiv-stage/7", formats.STAGE),
    ],
)
def test_an_unknown_format_is_refused_with_what_is_supported(tmp_path, name, value, supported):
    rd = RunDir(tmp_path)
    rd.save_json(name, {"format": value})
    with pytest.raises(formats.FormatError) as err:
        rd.load_json(name)
    message = str(err.value)
    assert str(rd.path(name)) in message
    assert f"field 'format' is {value!r}" in message
    assert repr(supported) in message


def test_an_unknown_stage_marker_format_is_refused_not_taken_for_a_missing_stage(tmp_path):
    rd = RunDir(tmp_path)
    rd.mark_done("lift", "abc", particles=3)
    assert json.loads(rd.path("stages/lift.json").read_text())["format"] == formats.STAGE
    assert rd.stage_done("lift", "abc") and not rd.stage_done("lift", "other")
    rd.save_json("stages/lift.json", {"format": "mosiv-stage/2", "config": "abc"})
    with pytest.raises(formats.FormatError, match="stages/lift.json"):
        rd.stage_done("lift", "abc")


def test_a_file_outside_the_run_layout_is_not_checked(tmp_path):
    rd = RunDir(tmp_path)
    rd.save_json("diagnosis/notes.json", {"format": "anything/3"})
    assert rd.load_json("diagnosis/notes.json") == {"format": "anything/3"}


def test_history_reads_both_layouts_and_refuses_an_unknown_one(tmp_path):
    records = [{"phase": "velocity", "iteration": 0}]
    path = tmp_path / "history.json"
    path.write_text(json.dumps(records))
    assert formats.read_history(path) == records
    path.write_text(json.dumps(formats.stamped_entries(formats.HISTORY, records)))
    assert formats.read_history(path) == records
    path.write_text(json.dumps({"format": "mosiv-history/2", "entries": records}))
    with pytest.raises(formats.FormatError, match="'mosiv-history/2'"):
        formats.read_history(path)
    path.write_text(json.dumps({"format": formats.HISTORY, "records": records}))
    with pytest.raises(formats.FormatError, match="entries"):
        formats.read_history(path)
