"""The ``genesis`` bench peer (``mosiv bench sim --peer genesis``).

How MOSIV's bench workload maps onto Genesis' options (grid density and box, particle lattice
and size, time step, law) is plain Python and always tested. Timing Genesis needs the engine:
that test is marked ``genesis_engine`` and deselected, with the reason, without it
(conftest.py).
"""

from __future__ import annotations

import dataclasses
import math
import subprocess
import sys

import numpy as np
import pytest
import torch
from mosiv_genesis.bench import (
    GRADIENTS_NOTE,
    genesis_bench_settings,
    lattice_box,
    settings_notes,
)
from mosiv_genesis.source import MPM_BOUNDARY_CELLS

from mosiv_framework.bench_peer import peer_workload
from mosiv_framework.errors import ConfigError, StageNotAvailable
from mosiv_framework.registry import get_registry

SIZES = [(1000, 48, 60), (8000, 48, 60), (512, 32, 25), (3375, 64, 100)]


def genesis_regular_lattice(pos, size, p_size) -> np.ndarray:
    """Genesis' ``regular`` sampler on a Box (genesis/utils/particle.py, _box_to_particles):
    round(size / p_size) points per axis from lower + p/2 to upper - p/2."""
    pos, size = np.asarray(pos), np.asarray(size)
    lower, upper = pos - size / 2, pos + size / 2
    axes = [
        np.linspace(lower[i] + p_size / 2, upper[i] - p_size / 2, max(1, round(size[i] / p_size)))
        for i in range(3)
    ]
    return np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)


def _sorted_rows(a: np.ndarray) -> np.ndarray:
    return a[np.lexsort(a.T[::-1])]


@pytest.mark.parametrize("particles,grid,substeps", SIZES)
def test_settings_run_the_same_workload(particles, grid, substeps):
    w = peer_workload(device="cpu", particles=particles, grid=grid, substeps=substeps, frames=4)
    s = genesis_bench_settings(w)
    # the same cell and the same substep
    assert math.isclose(1.0 / s.grid_density, w.dx, rel_tol=1e-12)
    assert math.isclose(s.substep_dt, 1.0 / (24.0 * substeps), rel_tol=1e-12)
    assert s.substeps == substeps and s.gravity == (0.0, 0.0, -9.8)
    # Genesis' particle boundary is the domain, its floor the ground plane
    low, high = s.boundary
    assert np.allclose(low, [0.0, 0.0, 0.02]) and np.allclose(high, [1.0, 1.0, 1.0])
    # its grid: MOSIV's (grid + 2 x 3 padding cells) nodes per axis; the floor raised by the
    # ground height takes one node off z at these resolutions
    mosiv_nodes = grid + 2 * MPM_BOUNDARY_CELLS + 1
    assert s.grid_nodes[:2] == (mosiv_nodes, mosiv_nodes)
    assert mosiv_nodes - s.grid_nodes[2] == round(0.02 * grid)
    # Genesis' regular sampling of the Box is the bench body, and its particle volume too
    sampled = genesis_regular_lattice(s.box_pos, s.box_size, s.particle_size)
    ours = w.positions.numpy().astype(np.float64)
    assert sampled.shape == ours.shape
    assert np.abs(_sorted_rows(sampled) - _sorted_rows(ours)).max() < 1e-6
    assert math.isclose(s.particle_size**3, w.particle_volume, rel_tol=1e-6)
    assert s.material == {"E": 5.0e4, "nu": 0.25, "rho": 1000.0, "model": "neohooken",
                          "sampler": "regular"}  # fmt: skip
    assert s.velocity == pytest.approx((0.3, 0.0, 0.0))


def test_notes_flag_a_substep_above_genesis_hint_only_when_it_is():
    coarse = peer_workload(device="cpu", particles=512, grid=48, substeps=60, frames=1)
    fine = dataclasses.replace(coarse, substeps=120)  # dt 3.5e-4 s < 0.02 / 48 = 4.2e-4 s
    assert any("above Genesis' suggested" in n for n in settings_notes(
        genesis_bench_settings(coarse), coarse))  # fmt: skip
    assert not any("above Genesis' suggested" in n for n in settings_notes(
        genesis_bench_settings(fine), fine))  # fmt: skip


