"""The task runner's checks and its in-process mode (mosiv_framework.scale, no Ray started):
names, ``--jobs``/``--gpus-per-task`` values, tasks one after another with the first exception
propagating. tests/test_ray_suite.py runs the same interface on a local Ray."""

from __future__ import annotations

import argparse

import pytest

from mosiv_framework.errors import ConfigError
from mosiv_framework.scale import Task, run_tasks
from mosiv_framework.scale.flags import add_scale_flags, scale_options


def _square(x: int) -> int:
    return x * x


def _raise(message: str) -> None:
    raise KeyError(message)


def test_in_process_tasks_run_in_order_and_report_each():
    seen = []
    outcomes = run_tasks(
        [Task(f"t{i}", _square, (i,)) for i in (3, 1, 2)], jobs=1, on_done=seen.append
    )
    assert list(outcomes) == ["t3", "t1", "t2"]
    assert [outcomes[n].result for n in outcomes] == [9, 1, 4]
    assert [o.name for o in seen] == ["t3", "t1", "t2"]
    assert all(o.ok and not o.retried and o.attempts == 1 for o in outcomes.values())


def test_in_process_the_first_exception_propagates_and_stops_the_rest():
    seen = []
    tasks = [Task("a", _square, (2,)), Task("b", _raise, ("b broke",)), Task("c", _square, (3,))]
    with pytest.raises(KeyError, match="b broke"):
        run_tasks(tasks, jobs=1, on_done=seen.append)
    assert [o.name for o in seen] == ["a"]


def test_repeated_names_and_bad_jobs_are_refused_before_anything_runs():
    with pytest.raises(ValueError, match=r"repeat: \['a'\]"):
        run_tasks([Task("a", _square, (1,)), Task("a", _square, (2,))], jobs=1)
    with pytest.raises(ValueError, match="jobs=0"):
        run_tasks([Task("a", _square, (1,))], jobs=0)


def _parse(*argv: str) -> dict:
    parser = argparse.ArgumentParser()
    add_scale_flags(parser, "entries")
    return scale_options(parser.parse_args(argv))


def test_jobs_default_to_this_process_on_one_machine_and_no_limit_on_a_cluster():
    assert _parse() == {"ray_address": None, "jobs": 1, "gpus_per_task": None}
    assert _parse("--ray-address", "auto")["jobs"] is None
    assert _parse("--ray-address", "auto", "--jobs", "3")["jobs"] == 3
    assert _parse("--jobs", "4", "--gpus-per-task", "0.25") == {
        "ray_address": None,
        "jobs": 4,
        "gpus_per_task": 0.25,
    }


@pytest.mark.parametrize(
    "argv, named",
    [(("--jobs", "0"), "--jobs 0"), (("--gpus-per-task", "-1"), "--gpus-per-task -1")],
)
def test_bad_flag_values_name_the_flag(argv, named):
    with pytest.raises(ConfigError, match=named):
        _parse(*argv)
