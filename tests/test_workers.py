"""Suites spread their worker processes over the listed GPUs, one GPU per worker in turn."""

import os
import signal
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


def test_a_dead_job_runs_again_alone_and_a_raising_job_does_not(tmp_path):
    from mosiv_framework.workers import WorkerDied, run_jobs

    marker = str(tmp_path / "attempts-")
    behaviours = {"a": "answer", "b": "crash", "c": "answer", "d": "raise"}
    errors, retried = {}, []
    results = run_jobs(
        _crash_once_then_answer,
        {key: (marker, key, b) for key, b in behaviours.items()},
        workers=4,
        on_error=lambda key, error: errors.update({key: error}),
        on_retry=lambda key, died: retried.append((key, died)),
    )
    assert results == {"a": "A", "b": "B", "c": "C"}
    assert list(errors) == ["d"] and isinstance(errors["d"], ValueError)
    assert [key for key, _ in retried] == ["b"] and isinstance(retried[0][1], WorkerDied)
    assert "exited with code 1 and no result" in str(retried[0][1])
    assert (tmp_path / "attempts-b").read_text().count("attempt") == 2
    # the others ran once: a dead job no longer takes the jobs beside it down
    for key in "acd":
        assert (tmp_path / f"attempts-{key}").read_text().count("attempt") == 1


class _KeywordOnlyError(Exception):
    def __init__(self, *, what: str):
        super().__init__(f"broken: {what}")


def _raise_untravelling(what: str) -> None:
    raise _KeywordOnlyError(what=what)


def _raise_diverged(frame: int) -> None:
    from mosiv_framework.errors import SimulationDiverged

    raise SimulationDiverged(object_id=2, frame=frame, substep=1, reason="r", advice="a")


def test_errors_that_do_not_unpickle_still_reach_the_parent_by_name(tmp_path):
    """A job's SimulationDiverged once pickled but did not unpickle, and the suite died."""
    from mosiv_framework.errors import SimulationDiverged
    from mosiv_framework.workers import run_jobs

    errors = {}
    results = run_jobs(
        _raise_untravelling,
        {"odd": ("x",)},
        workers=1,
        on_error=lambda key, error: errors.update({key: error}),
    )
    assert results == {} and isinstance(errors["odd"], RuntimeError)
    assert "_KeywordOnlyError: broken: x" in str(errors["odd"])
    run_jobs(
        _raise_diverged,
        {"sim": (18,)},
        workers=1,
        on_error=lambda key, error: errors.update({key: error}),
    )
    assert isinstance(errors["sim"], SimulationDiverged) and errors["sim"].frame == 18


def test_a_job_killed_by_a_signal_is_named_and_fails_after_the_retries(tmp_path):
    from mosiv_framework.workers import WorkerDied, run_jobs

    errors = {}
    log = tmp_path / "logs" / "x.log"
    results = run_jobs(
        _killed_always,
        {"x": (str(tmp_path / "x"),)},
        workers=1,
        retries=1,
        logs={"x": log},
        on_error=lambda key, error: errors.update({key: error}),
    )
    assert results == {} and isinstance(errors["x"], WorkerDied)
    assert errors["x"].exit_code == -signal.SIGKILL
    assert "killed by SIGKILL (signal 9)" in str(errors["x"]) and str(log) in str(errors["x"])
    assert (tmp_path / "x").read_text().count("attempt") == 2  # the first try and one retry
    assert log.read_text().count("last words") == 2  # each attempt's output, in its log


def test_jobs_are_pinned_to_the_least_busy_gpu(tmp_path):
    from mosiv_framework.workers import run_jobs

    results = run_jobs(
        _visible_devices_after_a_pause, {k: (k,) for k in range(4)}, workers=2, gpus="2,5"
    )
    assert sorted(results.values()) == ["2", "2", "5", "5"]


def _killed_always(path: str) -> None:
    from pathlib import Path

    with Path(path).open("a") as log:
        log.write("attempt\n")
    print("last words", flush=True)
    os.kill(os.getpid(), signal.SIGKILL)


def _sleep_and_report(pid_file: str) -> None:
    from pathlib import Path

    Path(pid_file).write_text(str(os.getpid()))
    time.sleep(60)


def test_a_terminated_parent_takes_its_jobs_with_it(tmp_path):
    import subprocess
    import sys

    pid_file = tmp_path / "child.pid"
    parent = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "import sys; sys.path.insert(0, sys.argv[1]); import test_workers as t; "
            "from mosiv_framework.workers import run_jobs; "
            "run_jobs(t._sleep_and_report, {'x': (sys.argv[2],)}, workers=1)",
            os.path.dirname(__file__),
            str(pid_file),
        ]
    )
    deadline = time.time() + 30
    while not (pid_file.exists() and pid_file.read_text()) and time.time() < deadline:
        time.sleep(0.1)
    child = int(pid_file.read_text())
    parent.send_signal(signal.SIGTERM)
    assert parent.wait(timeout=30) == 128 + signal.SIGTERM
    time.sleep(0.5)
    with pytest.raises(ProcessLookupError):  # the child was killed and reaped, not orphaned
        os.kill(child, 0)