def test_lattice_box_refuses_a_body_that_is_not_a_full_lattice():
    w = peer_workload(device="cpu", particles=512, grid=32, substeps=10, frames=1)
    pos = w.positions.numpy().astype(np.float64)
    centre, size = lattice_box(pos, w.spacing)
    assert np.allclose(size, 8 * w.spacing) and np.allclose(centre, pos.mean(0))
    jittered = pos.copy()
    jittered[0] += 0.3 * w.spacing
    with pytest.raises(ConfigError, match="not a full lattice"):
        lattice_box(jittered, w.spacing)
    with pytest.raises(ConfigError, match="511 particles are not a full lattice"):
        lattice_box(pos[1:], w.spacing)


def test_what_genesis_cannot_match_is_refused_by_name():
    w = peer_workload(device="cpu", particles=512, grid=32, substeps=10, frames=1)
    with pytest.raises(ConfigError, match="law 'sand' is not mapped"):
        genesis_bench_settings(dataclasses.replace(w, family="sand"))
    with pytest.raises(ConfigError, match="particle volume"):
        genesis_bench_settings(dataclasses.replace(w, particle_volume=2 * w.particle_volume))
    sunk = w.positions - torch.tensor([0.0, 0.0, 0.1])  # below the ground at 0.02 m
    with pytest.raises(ConfigError, match="outside Genesis' MPM boundary"):
        genesis_bench_settings(dataclasses.replace(w, positions=sunk))


def test_peer_registers_without_importing_genesis():
    code = (
        "import sys\nfrom mosiv_framework.registry import get_registry\n"
        "peer = get_registry().create('bench_peer', 'genesis')\n"
        "print(type(peer).__name__, 'genesis' in sys.modules)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["GenesisPeer", "False"]
    assert get_registry().get("bench_peer", "genesis").distribution == "mosiv-genesis"


def test_missing_engine_says_what_to_install(monkeypatch):
    from mosiv_genesis import bench

    monkeypatch.setitem(sys.modules, "genesis", None)  # import genesis -> ImportError
    w = peer_workload(device="cpu", particles=64, grid=16, substeps=10, frames=1)
    with pytest.raises(StageNotAvailable, match=r"plugins/mosiv-genesis\[engine\]"):
        bench.GenesisPeer().measure(w)


@pytest.mark.genesis_engine
@pytest.mark.slow
def test_genesis_peer_times_the_bench_body_in_free_fall(capsys):
    """Two frames before the body lands: Genesis' centroid flies as n = 80 semi-implicit
    Euler substeps fly it, x0 + v t + g dt^2 n (n + 1) / 2 (0.4 mm below x0 + v t + g t^2 / 2),
    so positions, velocity, gravity, dt and substeps reached it as MOSIV's backends get them."""
    from mosiv_framework.bench_peer import run_peer_bench

    r = run_peer_bench(peer="genesis", device="cpu", particles=512, grid=32, substeps=40, frames=2)
    # Genesis warns about this dt (above its hint) on stderr: stdout stays the bench's table
    captured = capsys.readouterr()
    assert "substep_dt" in captured.err and "substep_dt" not in captured.out
    assert r.particles == 512 and r.forward_particle_substeps_per_s > 0 and r.warmup_s > 0
    assert r.gradients == "forward only" and GRADIENTS_NOTE in r.notes
    assert r.peak_memory_bytes is not None and r.peak_memory_bytes > 0
    w = peer_workload(device="cpu", particles=512, grid=32, substeps=40, frames=2)
    n, dt = 80, 1.0 / (24 * 40)
    start = w.positions.double().mean(0)
    drop = 9.8 * dt * dt * n * (n + 1) / 2
    expected = start + torch.tensor([0.3 * n * dt, 0.0, -drop], dtype=torch.float64)
    assert np.allclose(r.final_centroid, expected.numpy(), atol=2e-5)
