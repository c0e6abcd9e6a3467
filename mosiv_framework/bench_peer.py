"""Another simulator timed on the bench's workload, side by side (``mosiv bench sim --peer``).

A peer is a registered ``bench_peer`` component (interfaces.BenchPeer), provided by a plugin:
the core never imports the other engine. ``peer_workload`` describes the exact run the MOSIV
backends make in ``bench.run_bench``: the same particles (positions, volume), law parameters,
initial velocity, world (domain, gravity, ground, fps), grid resolution, substep count and
frames. The peer maps it onto its own options, times a forward rollout after an untimed warm-up
that pays for its kernel compilation, and reports its final positions, so the motions of both
sides can be compared as well as their speeds.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch

from mosiv_framework.bench import bench_params, bench_particles, bench_world
from mosiv_framework.errors import ConfigError, StageNotAvailable
from mosiv_framework.registry import get_registry

#: peers the project knows of -> what to install for them (a hint in the error message only)
KNOWN_PEERS: dict[str, str] = {
    "genesis": "pip install -e 'plugins/mosiv-genesis[engine]' (mosiv-genesis with genesis-world)",
}


@dataclass(frozen=True)
class PeerWorkload:
    """One bench run, in plain numbers a peer can map onto its own options.

    positions: [N, 3] float32 on the CPU (m); spacing: the particle lattice's spacing (m);
    particle_volume: each particle's volume (m^3); family: the constitutive law (the
    ``mosiv_framework.laws`` name); values: its parameters and the object's (E Pa, nu, rho
    kg/m^3, friction); velocity: the body's initial velocity (m/s); ground_friction: the
    ground's Coulomb coefficient; domain_lower/upper, gravity
    (m/s^2), ground_height (m, or None), fps: the bench World; grid: cells along the domain's
    longest side; substeps per frame; frames timed; device: "cpu" or "cuda".
    """

    positions: torch.Tensor
    spacing: float
    particle_volume: float
    family: str
    values: dict[str, float]
    velocity: tuple[float, float, float]
    ground_friction: float
    domain_lower: tuple[float, float, float]
    domain_upper: tuple[float, float, float]
    gravity: tuple[float, float, float]
    ground_height: float | None
    fps: float
    grid: int
    substeps: int
    frames: int
    device: str

    @property
    def extent(self) -> float:
        """The domain's longest side (m)."""
        return max(u - lo for lo, u in zip(self.domain_lower, self.domain_upper))

    @property
    def dx(self) -> float:
        """Grid cell size (m), as the MOSIV backends use it (MPMOptions.grid)."""
        return self.extent / self.grid

    @property
    def substep_dt(self) -> float:
        """One substep (s): 1 / (fps substeps)."""
        return 1.0 / (self.fps * self.substeps)

    @property
    def particles(self) -> int:
        return int(self.positions.shape[0])


@dataclass
class PeerTiming:
    """What a peer measured on one workload.

    forward_s: wall seconds of ``frames`` frames (every frame's positions read back, as a MOSIV
    rollout records them); warmup_s: the untimed warm-up (scene build, kernel compilation, one
    frame); particles: how many the peer simulated; final_positions: [N, 3] after the last frame
    (CPU); peak_memory_bytes and memory_note: a memory figure and what it counts, or None;
    gradients: what the peer's timing says about gradients (a line for the table); notes: other
    lines worth printing (the peer's own stability warnings, ...).
    """

    forward_s: float
    warmup_s: float
    particles: int
    final_positions: torch.Tensor
    peak_memory_bytes: int | None = None
    memory_note: str = ""
    gradients: str = "forward only"
    notes: list[str] = field(default_factory=list)


@dataclass
class PeerBenchResult:
    peer: str
    device: str
    particles: int
    grid: int
    substeps: int
    frames: int
    forward_particle_substeps_per_s: float
    forward_s: float
    warmup_s: float
    peak_memory_bytes: int | None
    memory_note: str
    gradients: str
    #: centroid of the body after the last frame (m): compare with a MOSIV backend's
    final_centroid: list[float]
    notes: list[str]

    def as_dict(self) -> dict:
        from dataclasses import asdict

        return asdict(self)


