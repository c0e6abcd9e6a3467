"""Worker processes for suites that run many scenes at once, spread over the host's GPUs.

A suite (``diagnose-suite``, the benchmark scripts) runs one scene per worker process. On a
host with several GPUs each worker is pinned to one of them, round-robin, by setting
``CUDA_VISIBLE_DEVICES`` before the worker imports any backend; the recipes then keep naming
plain ``cuda`` and every process sees its own GPU as device 0.

Which GPUs to use comes from the ``gpus`` argument or else the ``MOSIV_GPUS`` environment
variable (comma-separated CUDA ordinals, e.g. ``0,1,2,3``); with neither, workers inherit the
parent's environment unchanged.
"""

from __future__ import annotations

import multiprocessing
import os
from collections.abc import Callable, Hashable, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from concurrent.futures.process import BrokenProcessPool

GPUS_VARIABLE = "MOSIV_GPUS"


def gpu_list(gpus: str | Sequence[str] | None = None) -> list[str]:
    """The GPU ordinals to spread workers over: ``gpus`` if given, else ``$MOSIV_GPUS``."""
    if gpus is None:
        gpus = os.environ.get(GPUS_VARIABLE, "")
    if isinstance(gpus, str):
        gpus = gpus.split(",")
    listed = [str(g).strip() for g in gpus if str(g).strip()]
    for g in listed:
        if not g.isdigit():
            raise ValueError(
                f"GPU list {','.join(listed)!r} (from --gpus or ${GPUS_VARIABLE}): {g!r} is "
                "not a CUDA ordinal; valid is e.g. 0,1,2,3"
            )
    return listed


def _pin_worker(counter, gpus: list[str]) -> None:
    # Runs first in every worker, before any job imports torch, Warp or Taichi.
    with counter.get_lock():
        index = counter.value
        counter.value += 1
    os.environ["CUDA_VISIBLE_DEVICES"] = gpus[index % len(gpus)]


def worker_pool(jobs: int, *, gpus: str | Sequence[str] | None = None) -> ProcessPoolExecutor:
    """``jobs`` spawned worker processes (clean: no inherited torch or Warp state), each
    pinned to one GPU of :func:`gpu_list` in turn when that list is not empty."""
    context = multiprocessing.get_context("spawn")
    listed = gpu_list(gpus)
    if not listed:
        return ProcessPoolExecutor(max_workers=jobs, mp_context=context)
    counter = context.Value("i", 0)
    return ProcessPoolExecutor(
        max_workers=jobs, mp_context=context, initializer=_pin_worker, initargs=(counter, listed)
    )


def run_jobs(
    fn: Callable,
    jobs_by_key: dict[Hashable, tuple],
    *,
    workers: int,
    gpus: str | Sequence[str] | None = None,
    retries: int = 2,
    on_result: Callable = lambda key, result: None,
    on_error: Callable = lambda key, error: None,
    on_retry: Callable = lambda keys: None,
) -> dict:
    """``fn(*args)`` for every ``key: args`` of ``jobs_by_key`` in a :func:`worker_pool`;
    returns ``{key: result}`` for the jobs that finished, calling ``on_result`` for each as it
    does, ``on_error`` for each job that raised, and ``on_retry`` with the keys of the jobs a
    dead worker cut short before they run again.

    A worker process that dies (a crash in native code, the out-of-memory killer) breaks the
    whole pool: every job still in it fails with ``BrokenProcessPool``, not only the one that
    crashed (13 diagnosis entries were lost that way at once, session 15). Those jobs are
    submitted again to a fresh pool, up to ``retries`` more rounds, so the work a suite's
    entries had saved (their finished stages) is picked up where it stopped; a job that
    raised an ordinary exception is not retried.
    """
    results: dict = {}
    pending = dict(jobs_by_key)
    for round_ in range(retries + 1):
        if not pending:
            break
        cut_short: dict = {}
        with worker_pool(min(workers, len(pending)), gpus=gpus) as pool:
            futures = {pool.submit(fn, *args): key for key, args in pending.items()}
            for future in as_completed(futures):
                key = futures[future]
                try:
                    results[key] = future.result()
                except BrokenProcessPool as error:
                    if round_ < retries:
                        cut_short[key] = pending[key]
                    else:
                        on_error(key, error)
                    continue
                except Exception as error:  # one broken job must not lose the others
                    on_error(key, error)
                    continue
                on_result(key, results[key])
        pending = cut_short
        if pending:
            on_retry(sorted(pending, key=str))
    return results


def environment_for(index: int, *, gpus: str | Sequence[str] | None = None) -> dict[str, str]:
    """The environment of the ``index``-th child process of a suite that starts commands
    itself (rather than through :func:`worker_pool`): pinned to a GPU in turn."""
    env = dict(os.environ)
    listed = gpu_list(gpus)
    if listed:
        env["CUDA_VISIBLE_DEVICES"] = listed[index % len(listed)]
    return env
