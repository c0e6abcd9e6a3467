"""benchmarks/taichi_profile.py on the CPU at a tiny size, in its own process (Taichi's kernel
profiler is chosen when its runtime starts): the timed rollouts, the forward substep's kernels
in the table, and the JSON file agree; bad sizes are refused."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "taichi_profile.py"


def test_profile_lists_the_forward_substep_kernels(tmp_path):
    pytest.importorskip("mosiv_taichi_mpm")
    out_path = tmp_path / "timings.json"
    argv = ["--particles", "300", "--grid", "16", "--substeps", "3", "--frames", "2"]
    run = subprocess.run(
        [sys.executable, str(SCRIPT), *argv, "--repeats", "2", "--json", str(out_path)],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert run.returncode == 0, run.stderr[-2000:]
    out = json.loads(out_path.read_text())

    assert len(out["wall_s"]) == 2 and all(w > 0 for w in out["wall_s"])
    work = out["particles"] * 3 * 2
    assert out["rate_last"] == pytest.approx(work / out["wall_s"][-1])
    substep = {name: v for name, v in out["kernels_ms"].items() if name.startswith("substep")}
    assert substep, "the one-call forward substep was not profiled"
    assert all(count == 3 * 2 for count, _ in substep.values())  # one launch per substep
    assert 0 < out["kernel_s_last"] <= out["wall_s"][-1]
    assert "particle-substeps/s" in run.stdout


def test_profile_refuses_a_count_below_one():
    pytest.importorskip("mosiv_taichi_mpm")
    run = subprocess.run(
        [sys.executable, str(SCRIPT), "--repeats", "0"], capture_output=True, text=True, timeout=300
    )
    assert run.returncode == 2 and "--repeats must be at least 1" in run.stderr
