"""benchmarks/import_memory.py: the import's peak memory against its frames, on a small rig
(the figures themselves are in docs/BENCHMARKS.md, "Import memory")."""

from __future__ import annotations

import importlib
import json
import sys
from pathlib import Path

import pytest

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"

pytest.importorskip("imageio_ffmpeg")


def _module():
    sys.path.insert(0, str(BENCHMARKS))
    try:
        return importlib.import_module("import_memory")
    finally:
        sys.path.remove(str(BENCHMARKS))


def test_measures_an_import_against_its_frames_and_keeps_a_users_folder(tmp_path, capsys):
    bench = _module()
    out = tmp_path / "out"
    assert bench.main(["--out", str(out), "--cameras", "3", "--frames", "12", "--size", "96"]) == 0
    row = json.loads((out / "import_memory.json").read_text())
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1]) == row
    assert (row["cameras"], row["frames"], row["size"]) == (3, 12, 96)
    # every camera's frames as uint8 RGB: 3 x 12 x 96 x 96 x 3 bytes
    assert row["frames_mb"] == round(3 * 12 * 96 * 96 * 3 / 2**20, 1)
    # both children ran the import and read their own peaks (the modules alone are 100s of MB)
    assert row["baseline_rss_mb"] > 100 and row["import_peak_rss_mb"] > 100
    assert row["import_own_mb"] == pytest.approx(
        row["import_peak_rss_mb"] - row["baseline_rss_mb"], abs=0.11
    )
    assert (out / "full" / "imported" / "scene.json").is_file()
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("keep")
    with pytest.raises(SystemExit, match="not empty"):
        bench.main(["--out", str(mine)])
    assert [p.name for p in mine.iterdir()] == ["notes.txt"]


def test_peak_memory_is_this_programs_own():
    """VmHWM starts afresh with each program; a fresh child reads well below a parent that
    holds a large array."""
    import subprocess

    import numpy as np

    bench = _module()
    held = np.ones(64 * 2**20, dtype=np.uint8)  # 64 MB touched here
    mine = bench.peak_rss_mb()
    code = "import sys; sys.path.insert(0, sys.argv[1]); import import_memory as m; "
    code += "print(m.peak_rss_mb())"
    child = float(
        subprocess.run(
            [sys.executable, "-c", code, str(BENCHMARKS)], capture_output=True, text=True
        ).stdout
    )
    assert held.sum() > 0 and child < mine
