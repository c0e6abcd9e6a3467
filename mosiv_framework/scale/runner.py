"""Run a suite's entries as Ray tasks: :func:`run_tasks`.

Each :class:`Task` is one entry (a scene to generate, a run to diagnose): a function of an
importable module, its arguments and, optionally, a file its output goes to. ``run_tasks``
runs them on a local Ray started for the call (every CPU of the host, its GPUs as Ray detects
them) or on the cluster at ``ray_address``, each task asking for ``cpus_per_task`` CPUs and
``gpus_per_task`` GPUs: a fraction lets several tasks share one GPU, and Ray hands each task
its devices through ``CUDA_VISIBLE_DEVICES``, so recipes keep naming plain ``cuda``.

A task whose worker process dies (a signal, the out-of-memory killer, a crash in native code,
a lost node) is submitted again, up to ``retries`` more times, and counted in its
:class:`Outcome`; the suites' entries resume from the stages they saved, so a rerun repeats
only the unfinished work. The Ray tasks themselves run with ``max_retries=0`` and this module
resubmits them: Ray's own retry would rerun a task silently, and a suite has to name each
death the moment it happens and report which entries needed another attempt.

With ``jobs == 1`` and no ``ray_address`` the tasks run one after another in this process
(no Ray started), and the first exception propagates with its traceback: the mode to debug in.
"""

from __future__ import annotations

import contextlib
import faulthandler
import logging
import os
import signal
import socket
import sys
import threading
import time
import traceback
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from mosiv_framework.logs import LEVEL_VARIABLE, configure_from_environment

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Task:
    """One entry of a suite: ``fn(*args)`` named ``name`` (unique in the suite).

    ``fn`` must be a function of an importable module (Ray workers import it by name);
    ``log``, if given, receives the task's stdout, stderr and log records (appended) when it
    runs on Ray; in this process (``jobs=1``) the output stays on the console.
    """

    name: str
    fn: Callable
    args: tuple = ()
    log: Path | None = None


@dataclass
class Outcome:
    """What became of one task: its ``result`` or its ``error``, and how many attempts it
    took (more than one: its worker died and it ran again)."""

    name: str
    result: Any = None
    error: BaseException | None = None
    attempts: int = 1
    seconds: float = 0.0

    @property
    def ok(self) -> bool:
        return self.error is None

    @property
    def retried(self) -> bool:
        return self.attempts > 1


class TaskDied(RuntimeError):
    """A task's worker process died on every attempt it was given."""

    def __init__(self, name: str, attempts: int, why: str, log_path: Path | None):
        self.name, self.attempts, self.log_path = name, attempts, log_path
        where = f" (its output: {log_path})" if log_path is not None else ""
        super().__init__(f"the worker of {name!r} died on all {attempts} attempt(s): {why}{where}")


def run_tasks(
    tasks: Sequence[Task],
    *,
    ray_address: str | None = None,
    jobs: int | None = None,
    gpus_per_task: float | None = None,
    cpus_per_task: float = 1.0,
    retries: int = 2,
    on_done: Callable[[Outcome], None] | None = None,
) -> dict[str, Outcome]:
    """Run every task; returns ``{name: Outcome}`` in the order of ``tasks``.

    Args:
        tasks: the entries, names unique.
        ray_address: a running Ray cluster (``auto``, ``ray://host:10001``, ``host:6379``);
            None starts a local Ray for this call, or joins the one this process already has.
        jobs: at most this many tasks in flight (None: as many as the cluster's free CPUs and
            GPUs allow). ``1`` without ``ray_address``: one after another in this process.
        gpus_per_task: GPUs each task asks for; ``0.25`` lets four tasks share one GPU, ``0``
            hides the GPUs from the task. None: one each where the cluster has GPUs, else 0.
        cpus_per_task: CPUs each task asks for (Ray's scheduling unit; threads are not capped).
        retries: how many more times a task whose worker died is submitted.
        on_done: called with each outcome as it is known (e.g. to update an index).

    An exception a task raises is its outcome's ``error`` (not retried: it would raise
    again); a task that died more than ``retries`` times has a :class:`TaskDied` error.
    """
    names = [t.name for t in tasks]
    if len(set(names)) != len(names):
        raise ValueError(f"task names repeat: {sorted({n for n in names if names.count(n) > 1})}")
    if jobs is not None and jobs < 1:
        raise ValueError(f"jobs={jobs}: must be at least 1 (or None: no limit)")
    on_done = on_done or (lambda outcome: None)
    if jobs == 1 and ray_address is None:
        return _run_here(tasks, on_done)
    import ray

    started = _connect(ray_address)
    try:
        gpus = gpus_per_task
        if gpus is None:
            gpus = 1.0 if ray.cluster_resources().get("GPU", 0) > 0 else 0.0
        outcomes = _run_on_ray(
            tasks, jobs=jobs, gpus=gpus, cpus=cpus_per_task, retries=retries, on_done=on_done
        )
    finally:
        if started:
            ray.shutdown()
    return {name: outcomes[name] for name in names}


