"""benchmarks/rollout_profile.py on the CPU at a tiny size: the timed rollout and backward give
the rate, the profiler's table names the rollout's autograd function, and the timings land in
the JSON file; bad sizes are refused."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import pytest

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "rollout_profile.py"


@pytest.fixture(scope="module")
def rollout_profile():
    pytest.importorskip("mosiv_warp_mpm")
    spec = importlib.util.spec_from_file_location("rollout_profile", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_profile_times_a_rollout_and_its_backward(rollout_profile, tmp_path, capsys):
    out_path = tmp_path / "timings.json"
    argv = ["--particles", "300", "--grid", "16", "--substeps", "3", "--frames", "2"]
    out = rollout_profile.main([*argv, "--settle", "--json", str(out_path)])
    text = capsys.readouterr().out

    assert out["rollout_s"] > 0 and out["backward_s"] > 0 and out["settled"]
    work = out["particles"] * 3 * 2
    assert out["rate"] == pytest.approx(work / (out["rollout_s"] + out["backward_s"]))
    assert out["device_busy_ms"] is None  # no device on the CPU
    assert "WarpRollout" in text and "particle-substeps/s" in text
    assert json.loads(out_path.read_text()) == out


def test_profile_refuses_a_count_below_one(rollout_profile, capsys):
    with pytest.raises(SystemExit):
        rollout_profile.main(["--frames", "0"])
    assert "--frames must be at least 1, got 0" in capsys.readouterr().err
