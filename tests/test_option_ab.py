"""benchmarks/option_ab.py: both values of an option are timed on the same workload, each side
on its own simulator made once, and the ratio is B's median over A's."""

from __future__ import annotations

import importlib
import json
import statistics
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture
def option_ab(monkeypatch):
    monkeypatch.syspath_prepend(str(ROOT / "benchmarks"))
    return importlib.import_module("option_ab")


def test_both_sides_are_timed_and_compared(option_ab, tmp_path, capsys):
    out = tmp_path / "ab.json"
    argv = ["--backend", "warp-mpm", "--option", "grid_window", "--values", "whole",
            "particles", "--particles", "300", "--grid", "16", "--substeps", "4", "--frames",
            "1", "--repeats", "2", "--json", str(out)]  # fmt: skip
    assert option_ab.main(argv) == 0
    saved = json.loads(out.read_text())
    (row,) = saved["rows"]
    whole, window = row["timings"]["whole"], row["timings"]["particles"]
    assert len(whole) == len(window) == 2
    # the same workload on both sides: the same particles, and the same motion (warp-mpm's
    # grid window changes which nodes are visited, not the result)
    assert whole[0]["particles"] == window[0]["particles"] == row["particles"]
    assert whole[0]["final_centroid"] == pytest.approx(window[0]["final_centroid"], abs=1e-6)
    fwd = row["forward_particle_substeps_per_s"]
    rates = {side: [t["forward_particle_substeps_per_s"] for t in timings]
             for side, timings in (("A", whole), ("B", window))}  # fmt: skip
    assert fwd["A"] == pytest.approx(statistics.median(rates["A"]))
    assert fwd["B"] == pytest.approx(statistics.median(rates["B"]))
    assert fwd["B_over_A"] == pytest.approx(fwd["B"] / fwd["A"])
    assert row["forward_backward_particle_substeps_per_s"]["A"] > 0
    table = capsys.readouterr().out
    assert "| fwd whole | fwd particles | fwd particles / whole |" in table