def run_command(command: Sequence[str]) -> int:
    """A task body that runs one program (a suite's per-entry process) and returns its exit
    code; the program inherits the task's log as its output and the GPUs Ray gave the task
    (``CUDA_VISIBLE_DEVICES``). A function of this installed module, so that a Ray worker can
    import it whatever script made the task (a function of a script's sibling module cannot
    be found there)."""
    import subprocess

    return subprocess.run(list(command)).returncode


def _run_here(tasks: Sequence[Task], on_done: Callable[[Outcome], None]) -> dict[str, Outcome]:
    outcomes = {}
    for task in tasks:
        log.info("%s: started", task.name)
        begin = time.perf_counter()
        result = task.fn(*task.args)
        outcomes[task.name] = Outcome(task.name, result, seconds=time.perf_counter() - begin)
        log.info("%s: finished in %.1f s", task.name, outcomes[task.name].seconds)
        on_done(outcomes[task.name])
    return outcomes


def _connect(ray_address: str | None) -> bool:
    """Connect to ``ray_address`` or start a local Ray (unless this process has one already);
    True if this call started or joined it (and so shuts it down afterwards)."""
    import ray

    if ray.is_initialized():
        return False
    level = os.environ.get(LEVEL_VARIABLE, "")
    quiet = {
        "include_dashboard": False,
        "logging_level": logging.WARNING,
        # workers log like this process: they call configure_from_environment on this
        "runtime_env": {"env_vars": {LEVEL_VARIABLE: level}} if level else None,
    }
    if ray_address is None:
        ray.init(num_cpus=os.cpu_count() or 1, **quiet)
    else:
        ray.init(address=ray_address, **quiet)
    return True


# the failures Ray reports when a task's process or node is gone, rather than the task raising
_DEATHS = ("WorkerCrashedError", "OutOfMemoryError", "NodeDiedError", "LocalRayletDiedError")


