"""benchmarks/warp_profile.py --backward on the CPU at a tiny size: each adjoint kernel of a
substep is reported once per substep with a positive time, the phases and totals add up, the
implied rate follows from them, and the profiled phase-by-phase schedule gives the real
backward pass's gradients bit for bit (so the profile measures what rollouts run)."""

from __future__ import annotations

import json
import sys
from dataclasses import replace
from pathlib import Path

import pytest

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"
SUBSTEPS = 4


@pytest.fixture(scope="module")
def profile_module():
    pytest.importorskip("mosiv_warp_mpm")
    sys.path.insert(0, str(BENCHMARKS))
    try:
        import warp_profile
    finally:
        sys.path.remove(str(BENCHMARKS))
    return warp_profile


def test_backward_profile_reports_each_adjoint_kernel(profile_module, tmp_path, capsys):
    out = tmp_path / "profile.json"
    argv = ["--backward", "--device", "cpu", "--particles", "500", "--grid", "16"]
    argv += ["--substeps", str(SUBSTEPS), "--ablate-parameter-gradients", "--json", str(out)]
    p = profile_module.main(argv)
    text = capsys.readouterr().out

    assert p.mode == "backward" and p.timing == "cpu wall per launch group"
    assert "launch group's wall time" in text  # says that CPU rows are not per-kernel CUDA time
    rows = {(r.phase, r.name): r for r in p.rows}
    for kernel in profile_module.ADJOINT_KERNELS:
        row = rows[("adjoint", f"backward kernel {kernel}")]
        assert row.launches == SUBSTEPS and row.ms > 0, row
        assert f"backward kernel {kernel}" in text
    groups = {"load checkpoint": 1, "re-simulation": 1, "seed/finish copies": 2}
    groups |= {"zero gradients": SUBSTEPS, "taped replay": SUBSTEPS}
    # the particles' parameter copies: gathered once, their gradients summed per object once
    groups |= {"gather parameters": 1, "reduce parameter gradients": 1}
    for phase, launches in groups.items():
        row = rows[(phase, "all launches (wall)")]
        assert row.launches == launches and row.ms > 0, row
    assert {r.phase for r in p.rows} == set(groups) | {"adjoint"}

    # totals: the rows sum to the total, which on the CPU is the timed phases' wall
    assert p.total_ms == pytest.approx(sum(r.ms for r in p.rows), rel=1e-12)
    assert p.total_ms == pytest.approx(p.wall_ms, rel=1e-9)
    assert sum(p.phase_totals().values()) == pytest.approx(p.total_ms, rel=1e-12)
    assert [r.ms for r in p.rows] == sorted((r.ms for r in p.rows), reverse=True)
    work = p.particles * SUBSTEPS
    assert p.forward_ms > 0
    assert p.rate == pytest.approx(work / ((p.forward_ms + p.total_ms) / 1e3), rel=1e-12)
    assert p.graph_rate == pytest.approx(
        work / ((p.graph_forward_ms + p.graph_backward_ms) / 1e3), rel=1e-12
    )
    assert f"{p.rate:.3g} particle-substeps/s" in text
    assert p.memory["backward_workspace_bytes"] > 0

    assert p.gradient_check["bit_identical"], p.gradient_check

    # the per-kernel table puts each adjoint beside one forward pass of its kernel; on the CPU
    # the forward is one wall-timed group, so give it per-kernel rows as CUDA timing would
    assert "per kernel (ms)" in text
    Row = profile_module.Row
    ran = {k: profile_module.TAPED_AS.get(k, k) for k in profile_module.ADJOINT_KERNELS}
    forward = [Row("forward", f"forward kernel {k}", 1, 0.5) for k in ran.values()]
    table = profile_module.kernel_table(replace(p, forward_rows=forward)).splitlines()
    for kernel in profile_module.ADJOINT_KERNELS:
        line = next(ln for ln in table if f" {ran[kernel]} " in ln)
        adjoint = rows[("adjoint", f"backward kernel {kernel}")].ms
        assert line.split()[-1] == f"{adjoint / 0.5:.1f}", line
    ablated = {(r["phase"], r["name"]): r for r in p.ablation["rows"]}
    for kernel in profile_module.ADJOINT_KERNELS:
        assert ablated[("adjoint", f"backward kernel {kernel}")]["ms"] > 0
    assert p.ablation["total_ms"] == pytest.approx(sum(r["ms"] for r in p.ablation["rows"]))

    saved = json.loads(out.read_text())
    assert saved["total_ms"] == pytest.approx(sum(r["ms"] for r in saved["rows"]))
    assert len(saved["rows"]) == len(p.rows)


def test_profile_refuses_a_count_below_one(profile_module, capsys):
    with pytest.raises(SystemExit):
        profile_module.main(["--backward", "--device", "cpu", "--substeps", "0"])
    assert "--substeps must be at least 1, got 0" in capsys.readouterr().err


def test_the_profile_runs_each_grid_window(profile_module, tmp_path):
    """--grid-window: the profiled schedule through each window gives the real path's
    gradients bit for bit (its own check); an unknown window is refused."""
    for window in ("whole", "device"):
        argv = ["--backward", "--device", "cpu", "--particles", "200", "--grid", "16"]
        argv += ["--substeps", "4", "--grid-window", window]
        p = profile_module.main(argv)
        assert p.gradient_check["bit_identical"], (window, p.gradient_check)
    with pytest.raises(SystemExit):
        profile_module.main(["--grid-window", "box"])
