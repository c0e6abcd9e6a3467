"""Throughput and memory benchmark of any registered simulator backend (``mosiv bench sim``).

The scene is a cube of elastic particles falling onto the ground inside a unit domain: the same
workload for every backend, so figures are comparable side by side. Throughput is reported in
particle-substeps per second (particles x substeps x frames / wall seconds), after one untimed
warm-up rollout of the same length that pays for kernel compilation: of the same length because
a backend may compile some kernels only when a rollout crosses a frame boundary (taichi-mpm's
state transfer between frames), which a one-frame warm-up left inside the timed rollout (0.45
s on an H200).

``run_batch_bench`` measures ``Simulator.rollout_batch``: B members (the same cube, stiffnesses
spread over a decade) in one batched call against the same B members rolled out one after the
other, in the same process, so both sides of the comparison come from one run.
"""

from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, field

import torch

from mosiv_framework.laws import get_law
from mosiv_framework.registry import get_registry
from mosiv_framework.types import ObjectParams, ParticleSet, SimulationParams, Trajectory, World


@dataclass
class BenchResult:
    backend: str
    device: str
    particles: int
    grid: int
    substeps: int
    frames: int
    forward_particle_substeps_per_s: float
    forward_backward_particle_substeps_per_s: float | None
    forward_s: float
    forward_backward_s: float | None
    peak_memory_bytes: int | None
    peak_memory_forward_backward_bytes: int | None
    #: centroid of the body after the timed forward rollout's last frame (m)
    final_centroid: list[float] | None = None

    def as_dict(self) -> dict:
        return asdict(self)


def bench_world() -> World:
    return World(
        (0.0, 0.0, 0.0), (1.0, 1.0, 1.0), gravity=(0.0, 0.0, -9.8), ground_height=0.02, fps=24.0
    )


def bench_particles(n: int, *, grid: int) -> ParticleSet:
    """About ``n`` particles on a lattice filling a cube centred in the domain.

    The cube's side grows with n so that there are about 8 particles per grid cell.
    """
    dx = 1.0 / grid
    side_count = max(2, round(n ** (1.0 / 3.0)))
    spacing = dx / 2.0
    side = min(side_count * spacing, 0.6)
    spacing = side / side_count
    ticks = (torch.arange(side_count, dtype=torch.float32) + 0.5) * spacing
    grid_pts = torch.stack(torch.meshgrid(ticks, ticks, ticks, indexing="ij"), dim=-1).reshape(
        -1, 3
    )
    origin = torch.tensor([0.5 - side / 2, 0.5 - side / 2, 0.1])
    positions = grid_pts + origin
    volumes = torch.full((positions.shape[0],), spacing**3)
    ids = torch.ones(positions.shape[0], dtype=torch.int64)
    return ParticleSet(positions, volumes, ids, {1: "elastic"})


def bench_params(device: torch.device, *, requires_grad: bool) -> SimulationParams:
    law = get_law("elastic")
    values = {
        name: torch.tensor(value, dtype=torch.float32, device=device, requires_grad=requires_grad)
        for name, value in law.defaults().items()
    }
    v0 = torch.tensor([0.3, 0.0, 0.0], device=device, requires_grad=requires_grad)
    gf = torch.tensor(0.3, device=device, requires_grad=requires_grad)
    return SimulationParams({1: ObjectParams("elastic", values)}, {1: v0}, gf)


@dataclass
class BatchBenchResult:
    backend: str
    device: str
    batch: int
    particles: int
    grid: int
    substeps: int
    frames: int
    batched_particle_substeps_per_s: float
    sequential_particle_substeps_per_s: float
    #: batched / sequential throughput (B would be perfect batching)
    gain: float
    batched_s: float
    sequential_s: float
    peak_memory_batched_bytes: int | None
    peak_memory_sequential_bytes: int | None
    #: the process's resident-memory high-water mark after each side (``peak_rss_bytes``)
    max_rss_after_sequential_bytes: int
    max_rss_after_batched_bytes: int
    #: the simulator options given beside device, grid and substeps
    options: dict = field(default_factory=dict)
    #: True: both sides timed forward plus backward (every member's parameters differentiable)
    gradients: bool = False

    def as_dict(self) -> dict:
        return asdict(self)


def batch_params(
    device: torch.device, batch: int, *, requires_grad: bool = False
) -> list[SimulationParams]:
    """B members: the bench parameters with E spread log-evenly over a decade around the
    default, as a global search over stiffness would try."""
    members = []
    for b in range(batch):
        params = bench_params(device, requires_grad=requires_grad)
        scale = 10.0 ** ((b / max(1, batch - 1)) - 0.5)
        # a leaf of its own: every timed call back-propagates into it again
        scaled = (params.objects[1].values["E"] * scale).detach()
        params.objects[1].values["E"] = scaled.requires_grad_(requires_grad)
        members.append(params)
    return members


def _max_rss_bytes() -> int:
    from mosiv_framework.pipeline.memory import peak_rss_bytes

    return peak_rss_bytes()