def _run_on_ray(
    tasks: Sequence[Task],
    *,
    jobs: int | None,
    gpus: float,
    cpus: float,
    retries: int,
    on_done: Callable[[Outcome], None],
) -> dict[str, Outcome]:
    import ray

    deaths = tuple(getattr(ray.exceptions, n) for n in _DEATHS if hasattr(ray.exceptions, n))
    level = os.environ.get(LEVEL_VARIABLE, "")
    remote = ray.remote(
        num_cpus=cpus,
        num_gpus=gpus,
        max_retries=0,  # resubmitted here, see the module's docstring
        runtime_env={"env_vars": {LEVEL_VARIABLE: level}} if level else None,
    )(_execute)
    by_name = {t.name: t for t in tasks}
    waiting = [t.name for t in tasks]
    attempts = dict.fromkeys(by_name, 0)
    submitted: dict[str, float] = {}
    running: dict[Any, str] = {}
    outcomes: dict[str, Outcome] = {}
    with _terminate_cleanly(running):
        while waiting or running:
            while waiting and (jobs is None or len(running) < jobs):
                name = waiting.pop(0)
                attempts[name] += 1
                task = by_name[name]
                running[remote.options(name=name).remote(task.fn, task.args, task.log, name)] = name
                submitted.setdefault(name, time.perf_counter())
                log.info("%s: queued (attempt %d)", name, attempts[name])
            (ref,), _ = ray.wait(list(running), num_returns=1)
            name = running.pop(ref)
            outcome = Outcome(name, attempts=attempts[name])
            try:
                outcome.result = ray.get(ref)
            except deaths as died:
                why = str(died).splitlines()[0]
                if attempts[name] <= retries:
                    log.warning(
                        "%s: its worker died (%s); running it again from its finished stages "
                        "(attempt %d of %d)",
                        name,
                        why,
                        attempts[name] + 1,
                        retries + 1,
                    )
                    waiting.insert(0, name)
                    continue
                outcome.error = TaskDied(name, attempts[name], why, by_name[name].log)
            except ray.exceptions.RayTaskError as raised:
                outcome.error = raised.cause if raised.cause is not None else raised
            outcome.seconds = time.perf_counter() - submitted[name]
            _report(outcome, by_name[name].log)
            outcomes[name] = outcome
            on_done(outcome)
    return outcomes


def _report(outcome: Outcome, log_path: Path | None) -> None:
    again = f", after {outcome.attempts - 1} retry(ies)" if outcome.retried else ""
    if outcome.ok:
        log.info("%s: finished in %.1f s%s", outcome.name, outcome.seconds, again)
    else:
        where = f" (log: {log_path})" if log_path is not None else ""
        log.error("%s: FAILED%s: %r%s", outcome.name, again, outcome.error, where)


@contextlib.contextmanager
def _terminate_cleanly(running: dict) -> Iterator[None]:
    """Cancel the tasks still running when the loop is left early (Ctrl-C, an error); a
    SIGTERM (``timeout``, a batch system) is made to leave it as Ctrl-C does."""
    import ray

    on_main_thread = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGTERM, _exit_on_signal) if on_main_thread else None
    try:
        yield
    finally:
        for ref in list(running):
            ray.cancel(ref, force=True)
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)


def _exit_on_signal(signum, frame) -> None:
    raise SystemExit(128 + signum)


def _execute(fn: Callable, args: tuple, log_path: Path | None, name: str) -> Any:
    """The body of every Ray task: log like the CLI, send output to the task's log, run."""
    configure_from_environment()  # a Ray worker starts without the CLI's logging set-up
    gpus = os.environ.get("CUDA_VISIBLE_DEVICES", "-")
    # before the redirection: this line reaches the console of the suite (Ray forwards it)
    where = f"{socket.gethostname()} (pid {os.getpid()}, GPUs {gpus})"
    log.info("%s: started on %s", name, where)
    with _output_to(log_path):
        log.info("%s: started on %s", name, where)
        try:
            return fn(*args)
        except Exception:
            traceback.print_exc()  # the full traceback in the task's log; Ray carries the rest
            raise


@contextlib.contextmanager
def _output_to(path: Path | None) -> Iterator[None]:
    """Append this worker's output to ``path`` while the block runs: file descriptors 1 and
    2 point at the file, so native code's output and a crash's stack (``faulthandler``) land
    there too; afterwards they point back (Ray reuses the worker for other tasks)."""
    if path is None:
        yield
        return
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    sys.stdout.flush()
    sys.stderr.flush()
    saved = os.dup(1), os.dup(2)
    with open(path, "ab") as sink:
        os.dup2(sink.fileno(), 1)
        os.dup2(sink.fileno(), 2)
        faulthandler.enable(file=2)
        try:
            yield
        finally:
            sys.stdout.flush()
            sys.stderr.flush()
            os.dup2(saved[0], 1)
            os.dup2(saved[1], 2)
            for fd in saved:
                os.close(fd)
