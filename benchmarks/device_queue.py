"""A list of GPU jobs on the device machine: a few at a time per GPU, each in its own copy of
the checkout, detached from the device call that starts them.

Why not just start them all (benchmarks/device_batch.sh start): two ways of losing a lease.

- Every device call copies the working tree into the repository root again. A job that imports
  a module lazily (a plugin's simulator, say) while a later call's copy is going on can find the
  file missing and die. Here a job runs in a snapshot of the checkout taken when it starts.
- Fourteen processes on two GPUs, each torch process spreading its CPU work over every core,
  slowed every one of them about tenfold, so none finished within the lease. Here at most
  ``--slots`` jobs run on each GPU at once and each gets its share of the CPU cores as threads.

Usage (repository root, after ``source benchmarks/gpu_setup.sh``)::

    python3 benchmarks/device_queue.py start JOBFILE --slots 3 --code-version COMMIT
    bash benchmarks/device_batch.sh wait SECONDS 'GLOB' ...   # later calls: wait, pack results
    python3 benchmarks/device_queue.py stop                    # end the queue and its jobs
    python3 benchmarks/device_queue.py stop --only A,B         # end jobs A and B only

``--mps`` runs the jobs under NVIDIA's Multi-Process Service: the queue starts its control
daemon (``nvidia-cuda-mps-control -d``, pipe and log folders in ``JOBS/mps``) and quits it when
the queue ends or is stopped. Without it a GPU runs one process's kernels at a time, switching
between processes; jobs at Genesis-scene size (a few thousand particles) leave most of the GPU
idle in each kernel, so several of them then take as long as one after the other. Under MPS
their kernels run side by side (docs/BENCHMARKS.md, "Several processes on one GPU").

``stop`` frees the GPU before the lease's end (for a benchmark that must run alone, say): the
queue starts nothing more and every running job's process group is ended (``NAME.rc`` then
reads ``stopped``); what the jobs saved stays. It finds them by the process ids the queue
records (``JOBS/queue.pid``, ``JOBS/NAME.pid``), not by matching command lines, which would
also match the device call that runs ``stop``. ``stop --only NAMES`` ends just those jobs,
running or still queued, and the queue goes on with the others: when more jobs share the GPUs
than can finish inside a lease, stopping the furthest behind lets the rest finish.

JOBFILE holds one job per line, ``NAME COMMAND...`` (COMMAND in shell syntax, run by bash in
the job's snapshot); blank lines and lines starting with # are skipped. Each job logs to
``JOBS/NAME.log`` and leaves its exit code in ``JOBS/NAME.rc`` (JOBS: ``--jobs-dir``, default
``jobs`` in the home folder, the folder device_batch.sh reads); a job not yet started has
``JOBS/NAME.queued``.
Jobs start in file order on the GPU with the fewest running jobs. The checkout is copied once
when the queue starts (``JOBS/checkout-STAMP``) and each job runs in its own copy of that,
deleted when the job ends: give jobs output folders outside the checkout.
"""

from __future__ import annotations

import argparse
import os
import shutil
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
#: hidden folders at the top of the checkout that a snapshot keeps (the others hold staged
#: wheels, data parts and caches, which jobs do not import from the checkout)
SNAPSHOT_KEEP_HIDDEN = {".tideps", ".ci"}
#: what a snapshot leaves out anywhere: run folders and caches
SNAPSHOT_IGNORE_ANYWHERE = {"runs", "__pycache__", ".pytest_cache", ".ruff_cache", ".git"}


def snapshot_ignore(folder: str, names: list[str]) -> set[str]:
    """shutil.copytree's ignore: what of ``names`` in ``folder`` a snapshot leaves out."""
    left_out = {n for n in names if n in SNAPSHOT_IGNORE_ANYWHERE or n.endswith(".egg-info")}
    if Path(folder).resolve() == ROOT:
        left_out |= {n for n in names if n.startswith(".") and n not in SNAPSHOT_KEEP_HIDDEN}
    return left_out


#: how often the queue looks for finished jobs
POLL_SECONDS = 2.0
#: beside a job stopped on its own (``stop --only``): the queue does not start it, or records
#: its end as "stopped" rather than as a failure
STOPPED = ".stopped"


#: NVIDIA's MPS control program (``--mps``), installed with the driver
MPS_CONTROL = "nvidia-cuda-mps-control"


@dataclass
class Job:
    """One line of the job file."""

    name: str
    command: str


