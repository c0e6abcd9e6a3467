"""`mosiv bench sim --jsonl FILE`: every result lands in FILE as one JSON line the moment it is
measured, the same rows `--json` prints at the end; an existing FILE is refused, not
overwritten."""

from __future__ import annotations

import json

import pytest

from mosiv_framework.cli.main import main

TINY = ["--particles", "64", "--grid", "16", "--substeps", "2", "--frames", "1"]


def test_each_result_is_one_line_and_equals_the_printed_rows(tmp_path, capsys):
    pytest.importorskip("mosiv_warp_mpm")
    path = tmp_path / "rows.jsonl"
    sizes = ["--particles", "64", "--grid", "16", "8", "--substeps", "2", "--frames", "1"]
    argv = ["bench", "sim", "--backend", "warp-mpm", *sizes, "--no-backward"]
    assert main([*argv, "--json", "--jsonl", str(path)]) == 0
    printed = json.loads(capsys.readouterr().out)
    lines = [json.loads(line) for line in path.read_text().splitlines()]
    assert len(lines) == 2 == len(printed)  # grids 16 and 8
    assert [row["grid"] for row in lines] == [16, 8]
    for line, row in zip(lines, printed):
        assert line["backend"] == row["backend"] and line["particles"] == row["particles"]
        assert line["forward_particle_substeps_per_s"] > 0


def test_batched_results_are_logged_too(tmp_path, capsys):
    pytest.importorskip("mosiv_warp_mpm")
    path = tmp_path / "batch.jsonl"
    argv = ["bench", "sim", "--backend", "warp-mpm", *TINY, "--batch", "2"]
    assert main([*argv, "--jsonl", str(path)]) == 0
    (row,) = [json.loads(line) for line in path.read_text().splitlines()]
    assert row["batch"] == 2 and row["gain"] > 0


def test_an_existing_file_is_refused_and_kept(tmp_path, capsys):
    path = tmp_path / "mine.jsonl"
    path.write_text("a user's notes\n")
    assert main(["bench", "sim", *TINY, "--jsonl", str(path)]) == 2
    assert "exists already" in capsys.readouterr().err
    assert path.read_text() == "a user's notes\n"


def test_a_missing_folder_is_named(tmp_path, capsys):
    path = tmp_path / "nowhere" / "rows.jsonl"
    assert main(["bench", "sim", *TINY, "--jsonl", str(path)]) == 2
    assert "does not exist" in capsys.readouterr().err
