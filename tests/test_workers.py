"""Suites spread their worker processes over the listed GPUs, one GPU per worker in turn."""

import os
import time

import pytest

from mosiv_framework.workers import environment_for, gpu_list, worker_pool


def _visible_devices_after_a_pause(_job=None) -> str:
    # the pause keeps this worker busy, so the other worker takes the next job
    time.sleep(1.0)
    return os.environ.get("CUDA_VISIBLE_DEVICES", "<unset>")


def test_workers_are_pinned_round_robin():
    with worker_pool(2, gpus="2,5") as pool:
        seen = set(pool.map(_visible_devices_after_a_pause, range(4)))
    assert seen == {"2", "5"}


def test_no_gpu_list_leaves_the_environment_alone(monkeypatch):
    monkeypatch.delenv("MOSIV_GPUS", raising=False)
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "7")
    with worker_pool(1) as pool:
        assert pool.submit(_visible_devices_after_a_pause).result() == "7"
    assert environment_for(4)["CUDA_VISIBLE_DEVICES"] == "7"


def test_environment_variable_and_child_environments(monkeypatch):
    monkeypatch.setenv("MOSIV_GPUS", "0, 1,3")
    assert gpu_list() == ["0", "1", "3"]
    assert [environment_for(i)["CUDA_VISIBLE_DEVICES"] for i in range(4)] == ["0", "1", "3", "0"]


def test_a_bad_gpu_list_names_the_value():
    with pytest.raises(ValueError, match="'cuda:1' is not a CUDA ordinal"):
        gpu_list("0,cuda:1")


def _crash_once_then_answer(marker: str, key: str, behaviour: str) -> str:
    """A job that kills its worker the first time it runs (``crash``), raises (``raise``), or
    answers after a pause (``answer``, long enough to be in flight when a worker dies). Each
    attempt leaves a line in ``marker`` + key."""
    from pathlib import Path

    attempts = Path(marker + key)
    first = not attempts.exists()
    with attempts.open("a") as log:
        log.write("attempt\n")
    if behaviour == "crash" and first:
        os._exit(1)  # as a segfault would: no exception, the process is gone
    if behaviour == "raise":
        raise ValueError(f"job {key} is broken")
    time.sleep(0.5 if behaviour == "answer" else 0.0)
    return key.upper()


def test_jobs_cut_short_by_a_dead_worker_run_again_and_a_raising_job_does_not(tmp_path):
    from mosiv_framework.workers import run_jobs

    marker = str(tmp_path / "attempts-")
    behaviours = {"a": "answer", "b": "crash", "c": "answer", "d": "raise"}
    errors, retried = {}, []
    results = run_jobs(
        _crash_once_then_answer,
        {key: (marker, key, b) for key, b in behaviours.items()},
        workers=4,
        on_error=lambda key, error: errors.update({key: error}),
        on_retry=retried.append,
    )
    assert results == {"a": "A", "b": "B", "c": "C"}
    assert list(errors) == ["d"] and isinstance(errors["d"], ValueError)
    assert retried and "b" in retried[0]
    assert (tmp_path / "attempts-b").read_text().count("attempt") == 2
    assert (tmp_path / "attempts-d").read_text().count("attempt") == 1  # not retried


def test_a_job_that_kills_its_worker_every_time_fails_after_the_retries(tmp_path):
    from concurrent.futures.process import BrokenProcessPool

    from mosiv_framework.workers import run_jobs

    errors = {}
    results = run_jobs(
        _crash_always,
        {"x": (str(tmp_path / "x"),)},
        workers=1,
        retries=1,
        on_error=lambda key, error: errors.update({key: error}),
    )
    assert results == {} and isinstance(errors["x"], BrokenProcessPool)
    assert (tmp_path / "x").read_text().count("attempt") == 2  # the first try and one retry


def _crash_always(path: str) -> None:
    from pathlib import Path

    with Path(path).open("a") as log:
        log.write("attempt\n")
    os._exit(1)