def read_jobs(path: Path) -> list[Job]:
    """The jobs of ``path`` in file order.

    Raises:
        ValueError: a line without a command, a name that is not a plain file name, or a name
            used twice (each names the job's log and exit-code files).
    """
    jobs: list[Job] = []
    for number, line in enumerate(path.read_text().splitlines(), start=1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        name, _, command = line.partition(" ")
        if not command.strip():
            raise ValueError(f"{path}:{number}: '{name}' has no command (want: NAME COMMAND...)")
        if "/" in name or name.startswith("."):
            raise ValueError(f"{path}:{number}: job name '{name}' must be a plain file name")
        if any(job.name == name for job in jobs):
            raise ValueError(f"{path}:{number}: job name '{name}' is used twice")
        jobs.append(Job(name, command.strip()))
    return jobs


def count_gpus() -> int:
    """GPUs this process may use: CUDA_VISIBLE_DEVICES where set, else nvidia-smi's list."""
    visible = os.environ.get("CUDA_VISIBLE_DEVICES")
    if visible is not None:
        return len([d for d in visible.split(",") if d.strip()])
    try:
        listing = subprocess.run(["nvidia-smi", "-L"], capture_output=True, text=True, check=True)
    except (OSError, subprocess.CalledProcessError):
        return 0
    return sum(1 for line in listing.stdout.splitlines() if line.startswith("GPU "))


def gpu_ids(n_gpus: int) -> list[str]:
    """The device ids to hand out, as CUDA_VISIBLE_DEVICES names them."""
    visible = os.environ.get("CUDA_VISIBLE_DEVICES")
    if visible is not None:
        return [d.strip() for d in visible.split(",") if d.strip()][:n_gpus]
    return [str(i) for i in range(n_gpus)]


def checkout_version() -> str | None:
    """The code version the jobs' result rows should name (``MOSIV_CODE_VERSION``, which
    ``identify_suite.code_version`` reads): that variable where set, else the checkout's short
    commit hash, else None (a device machine's copy of the tree has no git history: pass
    ``--code-version`` there)."""
    if os.environ.get("MOSIV_CODE_VERSION"):
        return os.environ["MOSIV_CODE_VERSION"]
    try:
        head = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True
        )
    except OSError:
        return None
    return (head.stdout.strip() or None) if head.returncode == 0 else None


def mps_environment(jobs_dir: Path) -> dict[str, str]:
    """Where the queue's MPS daemon and its clients (the jobs) meet: the variables that name
    its pipe and log folders, inside ``jobs_dir``."""
    return {
        "CUDA_MPS_PIPE_DIRECTORY": str(jobs_dir / "mps" / "pipe"),
        "CUDA_MPS_LOG_DIRECTORY": str(jobs_dir / "mps" / "log"),
    }


def start_mps(jobs_dir: Path) -> dict[str, str]:
    """Start the MPS control daemon for this queue (it detaches itself and outlives the call
    that starts it); returns the variables every job needs to reach it.

    Raises:
        SystemExit: the control program is not on PATH or would not start.
    """
    program = shutil.which(MPS_CONTROL)
    if program is None:
        raise SystemExit(
            f"--mps: {MPS_CONTROL} is not on PATH (it comes with the NVIDIA driver); "
            "run the queue without --mps"
        )
    env = mps_environment(jobs_dir)
    for folder in env.values():
        Path(folder).mkdir(parents=True, exist_ok=True)
    started = subprocess.run(
        [program, "-d"], env={**os.environ, **env}, capture_output=True, text=True
    )
    if started.returncode != 0:
        raise SystemExit(f"--mps: {MPS_CONTROL} -d failed: {started.stderr.strip()}")
    return env


def stop_mps(jobs_dir: Path) -> bool:
    """Quit the MPS daemon that ``start_mps`` started for ``jobs_dir``, where its pipe folder
    is there; returns whether one was asked to quit."""
    env = mps_environment(jobs_dir)
    pipe = Path(env["CUDA_MPS_PIPE_DIRECTORY"])
    program = shutil.which(MPS_CONTROL)
    if not pipe.exists() or program is None:
        return False
    subprocess.run(
        [program], input="quit\n", text=True, env={**os.environ, **env}, capture_output=True,
        timeout=60,
    )  # fmt: skip
    shutil.rmtree(pipe, ignore_errors=True)
    return True