def run_batch_bench(
    *,
    backend: str,
    device: str,
    particles: int,
    grid: int,
    substeps: int,
    batch: int,
    frames: int = 2,
    options: dict | None = None,
    gradients: bool = False,
) -> BatchBenchResult:
    """Throughput of one ``rollout_batch`` of ``batch`` members and of the same members rolled
    out one by one (after an untimed warm-up of each): forward only, or with ``gradients``
    forward plus backward (the batch's members' losses summed and back-propagated once, each
    single rollout's on its own, as one iteration of B fits would). ``options``: further
    simulator options, for both sides (e.g. warp-mpm's grid_window)."""
    config = {"device": device, "grid": grid, "substeps": substeps, **(options or {})}
    simulator = get_registry().create("simulator", backend, config)
    torch_device = torch.device("cuda" if device == "cuda" else "cpu")
    world = bench_world()
    parts = bench_particles(particles, grid=grid).to(torch_device)
    members = batch_params(torch_device, batch, requires_grad=gradients)
    work = len(parts) * substeps * frames * batch

    def finish(out: list) -> None:
        bad = [r for r in out if not isinstance(r, Trajectory)]
        if bad:
            raise RuntimeError(f"{backend}: a benchmark member diverged: {bad[0]}")
        if gradients:
            sum(t.positions[-1].sum() for t in out).backward()

    def timed(call) -> tuple[float, int | None]:
        with torch.set_grad_enabled(gradients):
            call(frames)  # warm-up: compilation, buffers and graph capture are not timed
            simulator.reset_peak_memory()
            if torch_device.type == "cuda":
                torch.cuda.synchronize()
            t0 = time.perf_counter()
            call(frames)
            if torch_device.type == "cuda":
                torch.cuda.synchronize()
        return time.perf_counter() - t0, simulator.peak_memory_bytes()

    def one_by_one(n: int) -> None:
        for p in members:
            finish([simulator.rollout(parts, p, world=world, frames=n)])

    sequential_s, peak_seq = timed(one_by_one)
    rss_seq = _max_rss_bytes()
    batched_s, peak_batch = timed(
        lambda n: finish(simulator.rollout_batch(parts, members, world=world, frames=n))
    )
    return BatchBenchResult(
        backend=backend,
        device=device,
        batch=batch,
        particles=len(parts),
        grid=grid,
        substeps=substeps,
        frames=frames,
        batched_particle_substeps_per_s=work / batched_s,
        sequential_particle_substeps_per_s=work / sequential_s,
        gain=sequential_s / batched_s,
        batched_s=batched_s,
        sequential_s=sequential_s,
        peak_memory_batched_bytes=peak_batch,
        peak_memory_sequential_bytes=peak_seq,
        max_rss_after_sequential_bytes=rss_seq,
        max_rss_after_batched_bytes=_max_rss_bytes(),
        options=dict(options or {}),
        gradients=gradients,
    )


def run_bench(
    *,
    backend: str,
    device: str,
    particles: int,
    grid: int,
    substeps: int,
    frames: int = 2,
    backward: bool = True,
    options: dict | None = None,
) -> BenchResult:
    """Forward and, with ``backward``, forward plus backward throughput of one rollout of the
    bench cube; ``options``: further simulator options (e.g. warp-mpm's grid_window)."""
    config = {"device": device, "grid": grid, "substeps": substeps, **(options or {})}
    simulator = get_registry().create("simulator", backend, config)
    return measure(
        simulator,
        backend=backend,
        device=device,
        particles=particles,
        grid=grid,
        substeps=substeps,
        frames=frames,
        backward=backward,
    )


def measure(
    simulator,
    *,
    backend: str,
    device: str,
    particles: int,
    grid: int,
    substeps: int,
    frames: int = 2,
    backward: bool = True,
) -> BenchResult:
    """``run_bench`` on a simulator made already (made with that ``device``, ``grid`` and
    ``substeps``): timing it again re-uses its compiled kernels and buffers, as an
    identification's iterations do."""
    torch_device = torch.device("cuda" if device == "cuda" else "cpu")
    world = bench_world()
    parts = bench_particles(particles, grid=grid).to(torch_device)
    n = len(parts)

    def sync() -> None:
        if torch_device.type == "cuda":
            torch.cuda.synchronize()

    with torch.no_grad():  # warm-up: kernel compilation and graph capture are not timed
        simulator.rollout(
            parts, bench_params(torch_device, requires_grad=False), world=world, frames=frames
        )
    simulator.reset_peak_memory()
    sync()
    t0 = time.perf_counter()
    with torch.no_grad():
        forward = simulator.rollout(
            parts, bench_params(torch_device, requires_grad=False), world=world, frames=frames
        )
    sync()
    forward_s = time.perf_counter() - t0
    final_centroid = [float(c) for c in forward.positions[-1].double().mean(dim=0)]
    peak_forward = simulator.peak_memory_bytes()

    fb_s = fb_rate = peak_fb = None
    if backward:
        params = bench_params(torch_device, requires_grad=True)
        warm = simulator.rollout(parts, params, world=world, frames=frames)
        warm.positions[-1].sum().backward()
        simulator.reset_peak_memory()
        params = bench_params(torch_device, requires_grad=True)
        sync()
        t0 = time.perf_counter()
        traj = simulator.rollout(parts, params, world=world, frames=frames)
        traj.positions[-1].sum().backward()
        sync()
        fb_s = time.perf_counter() - t0
        fb_rate = n * substeps * frames / fb_s
        peak_fb = simulator.peak_memory_bytes()
        if not all(math.isfinite(float(t.grad.abs().sum())) for _, t in params.named_tensors()):
            raise RuntimeError(f"{backend}: non-finite gradients in the benchmark rollout")

    return BenchResult(
        backend=backend,
        device=device,
        particles=n,
        grid=grid,
        substeps=substeps,
        frames=frames,
        forward_particle_substeps_per_s=n * substeps * frames / forward_s,
        forward_backward_particle_substeps_per_s=fb_rate,
        forward_s=forward_s,
        forward_backward_s=fb_s,
        peak_memory_bytes=peak_forward,
        peak_memory_forward_backward_bytes=peak_fb,
        final_centroid=final_centroid,
    )
