"""benchmarks/device_queue.py: at most --slots jobs per GPU, each on its own GPU id and thread
share, each in a snapshot of the checkout that later changes to the checkout do not reach."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
QUEUE = ROOT / "benchmarks" / "device_queue.py"
sys.path.insert(0, str(ROOT / "benchmarks"))

import device_queue  # noqa: E402


def _job(name: str, out: Path) -> str:
    # records its GPU, threads, working folder and start/end times, and that a module of the
    # checkout imports from its snapshot
    return (
        f'{name} python3 -c "import os, time, mosiv_framework as m; '
        f"t0 = time.time(); time.sleep(1.5); "
        f"open('{out}/{name}.txt', 'w').write(' '.join([os.environ['CUDA_VISIBLE_DEVICES'], "
        f"os.environ['OMP_NUM_THREADS'], os.getcwd(), m.__file__, str(t0), str(time.time())]))\""
    )


def test_queue_runs_each_job_in_a_snapshot_within_its_slots(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    jobs_dir = tmp_path / "jobs"
    jobfile = tmp_path / "jobs.txt"
    lines = ["# three jobs, two GPUs, one slot each", "", *(_job(f"j{i}", out) for i in range(3))]
    jobfile.write_text("\n".join(lines) + "\n")
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    env.pop("CUDA_VISIBLE_DEVICES", None)
    args = [sys.executable, str(QUEUE), "run", str(jobfile), "--gpus", "2", "--slots", "1"]
    args += ["--threads", "3", "--jobs-dir", str(jobs_dir)]
    subprocess.run(args, env=env, check=True, timeout=120)

    rows = {}
    for i in range(3):
        gpu, threads, cwd, module, t0, t1 = (out / f"j{i}.txt").read_text().split(" ")
        rows[i] = (gpu, float(t0), float(t1))
        assert threads == "3"
        assert cwd == str(jobs_dir / f"j{i}.tree")
        assert module.startswith(cwd + os.sep), "the job imported the checkout, not its snapshot"
        assert (jobs_dir / f"j{i}.rc").read_text().strip() == "0"
        assert not (jobs_dir / f"j{i}.queued").exists()
        assert not (jobs_dir / f"j{i}.tree").exists(), "snapshot left behind"
    assert {rows[0][0], rows[1][0]} == {"0", "1"}
    # one slot per GPU: the third job starts only after one of the first two has ended
    assert rows[2][1] >= min(rows[0][2], rows[1][2]) - 0.05
    # and never two jobs on one GPU at once
    for a in range(3):
        for b in range(a + 1, 3):
            if rows[a][0] == rows[b][0]:
                assert rows[a][2] <= rows[b][1] + 0.05 or rows[b][2] <= rows[a][1] + 0.05


def test_failed_job_leaves_its_exit_code_and_the_queue_goes_on(tmp_path):
    jobfile = tmp_path / "jobs.txt"
    jobfile.write_text("bad exit 3\ngood true\n")
    jobs_dir = tmp_path / "jobs"
    code = device_queue.main(
        ["run", str(jobfile), "--gpus", "1", "--slots", "1", "--jobs-dir", str(jobs_dir)]
    )
    assert code == 1
    assert (jobs_dir / "bad.rc").read_text().strip() == "3"
    assert (jobs_dir / "good.rc").read_text().strip() == "0"


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("alone\n", "'alone' has no command"),
        ("a/b true\n", "must be a plain file name"),
        ("x true\nx false\n", "'x' is used twice"),
    ],
)
def test_bad_job_file_is_named_with_its_line(tmp_path, text, message):
    jobfile = tmp_path / "jobs.txt"
    jobfile.write_text(text)
    with pytest.raises(ValueError, match=message) as error:
        device_queue.read_jobs(jobfile)
    assert str(jobfile) in str(error.value)


def test_a_job_whose_log_exists_is_refused(tmp_path, capsys):
    jobfile = tmp_path / "jobs.txt"
    jobfile.write_text("again true\n")
    jobs_dir = tmp_path / "jobs"
    jobs_dir.mkdir()
    (jobs_dir / "again.log").write_text("an earlier run\n")
    with pytest.raises(SystemExit):
        device_queue.main(["run", str(jobfile), "--gpus", "1", "--jobs-dir", str(jobs_dir)])
    assert "again" in capsys.readouterr().err
    assert (jobs_dir / "again.log").read_text() == "an earlier run\n"


def test_start_returns_at_once_and_the_detached_queue_runs_the_jobs(tmp_path):
    """``start`` snapshots the checkout and its job file, marks every job queued and returns;
    the queue it leaves behind runs them and records their exit codes."""
    import time

    jobfile = tmp_path / "jobs.txt"
    jobfile.write_text("first sleep 1\nsecond exit 4\n")
    jobs_dir = tmp_path / "jobs"
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    args = [sys.executable, str(QUEUE), "start", str(jobfile), "--gpus", "1", "--slots", "1"]
    started = subprocess.run(
        [*args, "--jobs-dir", str(jobs_dir)], env=env, capture_output=True, text=True, timeout=60
    )
    assert started.returncode == 0, started.stderr
    assert "queued 2 jobs" in started.stdout
    assert not (jobs_dir / "second.rc").exists()
    jobfile.unlink()  # the queue reads its own copy
    deadline = time.time() + 60
    while not (jobs_dir / "second.rc").exists() and time.time() < deadline:
        time.sleep(0.5)
    assert (jobs_dir / "first.rc").read_text().strip() == "0"
    assert (jobs_dir / "second.rc").read_text().strip() == "4"
    assert not list(jobs_dir.glob("*.queued"))
    snapshots = list(jobs_dir.glob("checkout-*"))
    assert any(s.is_dir() and (s / "benchmarks" / "device_queue.py").is_file() for s in snapshots)


def test_jobs_name_the_code_version_given_to_start(tmp_path):
    """A device machine's copy of the tree has no git history: the version given to ``start``
    reaches every job (``MOSIV_CODE_VERSION``, which result rows read), through the detached
    queue too; without one, the checkout's own commit is used where git knows it."""
    import time

    jobfile = tmp_path / "jobs.txt"
    jobfile.write_text(f"v bash -c 'echo $MOSIV_CODE_VERSION > {tmp_path}/v.txt'\n")
    jobs_dir = tmp_path / "jobs"
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    env.pop("MOSIV_CODE_VERSION", None)
    args = [sys.executable, str(QUEUE), "start", str(jobfile), "--gpus", "1"]
    args += ["--jobs-dir", str(jobs_dir), "--code-version", "abc1234"]
    subprocess.run(args, env=env, check=True, capture_output=True, timeout=60)
    deadline = time.time() + 60
    while not (jobs_dir / "v.rc").exists() and time.time() < deadline:
        time.sleep(0.5)
    assert (tmp_path / "v.txt").read_text().strip() == "abc1234"
    head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True)
    if head.returncode == 0:  # a checkout with its history (CI's is one)
        os.environ.pop("MOSIV_CODE_VERSION", None)
        assert device_queue.checkout_version() == head.stdout.decode().strip()