def job_environment(
    tree: Path,
    gpu: str,
    threads: int,
    code_version: str | None = None,
    extra: dict[str, str] | None = None,
) -> dict[str, str]:
    """The job's environment: its GPU, its CPU threads, import paths into its snapshot, the
    code version its rows name (``code_version``, where known) and ``extra`` (the MPS
    daemon's folders, say)."""
    env = dict(os.environ)
    env.update(extra or {})
    if code_version:
        env["MOSIV_CODE_VERSION"] = code_version
    env["CUDA_VISIBLE_DEVICES"] = gpu
    for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        env[var] = str(threads)
    paths = [p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p]
    # gpu_setup.sh puts the checkout and its plugins on PYTHONPATH: point them at the snapshot
    # (PYTHONPATH comes before the installed packages, so the snapshot's modules are imported)
    moved = [str(snapshot_path(Path(p), tree)) for p in paths]
    env["PYTHONPATH"] = os.pathsep.join([str(tree), *[p for p in moved if p != str(tree)]])
    return env


def snapshot_path(path: Path, tree: Path) -> Path:
    """``path`` inside the snapshot ``tree`` where it lies in the checkout and the snapshot has
    it (the staged packages, say, are left out of snapshots and stay where they are)."""
    try:
        inside = tree / path.resolve().relative_to(ROOT)
    except ValueError:
        return path
    return inside if inside.exists() else path


def take_snapshot(jobs_dir: Path) -> Path:
    """A copy of the checkout as it is now, which every job of this queue starts from (a job
    started later must not copy a checkout that a device call is replacing meanwhile)."""
    source = jobs_dir / f"checkout-{time.strftime('%Y%m%d-%H%M%S')}-{os.getpid()}"
    shutil.copytree(ROOT, source, ignore=snapshot_ignore, symlinks=True)
    return source


def launch(
    job: Job,
    source: Path,
    jobs_dir: Path,
    gpu: str,
    threads: int,
    code_version: str | None,
    extra_env: dict[str, str] | None = None,
) -> subprocess.Popen:
    """Copy the queue's snapshot ``source`` for ``job`` and start the job in it on ``gpu``."""
    tree = jobs_dir / f"{job.name}.tree"
    shutil.rmtree(tree, ignore_errors=True)
    shutil.copytree(source, tree, symlinks=True)
    log = open(jobs_dir / f"{job.name}.log", "w")  # noqa: SIM115 (the child holds it open)
    (jobs_dir / f"{job.name}.queued").unlink(missing_ok=True)
    print(f"{time.strftime('%H:%M:%S')} start {job.name} on GPU {gpu}", flush=True)
    process = subprocess.Popen(
        ["bash", "-c", job.command],
        cwd=tree,
        env=job_environment(tree, gpu, threads, code_version, extra_env),
        stdout=log,
        stderr=subprocess.STDOUT,
        stdin=subprocess.DEVNULL,
        start_new_session=True,  # its own process group, which ``stop`` ends as a whole
    )
    (jobs_dir / f"{job.name}.pid").write_text(f"{process.pid}\n")
    return process


def run_queue(
    jobs: list[Job],
    source: Path,
    jobs_dir: Path,
    n_gpus: int,
    slots: int,
    threads: int,
    code_version: str | None = None,
    extra_env: dict[str, str] | None = None,
) -> int:
    """Run every job in a copy of ``source``, at most ``slots`` at once per GPU, each with
    ``MOSIV_CODE_VERSION=code_version`` where given and ``extra_env``; returns how many
    failed."""
    gpus = gpu_ids(max(n_gpus, 1))
    (jobs_dir / "queue.pid").write_text(f"{os.getpid()}\n")
    waiting = list(jobs)
    running: dict[str, tuple[str, subprocess.Popen]] = {}
    on_gpu = {gpu: 0 for gpu in gpus}
    failed = 0
    while waiting or running:
        for name, (gpu, process) in list(running.items()):
            code = process.poll()
            if code is None:
                continue
            stopped = (jobs_dir / f"{name}{STOPPED}").exists()
            (jobs_dir / f"{name}.rc").write_text("stopped\n" if stopped else f"{code}\n")
            (jobs_dir / f"{name}.pid").unlink(missing_ok=True)
            on_gpu[gpu] -= 1
            shutil.rmtree(jobs_dir / f"{name}.tree", ignore_errors=True)
            failed += code != 0 and not stopped
            outcome = "stopped" if stopped else f"exit {code}"
            print(f"{time.strftime('%H:%M:%S')} end {name}: {outcome}", flush=True)
            del running[name]
        while waiting:
            gpu = min(gpus, key=lambda g: on_gpu[g])
            if on_gpu[gpu] >= slots:
                break
            job = waiting.pop(0)
            if (jobs_dir / f"{job.name}{STOPPED}").exists():  # stopped before it started
                (jobs_dir / f"{job.name}.queued").unlink(missing_ok=True)
                (jobs_dir / f"{job.name}.rc").write_text("stopped\n")
                print(f"{time.strftime('%H:%M:%S')} skip {job.name}: stopped", flush=True)
                continue
            on_gpu[gpu] += 1
            process = launch(job, source, jobs_dir, gpu, threads, code_version, extra_env)
            running[job.name] = (gpu, process)
            if (jobs_dir / f"{job.name}{STOPPED}").exists():  # stopped while it was launched
                _end_groups({job.name: process.pid}, grace_seconds=10.0)
        time.sleep(POLL_SECONDS)
    return failed


