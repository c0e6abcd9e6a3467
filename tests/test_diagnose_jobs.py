"""benchmarks/diagnose_jobs.py: a diagnosis suite's entries as device_queue.py jobs."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _load(name: str):
    spec = importlib.util.spec_from_file_location(name, ROOT / "benchmarks" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module


def test_every_entry_not_yet_scored_becomes_one_queue_job(tmp_path):
    """One job per entry of the Genesis test split, in suite order, each diagnosing that
    entry alone into the one absolute OUT with the budget and overrides; a scored entry is
    left out, so the list after a lease is what remains; an unknown name is refused."""
    jobs_module, queue = _load("diagnose_jobs"), _load("device_queue")
    out = tmp_path / "suite"
    (out / "wind-0").mkdir(parents=True)
    (out / "wind-0" / "score.json").write_text("{}")
    lines = jobs_module.job_lines(
        out,
        source="genesis",
        split="test",
        budget="full",
        overrides=["identify.param_iterations=40"],
    )
    path = tmp_path / "jobs.txt"
    path.write_text("\n".join(lines) + "\n")
    listed = queue.read_jobs(path)
    names = [job.name for job in listed]
    assert len(names) == 17 and "wind-0" not in names
    assert names[:2] == ["linear_drag-0", "linear_drag-1"] and names[-1] == "control-5"
    words = listed[0].command.split()
    assert words[:3] == ["mosiv", "diagnose-suite", str(out.resolve())]
    assert words[3:] == [
        "--source", "genesis", "--split", "test", "--only", "linear_drag-0",
        "--budget", "full", "--set", "identify.param_iterations=40",
    ]  # fmt: skip
    only = jobs_module.job_lines(out, source="genesis", split="test", budget="small",
                                 only=["control-0", "wind-0"])  # fmt: skip
    assert [line.split()[0] for line in only] == ["control-0"]
    with pytest.raises(ValueError, match="--only wind-9: not in the suite; valid: linear_drag-0"):
        jobs_module.job_lines(out, source="genesis", split="test", budget="full", only=["wind-9"])