def test_wait_packs_logs_but_not_the_checkout_snapshots(tmp_path):
    jobs_dir = tmp_path / "jobs"
    (jobs_dir / "checkout-20260101-000000-1" / "big").mkdir(parents=True)
    (jobs_dir / "checkout-20260101-000000-1" / "big" / "file.py").write_text("x = 1\n")
    (jobs_dir / "a.tree").mkdir()
    (jobs_dir / "a.tree" / "file.py").write_text("x = 1\n")
    (jobs_dir / "a.log").write_text("done\n")
    (jobs_dir / "a.rc").write_text("0\n")
    out = tmp_path / "out"
    out.mkdir()
    env = dict(os.environ, DEVICE_JOBS_DIR=str(jobs_dir), OUT=str(out))
    script = ROOT / "benchmarks" / "device_batch.sh"
    subprocess.run(["bash", str(script), "wait", "5"], env=env, check=True, capture_output=True)
    names = subprocess.run(
        ["tar", "tzf", str(out / "batch.tgz")], capture_output=True, text=True, check=True
    ).stdout.split()
    assert any(n.endswith("jobs/a.log") for n in names)
    assert any(n.endswith("jobs/a.rc") for n in names)
    assert not [n for n in names if "checkout-" in n or ".tree" in n]


def _gone(pid: int) -> bool:
    """The process has ended (a zombie whose parent has not reaped it counts as ended)."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except FileNotFoundError:
        return True
    return stat.rsplit(")", 1)[1].split()[0] == "Z"


def _wait_for(predicate, seconds: float) -> bool:
    import time

    deadline = time.time() + seconds
    while not predicate() and time.time() < deadline:
        time.sleep(0.2)
    return predicate()


@pytest.mark.skipif(not Path("/proc").is_dir(), reason="reads process states from /proc")
def _start_with_a_child_job(tmp_path, more_jobs: str):
    """A detached queue (one slot) whose first job starts a child process and writes its pid
    to a marker, then ``more_jobs`` (job-file lines); returns (jobs folder, environment,
    marker) once the child runs."""
    jobfile = tmp_path / "jobs.txt"
    marker = tmp_path / "child.pid"
    jobfile.write_text(f"first sleep 120 & echo $! > {marker}; wait\n{more_jobs}")
    jobs_dir = tmp_path / "jobs"
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    args = [sys.executable, str(QUEUE), "start", str(jobfile), "--gpus", "1", "--slots", "1"]
    subprocess.run([*args, "--jobs-dir", str(jobs_dir)], env=env, check=True, timeout=60)
    assert _wait_for(lambda: marker.exists() and marker.read_text().strip(), 60)
    return jobs_dir, env, marker


def test_stop_ends_the_queue_and_its_running_jobs_but_not_the_caller(tmp_path):
    """``stop`` ends the detached queue (nothing more starts) and the running job's whole
    process group, marks the job stopped, and leaves the process that called it alone (a
    command-line match on the jobs' command would have matched the caller too)."""
    # the job's own child (sleep) must end with it: the job's process group is ended
    jobs_dir, env, marker = _start_with_a_child_job(tmp_path, "second sleep 120\n")
    queue_pid = int((jobs_dir / "queue.pid").read_text())
    job_pid = int((jobs_dir / "first.pid").read_text())
    child_pid = int(marker.read_text())

    stopped = subprocess.run(
        [sys.executable, str(QUEUE), "stop", "--jobs-dir", str(jobs_dir)],
        env=env, capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert stopped.returncode == 0, stopped.stderr
    assert "jobs ended: first" in stopped.stdout
    assert _wait_for(lambda: all(_gone(p) for p in (queue_pid, job_pid, child_pid)), 15)
    assert (jobs_dir / "first.rc").read_text().strip() == "stopped"
    assert not (jobs_dir / "first.tree").exists()
    assert not (jobs_dir / "queue.pid").exists() and not (jobs_dir / "first.pid").exists()
    # the queue is gone, so the second job never starts
    import time

    time.sleep(2 * device_queue.POLL_SECONDS)
    assert not (jobs_dir / "second.log").exists()
    # a second stop finds nothing to end
    again = subprocess.run(
        [sys.executable, str(QUEUE), "stop", "--jobs-dir", str(jobs_dir)],
        env=env, capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert "jobs ended: none" in again.stdout


def test_stop_only_ends_the_named_jobs_and_the_queue_runs_the_rest(tmp_path):
    """``stop --only`` ends a running job (its process group) and a queued one before it
    starts, marks both "stopped", and the queue goes on to run the job not named."""
    done = tmp_path / "third.done"
    jobs_dir, env, marker = _start_with_a_child_job(
        tmp_path, f"second sleep 120\nthird touch {done}\n"
    )
    job_pid = int((jobs_dir / "first.pid").read_text())
    child_pid = int(marker.read_text())
    queue_pid = int((jobs_dir / "queue.pid").read_text())

    stop = [sys.executable, str(QUEUE), "stop", "--jobs-dir", str(jobs_dir)]
    ended = subprocess.run(
        [*stop, "--only", "first,second"], env=env, capture_output=True, text=True, timeout=60
    )
    assert ended.returncode == 0, ended.stderr
    assert "stopped in" in ended.stdout and "first, second" in ended.stdout
    assert _wait_for(lambda: _gone(job_pid) and _gone(child_pid), 15)
    assert _wait_for(lambda: done.exists(), 60)  # the queue went on to the third job
    assert _wait_for(lambda: (jobs_dir / "third.rc").exists(), 30)
    assert (jobs_dir / "third.rc").read_text().strip() == "0"
    for name in ("first", "second"):
        assert (jobs_dir / f"{name}.rc").read_text().strip() == "stopped"
    assert not (jobs_dir / "second.log").exists()  # never started
    assert _wait_for(lambda: _gone(queue_pid), 30)  # and the queue ended with its last job
    unknown = subprocess.run(
        [*stop, "--only", "fourth"], env=env, capture_output=True, text=True, timeout=60
    )
    assert unknown.returncode != 0 and "no job fourth" in unknown.stderr
    # an empty list (an unset shell variable, say) ends nothing, and never the whole queue
    assert device_queue.main(["stop", "--only", "", "--jobs-dir", str(jobs_dir)]) == 0
    assert (jobs_dir / "third.rc").read_text().strip() == "0"


def test_start_without_a_job_file_is_refused(tmp_path, capsys):
    with pytest.raises(SystemExit):
        device_queue.main(["start", "--jobs-dir", str(tmp_path)])
    assert "start needs a JOBFILE" in capsys.readouterr().err


def _fake_mps_control(bin_dir: Path, log: Path) -> None:
    """An nvidia-cuda-mps-control stand-in that records each call: its arguments, the pipe
    folder it was given and, when called without arguments, the command read from stdin."""
    bin_dir.mkdir()
    program = bin_dir / device_queue.MPS_CONTROL
    program.write_text(
        "#!/usr/bin/env bash\n"
        'cmd=""; if [ $# -eq 0 ]; then read -r cmd; fi\n'
        f'echo "args=$* cmd=$cmd pipe=$CUDA_MPS_PIPE_DIRECTORY" >> {log}\n'
    )
    program.chmod(0o755)


def test_mps_queue_starts_the_daemon_gives_its_folders_to_the_jobs_and_quits_it(tmp_path):
    log, out, jobs_dir = tmp_path / "mps.log", tmp_path / "out", tmp_path / "jobs"
    out.mkdir()
    _fake_mps_control(tmp_path / "bin", log)
    jobfile = tmp_path / "jobs.txt"
    jobfile.write_text(
        "".join(f'j{i} echo "$CUDA_MPS_PIPE_DIRECTORY" > {out}/j{i}.txt\n' for i in range(2))
    )
    env = dict(os.environ, PYTHONPATH=str(ROOT), PATH=f"{tmp_path / 'bin'}:{os.environ['PATH']}")
    args = [sys.executable, str(QUEUE), "run", str(jobfile), "--gpus", "1", "--slots", "2"]
    args += ["--jobs-dir", str(jobs_dir), "--mps"]
    subprocess.run(args, env=env, check=True, timeout=120)

    pipe = str(jobs_dir / "mps" / "pipe")
    calls = log.read_text().splitlines()
    assert calls == [f"args=-d cmd= pipe={pipe}", f"args= cmd=quit pipe={pipe}"]
    for i in range(2):
        assert (out / f"j{i}.txt").read_text().strip() == pipe
    assert not Path(pipe).exists(), "the daemon's pipe folder outlived the queue"


def test_mps_without_the_control_program_is_refused_before_any_job(tmp_path):
    jobfile = tmp_path / "jobs.txt"
    jobfile.write_text(f"j0 touch {tmp_path}/ran\n")
    env = dict(os.environ, PYTHONPATH=str(ROOT), PATH=str(Path(sys.executable).parent))
    args = [sys.executable, str(QUEUE), "run", str(jobfile), "--gpus", "1", "--mps"]
    args += ["--jobs-dir", str(tmp_path / "jobs")]
    done = subprocess.run(args, env=env, capture_output=True, text=True, timeout=60)
    assert done.returncode != 0
    assert device_queue.MPS_CONTROL in done.stderr and "without --mps" in done.stderr
    assert not (tmp_path / "ran").exists()
