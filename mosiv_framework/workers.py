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
import pickle
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Hashable, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import IO

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


def _start_worker(counter, gpus: list[str]) -> None:
    # Runs first in every worker, before any job imports torch, Warp or Taichi. A spawned
    # worker starts without the parent's logging set-up: it takes the level from the
    # environment the CLI left it.
    from mosiv_framework.logs import configure_from_environment

    configure_from_environment()
    if not gpus:
        return
    with counter.get_lock():
        index = counter.value
        counter.value += 1
    os.environ["CUDA_VISIBLE_DEVICES"] = gpus[index % len(gpus)]


def worker_pool(jobs: int, *, gpus: str | Sequence[str] | None = None) -> ProcessPoolExecutor:
    """``jobs`` spawned worker processes (clean: no inherited torch or Warp state), each
    pinned to one GPU of :func:`gpu_list` in turn when that list is not empty."""
    context = multiprocessing.get_context("spawn")
    listed = gpu_list(gpus)
    counter = context.Value("i", 0)
    return ProcessPoolExecutor(
        max_workers=jobs, mp_context=context, initializer=_start_worker, initargs=(counter, listed)
    )


class WorkerDied(RuntimeError):
    """A job's process ended without a result or an exception: killed by a signal (the
    out-of-memory killer, a crash in native code) or stopped by ``os._exit``."""

    def __init__(self, key: Hashable, exit_code: int, log: Path | None):
        self.key, self.exit_code, self.log = key, exit_code, log
        where = f" (its output: {log})" if log is not None else ""
        super().__init__(f"the process of job {key!r} {describe_exit(exit_code)}{where}")


def describe_exit(exit_code: int) -> str:
    """``exit_code`` of a child process in words: negative codes are the signal that ended it."""
    if exit_code < 0:
        try:
            name = signal.Signals(-exit_code).name
        except ValueError:
            name = f"signal {-exit_code}"
        return f"was killed by {name} (signal {-exit_code})"
    return f"exited with code {exit_code} and no result"


@dataclass
class _Running:
    process: subprocess.Popen
    folder: Path
    gpu: str | None
    log: IO | None


def run_jobs(
    fn: Callable,
    jobs_by_key: dict[Hashable, tuple],
    *,
    workers: int,
    gpus: str | Sequence[str] | None = None,
    retries: int = 2,
    logs: dict[Hashable, Path] | None = None,
    on_result: Callable = lambda key, result: None,
    on_error: Callable = lambda key, error: None,
    on_retry: Callable = lambda key, died: None,
    poll_s: float = 0.2,
) -> dict:
    """``fn(*args)`` for every ``key: args`` of ``jobs_by_key``, each job in a process of its
    own (``python -m mosiv_framework.worker_main``), at most ``workers`` at once, each pinned
    to the listed GPU (:func:`gpu_list`) running the fewest jobs. Returns ``{key: result}``
    for the jobs that finished, calling ``on_result`` for each as it does, ``on_error`` for
    each job that raised or died too often, and ``on_retry(key, WorkerDied)`` for each job
    run again after its process died.

    One process per job, not a pool: a pool's worker that dies breaks the whole pool, and
    every job in it fails with no word of why (8 diagnosis entries of one suite on two H200s
    failed so, three runs in a row). Here a job whose process dies (a signal, a crash
    in native code: the child runs with ``-X faulthandler``) costs only itself, the signal is
    named, and it runs again, up to ``retries`` more times, from the work it had saved. A job
    that raised an ordinary exception is not retried. ``logs`` (key: file) appends each job's
    output to its own file instead of this process's.
    """
    results: dict = {}
    listed = gpu_list(gpus)
    waiting = list(jobs_by_key)
    deaths = dict.fromkeys(jobs_by_key, 0)
    running: dict[Hashable, _Running] = {}
    started = 0
    scratch = Path(tempfile.mkdtemp(prefix="mosiv-jobs-"))
    # a SIGTERM (``timeout``, a batch system) must reach the ``finally`` below, as Ctrl-C does,
    # or the children run on as orphans holding their GPUs
    on_main_thread = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGTERM, _exit_on_signal) if on_main_thread else None
    try:
        while waiting or running:
            while waiting and len(running) < max(1, workers):
                key = waiting.pop(0)
                gpu = _least_busy(listed, [job.gpu for job in running.values()])
                started += 1
                running[key] = _start(
                    fn, jobs_by_key[key], scratch / str(started), gpu, (logs or {}).get(key)
                )
            time.sleep(poll_s)
            for key in [k for k, job in running.items() if job.process.poll() is not None]:
                job = running.pop(key)
                if job.log is not None:
                    job.log.close()
                outcome, value = _collect(job)
                if outcome == "result":
                    results[key] = value
                    on_result(key, value)
                elif outcome == "error":
                    on_error(key, value)
                else:
                    died = WorkerDied(key, job.process.returncode, (logs or {}).get(key))
                    deaths[key] += 1
                    if deaths[key] <= retries:
                        on_retry(key, died)
                        waiting.append(key)
                    else:
                        on_error(key, died)
    finally:
        for job in running.values():  # interrupted: leave no orphans behind
            job.process.kill()
            job.process.wait()
            if job.log is not None:
                job.log.close()
        shutil.rmtree(scratch, ignore_errors=True)
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)
    return results


def _exit_on_signal(signum, frame) -> None:
    raise SystemExit(128 + signum)


def _least_busy(listed: list[str], busy: list[str | None]) -> str | None:
    if not listed:
        return None
    return min(listed, key=lambda gpu: (busy.count(gpu), listed.index(gpu)))


def _start(fn, args: tuple, folder: Path, gpu: str | None, log: Path | None) -> _Running:
    folder.mkdir(parents=True)
    # the child puts this process's import path in place before it unpickles the job, so a
    # function of any importable module (a test file too) can be a job
    payload = pickle.dumps((fn, args))
    (folder / "job.pkl").write_bytes(pickle.dumps((list(sys.path), payload)))
    env = dict(os.environ)
    if gpu is not None:
        env["CUDA_VISIBLE_DEVICES"] = gpu  # before the child imports any backend
    handle = None
    if log is not None:
        log.parent.mkdir(parents=True, exist_ok=True)
        handle = log.open("ab")
    process = subprocess.Popen(
        [sys.executable, "-X", "faulthandler", "-m", "mosiv_framework.worker_main", str(folder)],
        env=env,
        stdin=subprocess.DEVNULL,
        stdout=handle,
        stderr=subprocess.STDOUT if handle is not None else None,
    )
    return _Running(process, folder, gpu, handle)


def _collect(job: _Running) -> tuple[str, object]:
    """("result", value), ("error", exception) or ("died", None) for a finished job."""
    for outcome in ("result", "error"):
        path = job.folder / f"{outcome}.pkl"
        if path.exists():
            return outcome, pickle.loads(path.read_bytes())
    return "died", None


def environment_for(index: int, *, gpus: str | Sequence[str] | None = None) -> dict[str, str]:
    """The environment of the ``index``-th child process of a suite that starts commands
    itself (rather than through :func:`worker_pool`): pinned to a GPU in turn."""
    env = dict(os.environ)
    listed = gpu_list(gpus)
    if listed:
        env["CUDA_VISIBLE_DEVICES"] = listed[index % len(listed)]
    return env
