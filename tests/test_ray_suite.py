"""Suites on a local Ray with CPU workers (mosiv_framework.scale): ``mosiv data suite --jobs 2``
on a cheap scene source, the task runner the diagnosis suite uses on trivial entries, a task
whose worker is killed (SIGKILL) rerun and reported, errors kept to their own entry, and the
workers logging at the level the command line chose.

Ray starts once for the module (2 CPUs). The tasks live in tests/ray_tasks.py, which the
workers import from this folder (``PYTHONPATH``); their ``worker_process_setup_hook`` adds the
``tiny`` scene source to each worker's registry.
"""

from __future__ import annotations

import ast
import json
import sys
from pathlib import Path

import pytest

ray = pytest.importorskip("ray")

import mosiv_framework.registry as registry_module  # noqa: E402
from mosiv_framework.cli.main import main  # noqa: E402
from mosiv_framework.registry import Registry  # noqa: E402
from mosiv_framework.scale import Task, TaskDied, run_command, run_tasks  # noqa: E402

HERE = Path(__file__).resolve().parent
if str(HERE) not in sys.path:
    sys.path.insert(0, str(HERE))
import ray_tasks  # noqa: E402


@pytest.fixture(scope="module", autouse=True)
def local_ray():
    ray.init(
        num_cpus=2,
        num_gpus=0,
        include_dashboard=False,
        logging_level="ERROR",
        runtime_env={
            "env_vars": {"PYTHONPATH": str(HERE)},
            "worker_process_setup_hook": "ray_tasks.register_tiny_source",
        },
    )
    yield
    ray.shutdown()


@pytest.fixture
def tiny_registry(monkeypatch):
    registry = Registry()
    ray_tasks.register_tiny_source(registry)
    monkeypatch.setattr(registry_module, "get_registry", lambda **_: registry)


def test_data_suite_runs_its_scenes_as_ray_tasks(tiny_registry, tmp_path, capsys):
    out = tmp_path / "suite"
    argv = ["data", "suite", str(out), "--source", "tiny", "--only", "E-P,S-S", "--jobs", "2"]
    assert main(argv) == 0
    index = json.loads((out / "suite.json").read_text())
    assert set(index["scenes"]) == {"E-P", "S-S"}
    assert index["scenes"]["S-S"]["materials"] == ["sand", "sand"]
    for code in ("E-P", "S-S"):
        scene = json.loads((out / code / "scene.json").read_text())
        assert [o["material"] for o in scene["objects"]] == index["scenes"][code]["materials"]
        # the worker's own progress went to the scene's log, not lost
        assert f"{code} (" in (out / "logs" / f"{code}.log").read_text()
    assert not (out / ".partial").exists()
    captured = capsys.readouterr()
    assert "2 of 2 scene(s) ready" in captured.out and "run again" not in captured.out
    assert "E-P: finished in" in captured.err and "S-S: finished in" in captured.err


def test_data_suite_reruns_a_scene_whose_worker_was_killed(tiny_registry, tmp_path, capsys):
    out, marker = tmp_path / "suite", tmp_path / "killed-once"
    argv = ["data", "suite", str(out), "--source", "tiny", "--only", "E-P,S-S", "--jobs", "2"]
    assert main([*argv, f"kill_marker=sand,sand:{marker}"]) == 0
    assert marker.is_file()  # the first attempt got as far as the kill
    assert (out / "S-S" / "scene.json").is_file() and (out / "E-P" / "scene.json").is_file()
    captured = capsys.readouterr()
    assert "run again after their worker died: S-S" in captured.out
    assert "S-S: its worker died" in captured.err


def test_diagnose_suite_runner_on_two_entries_one_killed_once(tmp_path):
    marker = tmp_path / "killed-once"
    tasks = [
        Task("a", ray_tasks.entry, ("a", str(tmp_path)), tmp_path / "a.log"),
        Task("b", ray_tasks.entry, ("b", str(tmp_path), str(marker)), tmp_path / "b.log"),
    ]
    seen = []
    outcomes = run_tasks(tasks, jobs=2, gpus_per_task=0, on_done=lambda o: seen.append(o.name))
    assert list(outcomes) == ["a", "b"] and sorted(seen) == ["a", "b"]
    assert all(o.ok for o in outcomes.values())
    assert (outcomes["a"].attempts, outcomes["b"].attempts) == (1, 2)
    assert outcomes["b"].retried and not outcomes["a"].retried
    for name in "ab":
        assert ast.literal_eval((tmp_path / f"{name}.json").read_text()) == outcomes[name].result
    # the dead worker's pid is not the pid that finished the entry
    assert int(marker.read_text()) != outcomes["b"].result["pid"]
    assert outcomes["b"].result["gpus"] in ("", None)  # 0 GPUs asked for: none visible


def test_a_process_entry_returns_its_exit_code_and_writes_to_the_entry_log(tmp_path):
    """run_command, the body of the benchmarks' per-entry processes: the program's output
    goes to the task's log and its exit code is the outcome's result."""
    program = "import os, sys; print('entry output'); sys.exit(3 if os.getpid() else 0)"
    log = tmp_path / "entry.log"
    task = Task("proc", run_command, ([sys.executable, "-c", program],), log)
    outcome = run_tasks([task], jobs=2, gpus_per_task=0)["proc"]
    assert outcome.ok and outcome.result == 3
    assert "entry output" in log.read_text()


def test_an_error_stays_with_its_entry_and_a_death_every_time_fails_it(tmp_path):
    tasks = [
        Task("wrong", ray_tasks.fail, ("wrong",)),
        Task("dies", ray_tasks.die),
        Task("fine", ray_tasks.entry, ("fine", str(tmp_path))),
    ]
    outcomes = run_tasks(tasks, jobs=2, gpus_per_task=0, retries=1)
    assert isinstance(outcomes["wrong"].error, ValueError)
    assert "entry wrong is wrong" in str(outcomes["wrong"].error)
    assert outcomes["wrong"].attempts == 1  # an ordinary exception is not retried
    assert isinstance(outcomes["dies"].error, TaskDied) and outcomes["dies"].attempts == 2
    assert outcomes["fine"].ok


@pytest.mark.parametrize("level, shown", [("INFO", True), ("WARNING", False)])
def test_ray_workers_log_at_the_level_the_cli_chose(level, shown, tmp_path, monkeypatch):
    monkeypatch.setenv("MOSIV_LOG_LEVEL", level)  # what configure_logging leaves for workers
    log = tmp_path / "entry.log"
    task = Task("a", ray_tasks.entry, ("a", str(tmp_path)), log)
    assert run_tasks([task], jobs=2, gpus_per_task=0)["a"].ok
    text = log.read_text()
    assert "[mosiv] warning: warning from a" in text
    assert ("[mosiv] info from a" in text) is shown
