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