def _signal(pid: int, sig: int, *, group: bool) -> bool:
    """Send ``sig`` to a process (or its process group); False where it is gone already."""
    try:
        (os.killpg if group else os.kill)(pid, sig)
    except ProcessLookupError:
        return False
    return True


def stop_jobs(jobs_dir: Path, names: list[str], grace_seconds: float = 10.0) -> list[str]:
    """End the named jobs only, and leave the queue running the others: a running one's
    process group ends (SIGTERM, then SIGKILL after ``grace_seconds``), a queued one never
    starts; the queue then writes ``NAME.rc`` "stopped". Returns the names that were running
    or queued."""
    known = {p.stem for p in jobs_dir.glob("*.log")} | {p.stem for p in jobs_dir.glob("*.queued")}
    unknown = sorted(set(names) - known)
    if unknown:
        raise SystemExit(
            f"stop --only: no job {', '.join(unknown)} in {jobs_dir} (jobs there: "
            f"{', '.join(sorted(known)) or 'none'})"
        )
    running, ended = {}, []
    for name in names:
        if (jobs_dir / f"{name}.rc").exists():
            continue  # ended already: its exit code stays
        (jobs_dir / f"{name}{STOPPED}").touch()  # the queue reads it before starting the job
        ended.append(name)
        try:  # the queue unlinks it when the job ends, maybe right now
            running[name] = int((jobs_dir / f"{name}.pid").read_text())
        except (FileNotFoundError, ValueError):
            pass  # not started yet: the queue reads the marker (before and after launching)
    _end_groups(running, grace_seconds)
    return sorted(ended)


def _end_groups(running: dict[str, int], grace_seconds: float) -> None:
    """SIGTERM each process group of ``running`` (name -> pid), SIGKILL what is left after
    ``grace_seconds``."""
    alive = {name: pid for name, pid in running.items() if _signal(pid, signal.SIGTERM, group=True)}
    deadline = time.time() + grace_seconds
    while alive and time.time() < deadline:
        time.sleep(0.2)
        alive = {name: pid for name, pid in alive.items() if _signal(pid, 0, group=True)}
    for pid in alive.values():
        _signal(pid, signal.SIGKILL, group=True)


