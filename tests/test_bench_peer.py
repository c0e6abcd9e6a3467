"""``mosiv bench sim --peer NAME``: the workload a peer gets, how its timing is turned into
rates and ratios, and the errors for a peer that is unknown or not installed.

The peer here is a test plugin registered through the registry as any plugin would be; the
Genesis peer itself is tested in plugins/mosiv-genesis/tests/test_genesis_bench.py."""

from __future__ import annotations

import json
import math
import types

import pytest
import torch

import mosiv_framework.bench_peer as bench_peer
from mosiv_framework.bench import bench_particles, bench_world
from mosiv_framework.bench_peer import (
    PeerTiming,
    compare_with_peer,
    peer_workload,
    resolve_peer,
    run_peer_bench,
)
from mosiv_framework.cli.main import main
from mosiv_framework.errors import ConfigError, StageNotAvailable
from mosiv_framework.interfaces import BenchPeer
from mosiv_framework.registry import Component, Registry, hookimpl
from mosiv_framework.testing.pytest_plugin import require_simulator


def free_fall(x0: torch.Tensor, w, frames: int) -> torch.Tensor:
    """Positions after ``frames`` frames of free flight stepped as MPM steps them: n substeps
    of dt, gravity into the velocity, then the velocity into the position (semi-implicit
    Euler), so x_n = x0 + v t + g dt^2 n (n + 1) / 2."""
    n, dt = frames * w.substeps, w.substep_dt
    g = torch.tensor(w.gravity, dtype=torch.float64)
    v = torch.tensor(w.velocity, dtype=torch.float64)
    return x0.double() + v * n * dt + g * dt * dt * n * (n + 1) / 2


class BallisticPeer(BenchPeer):
    """A peer without a grid: every particle flies freely (no ground, no stress), which is
    what an elastic body does before it lands. It reports a fixed time so that the rates
    computed from it are known exactly."""

    seconds = 0.5

    def __init__(self, drop: int = 0) -> None:
        self.drop = drop  # particles it leaves out, to test the count check

    def measure(self, w):
        final = free_fall(w.positions, w, w.frames)
        return PeerTiming(
            forward_s=self.seconds,
            warmup_s=0.0,
            particles=w.particles - self.drop,
            final_positions=final[: w.particles - self.drop],
            notes=["ballistic"],
        )


def _registry_with(**peers) -> Registry:
    module = types.ModuleType("test_peers")

    def mosiv_bench_peers(register):
        for name, factory in peers.items():
            register(Component("bench_peer", name, factory=factory, description="test peer"))

    module.mosiv_bench_peers = hookimpl(mosiv_bench_peers)
    registry = Registry()
    registry.add_plugin(module, name="test-peers")
    return registry


@pytest.fixture
def ballistic(monkeypatch):
    registry = _registry_with(ballistic=BallisticPeer, short=lambda: BallisticPeer(drop=1))
    monkeypatch.setattr(bench_peer, "get_registry", lambda: registry)
    return registry


def test_workload_is_the_bench_run():
    w = peer_workload(device="cpu", particles=1000, grid=48, substeps=60, frames=4)
    parts = bench_particles(1000, grid=48)
    assert torch.equal(w.positions, parts.positions) and w.particles == 1000
    assert math.isclose(w.particle_volume, float(parts.volumes[0]), rel_tol=1e-7)
    assert math.isclose(w.spacing**3, w.particle_volume, rel_tol=1e-6)
    world = bench_world()
    assert w.domain_lower == world.domain_lower and w.ground_height == world.ground_height
    assert math.isclose(w.dx, 1.0 / 48) and math.isclose(w.substep_dt, 1.0 / (24.0 * 60))
    assert w.family == "elastic" and w.values["E"] == 5.0e4 and w.values["nu"] == 0.25
    assert w.values["rho"] == 1000.0 and w.velocity == pytest.approx((0.3, 0.0, 0.0))


