"""`mosiv bench sim --json` with taichi-mpm: stdout is JSON alone (no Taichi banner on it)."""

from __future__ import annotations

import json
import os
import subprocess
import sys


def test_bench_json_stdout_parses_with_taichi():
    env = {k: v for k, v in os.environ.items() if k != "ENABLE_TAICHI_HEADER_PRINT"}
    command = [sys.executable, "-c", "from mosiv_framework.cli.main import main; main()"]
    command += ["bench", "sim"]
    command += ["--backend", "taichi-mpm", "--device", "cpu", "--particles", "64"]
    command += ["--grid", "16", "--substeps", "2", "--frames", "1", "--no-backward", "--json"]
    done = subprocess.run(command, capture_output=True, text=True, env=env, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "[Taichi]" not in done.stdout
    report = json.loads(done.stdout)
    assert report, "the JSON report is empty"