def stop(jobs_dir: Path, grace_seconds: float = 10.0) -> list[str]:
    """End the queue recorded in ``jobs_dir`` and every job it started that is still running
    (SIGTERM, then SIGKILL after ``grace_seconds``); returns the names of the jobs stopped."""
    queue_pid = jobs_dir / "queue.pid"
    if queue_pid.exists():
        _signal(int(queue_pid.read_text()), signal.SIGKILL, group=False)  # starts nothing more
        queue_pid.unlink()
    running = {}
    for pid_file in sorted(jobs_dir.glob("*.pid")):
        name = pid_file.stem
        if not (jobs_dir / f"{name}.rc").exists():
            running[name] = int(pid_file.read_text())
        pid_file.unlink()
    _end_groups(running, grace_seconds)
    for name in running:
        (jobs_dir / f"{name}.rc").write_text("stopped\n")
        shutil.rmtree(jobs_dir / f"{name}.tree", ignore_errors=True)
    stop_mps(jobs_dir)
    return sorted(running)


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "verb",
        choices=["start", "run", "stop"],
        help="start: detach and run; run: run here; stop: end the queue and its running jobs",
    )
    parser.add_argument("jobfile", type=Path, nargs="?", help="the jobs (start and run)")
    parser.add_argument("--slots", type=int, default=3, help="jobs at once per GPU (default 3)")
    parser.add_argument("--gpus", type=int, default=None, help="GPUs to use (default: all seen)")
    parser.add_argument("--threads", type=int, default=None, help="CPU threads per job")
    parser.add_argument("--jobs-dir", type=Path, default=Path.home() / "jobs")
    parser.add_argument(
        "--only",
        default=None,
        help="with stop: end only these jobs (comma-separated names), running or queued, and "
        "leave the queue running the others (to let the rest finish inside a lease, say)",
    )
    parser.add_argument(
        "--mps",
        action="store_true",
        help="run the jobs under NVIDIA MPS, so that one GPU runs several jobs' kernels at "
        "once (the queue starts the daemon and quits it at its end)",
    )
    # start passes this to the detached queue: the daemon runs already
    parser.add_argument("--mps-started", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument(
        "--source", type=Path, default=None, help="the snapshot to start jobs from (default: now)"
    )
    parser.add_argument(
        "--code-version",
        default=None,
        help="the code version the jobs' rows name (default: $MOSIV_CODE_VERSION, else the "
        "checkout's commit; a device machine's copy has no git history: pass "
        "$(git rev-parse --short HEAD) from the machine that sent it)",
    )
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = _parser()
    args = parser.parse_args(argv)
    if args.verb == "stop" and args.only is not None:
        names = [n for n in args.only.split(",") if n]
        ended = stop_jobs(args.jobs_dir, names)
        print(f"stopped in {args.jobs_dir}: {', '.join(ended) or 'none (all had ended)'}")
        return 0
    if args.verb == "stop":
        stopped = stop(args.jobs_dir)
        print(f"stopped the queue in {args.jobs_dir}; jobs ended: {', '.join(stopped) or 'none'}")
        return 0
    if args.jobfile is None:
        parser.error(f"{args.verb} needs a JOBFILE")
    code_version = args.code_version or checkout_version()
    if args.slots < 1:
        parser.error(f"--slots {args.slots}: want at least 1 job per GPU")
    jobs = read_jobs(args.jobfile)
    n_gpus = args.gpus if args.gpus is not None else count_gpus()
    threads = args.threads or max(1, (os.cpu_count() or 1) // (max(n_gpus, 1) * args.slots))
    args.jobs_dir.mkdir(parents=True, exist_ok=True)
    clash = [j.name for j in jobs if (args.jobs_dir / f"{j.name}.log").exists()]
    if clash:
        parser.error(f"{args.jobs_dir} already has logs of {', '.join(clash)}: rename those jobs")
    mps = None  # the daemon starts before anything is queued, so a refusal leaves nothing
    if args.mps_started:
        mps = mps_environment(args.jobs_dir)
    elif args.mps:
        mps = start_mps(args.jobs_dir)
    for job in jobs:
        # a job of that name stopped before it ever started left a marker and an exit code
        for stale in (STOPPED, ".rc"):
            (args.jobs_dir / f"{job.name}{stale}").unlink(missing_ok=True)
        (args.jobs_dir / f"{job.name}.queued").write_text(job.command + "\n")
    source = args.source or take_snapshot(args.jobs_dir)
    if args.verb == "run":
        try:
            failed = run_queue(
                jobs, source, args.jobs_dir, n_gpus, args.slots, threads, code_version, mps
            )
        finally:
            if mps:
                stop_mps(args.jobs_dir)
        return min(failed, 1)
    # the detached queue reads its own copy of the job file, taken while this call holds the
    # checkout still
    jobfile = source.with_suffix(".jobs")
    shutil.copyfile(args.jobfile, jobfile)
    rest = [str(jobfile), "--slots", str(args.slots), "--gpus", str(n_gpus)]
    rest += ["--threads", str(threads), "--jobs-dir", str(args.jobs_dir), "--source", str(source)]
    rest += ["--code-version", code_version] if code_version else []
    rest += ["--mps-started"] if mps else []
    log = open(args.jobs_dir / "queue.out", "a")  # noqa: SIM115 (the detached queue holds it)
    subprocess.Popen(
        [sys.executable, __file__, "run", *rest],
        start_new_session=True,
        stdout=log,
        stderr=subprocess.STDOUT,
        stdin=subprocess.DEVNULL,
    )
    shared = " under MPS" if mps else ""
    print(
        f"queued {len(jobs)} jobs: {n_gpus} GPU(s) x {args.slots} slots, {threads} threads "
        f"each{shared}"
    )
    if not code_version:
        print(
            "warning: no code version known (no git history here): rows will name 'unknown'; "
            "pass --code-version"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