def test_peer_rate_is_particle_substeps_over_its_seconds(ballistic):
    r = run_peer_bench(peer="ballistic", device="cpu", particles=64, grid=16, substeps=10, frames=3)
    assert r.particles == 64
    assert r.forward_particle_substeps_per_s == pytest.approx(64 * 10 * 3 / BallisticPeer.seconds)
    w = peer_workload(device="cpu", particles=64, grid=16, substeps=10, frames=3)
    t, n, dt = 3 / 24.0, 30, 1 / 240.0
    start = bench_particles(64, grid=16).positions.double().mean(0)
    drop = 9.8 * dt * dt * n * (n + 1) / 2  # 0.5 g t^2 (1 + 1/n)
    expected = start + torch.tensor([0.3 * t, 0.0, -drop], dtype=torch.float64)
    assert r.final_centroid == pytest.approx(expected.tolist(), abs=1e-6)
    assert free_fall(start[None], w, 3)[0].tolist() == pytest.approx(expected.tolist())


def test_a_peer_that_simulates_other_particles_is_refused(ballistic):
    with pytest.raises(RuntimeError, match="63 particles, not the workload's 64"):
        run_peer_bench(peer="short", device="cpu", particles=64, grid=16, substeps=10, frames=1)


def test_compare_refuses_different_workloads_and_divides_rates():
    ours = {"backend": "warp-mpm", "particles": 64, "grid": 16, "substeps": 10, "frames": 2,
            "device": "cpu", "forward_particle_substeps_per_s": 3.0e6,
            "final_centroid": [0.5, 0.5, 0.1]}  # fmt: skip
    peer = {**ours, "peer": "p", "forward_particle_substeps_per_s": 1.5e6,
            "final_centroid": [0.5, 0.5, 0.104]}  # fmt: skip
    c = compare_with_peer(ours, peer)
    assert c["forward_ratio"] == pytest.approx(2.0)
    assert c["centroid_distance_m"] == pytest.approx(0.004)
    with pytest.raises(ValueError, match="grid: 16 vs 32"):
        compare_with_peer(ours, {**peer, "grid": 32})


def test_unknown_peer_names_the_installed_and_known_ones(ballistic):
    with pytest.raises(ConfigError) as err:
        resolve_peer("nosuch")
    text = str(err.value)
    assert "'nosuch'" in text and "installed: ballistic, short" in text
    assert "genesis (pip install -e 'plugins/mosiv-genesis[engine]'" in text


def test_known_peer_without_its_plugin_says_what_to_install(ballistic):
    with pytest.raises(StageNotAvailable, match=r"genesis.*plugins/mosiv-genesis\[engine\]"):
        resolve_peer("genesis")


def test_cli_unknown_peer_fails_before_timing(capsys):
    # exit 2 at once: no MOSIV backend line is printed before the error
    assert main(["bench", "sim", "--peer", "nosuch", "--particles", "64", "--grid", "16"]) == 2
    captured = capsys.readouterr()
    assert "no bench peer of that name" in captured.err and "N=" not in captured.out


def test_cli_peer_with_batch_is_refused(capsys):
    assert main(["bench", "sim", "--peer", "genesis", "--batch", "2"]) == 2
    assert "does not combine with --batch" in capsys.readouterr().err


def test_cli_times_backend_and_peer_side_by_side(ballistic, capsys):
    """warp-mpm and the ballistic peer on the same 1-frame workload: before the body lands
    both follow free fall, so their final centroids agree; the ratio is the rates' quotient."""
    require_simulator("warp-mpm")
    argv = ["bench", "sim", "--backend", "warp-mpm", "--peer", "ballistic", "--particles", "64",
            "--grid", "16", "--substeps", "10", "--frames", "1", "--no-backward", "--json"]  # fmt: skip
    assert main(argv) == 0
    ours, peer = json.loads(capsys.readouterr().out)
    assert ours["backend"] == "warp-mpm" and peer["peer"] == "ballistic"
    versus = peer["versus"]["warp-mpm"]
    rate = ours["forward_particle_substeps_per_s"] / peer["forward_particle_substeps_per_s"]
    assert versus["forward_ratio"] == pytest.approx(rate)
    assert versus["centroid_distance_m"] < 5e-5

    assert main(argv[:-1]) == 0
    text = capsys.readouterr().out
    assert "ballistic (peer)" in text and "warm-up excluded" in text
    assert "warp-mpm / ballistic forward:" in text and "ballistic: ballistic" in text