def peer_workload(
    *, device: str, particles: int, grid: int, substeps: int, frames: int
) -> PeerWorkload:
    """The workload ``bench.run_bench`` gives a MOSIV backend with the same arguments."""
    world = bench_world()
    parts = bench_particles(particles, grid=grid)
    params = bench_params(torch.device("cpu"), requires_grad=False)
    [obj] = params.objects.values()
    volumes = parts.volumes
    if not torch.allclose(volumes, volumes[0]):
        raise ValueError("the bench body's particles must share one volume")
    volume = float(volumes[0])
    [velocity] = params.initial_velocity.values()
    return PeerWorkload(
        positions=parts.positions.float().contiguous(),
        spacing=volume ** (1.0 / 3.0),
        particle_volume=volume,
        family=obj.family,
        values={k: float(v) for k, v in obj.values.items()},
        velocity=tuple(float(v) for v in velocity),
        ground_friction=float(params.ground_friction),
        domain_lower=tuple(world.domain_lower),
        domain_upper=tuple(world.domain_upper),
        gravity=tuple(world.gravity),
        ground_height=world.ground_height,
        fps=world.fps,
        grid=grid,
        substeps=substeps,
        frames=frames,
        device=device,
    )


def resolve_peer(name: str):
    """The registered bench peer ``name``, built; a clear error if it is unknown or its
    plugin is not installed (StageNotAvailable for a peer the project knows of)."""
    registry = get_registry()
    if name in registry.names("bench_peer"):
        return registry.create("bench_peer", name)
    if name in KNOWN_PEERS:
        raise StageNotAvailable(
            f"bench peer {name!r} is not installed: {KNOWN_PEERS[name]}" + _broken_suffix(registry)
        )
    valid = ", ".join(registry.names("bench_peer")) or "none installed"
    known = ", ".join(f"{k} ({v})" for k, v in KNOWN_PEERS.items())
    raise ConfigError(
        f"--peer {name!r}: no bench peer of that name; installed: {valid}; known: {known}"
        + _broken_suffix(registry)
    )


def _broken_suffix(registry) -> str:
    if not registry.broken:
        return ""
    return "; broken plugins: " + ", ".join(f"{b.name} ({b.error})" for b in registry.broken)


def run_peer_bench(
    *, peer: str, device: str, particles: int, grid: int, substeps: int, frames: int = 2
) -> PeerBenchResult:
    """Time ``peer`` on the bench workload (forward, after its own untimed warm-up)."""
    component = resolve_peer(peer)
    workload = peer_workload(
        device=device, particles=particles, grid=grid, substeps=substeps, frames=frames
    )
    timing = component.measure(workload)
    if timing.particles != workload.particles:
        raise RuntimeError(
            f"bench peer {peer!r} simulated {timing.particles} particles, not the workload's "
            f"{workload.particles}: the two sides would not be comparable"
        )
    final = timing.final_positions.detach().to("cpu", torch.float64)
    if not torch.isfinite(final).all():
        raise RuntimeError(f"bench peer {peer!r}: non-finite positions after the last frame")
    if not math.isfinite(timing.forward_s) or timing.forward_s <= 0.0:
        raise RuntimeError(f"bench peer {peer!r}: invalid forward time {timing.forward_s!r} s")
    return PeerBenchResult(
        peer=peer,
        device=device,
        particles=workload.particles,
        grid=grid,
        substeps=substeps,
        frames=frames,
        forward_particle_substeps_per_s=workload.particles * substeps * frames / timing.forward_s,
        forward_s=timing.forward_s,
        warmup_s=timing.warmup_s,
        peak_memory_bytes=timing.peak_memory_bytes,
        memory_note=timing.memory_note,
        gradients=timing.gradients,
        final_centroid=[float(c) for c in final.mean(dim=0)],
        notes=list(timing.notes),
    )


def compare_with_peer(ours: dict, peer: dict) -> dict:
    """A MOSIV bench result (``BenchResult.as_dict``) against a peer's on the same workload:
    forward_ratio (ours / peer particle-substeps per second; above 1 means ours is faster) and
    centroid_distance_m (how far apart the two bodies' centroids end, m)."""
    keys = ("particles", "grid", "substeps", "frames", "device")
    differ = [f"{k}: {ours[k]} vs {peer[k]}" for k in keys if ours[k] != peer[k]]
    if differ:
        raise ValueError(f"{ours['backend']} and {peer['peer']} ran different workloads: {differ}")
    a, b = ours.get("final_centroid"), peer["final_centroid"]
    distance = math.dist(a, b) if a is not None else float("nan")
    return {
        "forward_ratio": ours["forward_particle_substeps_per_s"]
        / peer["forward_particle_substeps_per_s"],
        "centroid_distance_m": distance,
    }
