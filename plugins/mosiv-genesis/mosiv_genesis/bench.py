"""The ``genesis`` bench peer: Genesis' MPM timed on MOSIV's bench workload.

``mosiv bench sim --peer genesis`` gives it the run the MOSIV backends make (the core's
``bench_peer.PeerWorkload``); ``genesis_bench_settings`` maps it onto Genesis' options in plain
Python, so the mapping is tested without the engine:

- the same particles: a Box morph sampled with Genesis' ``regular`` sampler at the body's
  lattice spacing reproduces the body's lattice (and particle volume, which with rho sets
  Genesis' particle mass), and the workload's positions are then set explicitly;
- the same law: Genesis' Elastic with ``model="neohooken"`` has MOSIV's elastic Kirchhoff
  stress, mu (F F^T - I) + lambda ln(J) I, with the same E, nu and rho;
- the same grid: ``grid_density`` = grid / (the domain's longest side), so the cell is MOSIV's
  dx, over the domain grown by ``MPM_BOUNDARY_CELLS`` cells, which Genesis keeps as padding;
  its particle boundary is then the domain, with the floor at the world's ground height;
- the same time step: SimOptions dt = 1 / fps with the workload's substeps (dt = 1 / (fps S)),
  gravity, initial velocity and number of frames.

What is not the same: Genesis' floor is its MPM boundary, which stops the normal velocity
without friction, where MOSIV's ground applies Coulomb friction; the final centroids of both
sides say how much that moves the body.
"""

from __future__ import annotations

import contextlib
import os
import sys
import time
from dataclasses import dataclass

import numpy as np

from mosiv_framework.bench_peer import PeerTiming
from mosiv_framework.errors import ConfigError, StageNotAvailable
from mosiv_framework.interfaces import BenchPeer
from mosiv_genesis.source import MPM_BOUNDARY_CELLS, _genesis

#: Genesis' substep hint: it warns above dt = 0.02 s x (cell size in m) (its MPM solver)
GENESIS_DT_PER_DX = 2e-2
GRADIENTS_NOTE = (
    "forward only: Genesis' differentiable mode (requires_grad) is not timed; its material "
    "parameters (E, nu, rho) are constants of its compiled kernels, not inputs to differentiate"
)


@dataclass(frozen=True)
class GenesisBenchSettings:
    """Genesis options for one bench workload (see the module docstring).

    grid_density: cells per metre; lower_bound / upper_bound: the MPM box (m); particle_size:
    the lattice spacing (m); box_pos / box_size: the Box morph whose regular sampling is the
    body's lattice; frame_dt (s) and substeps: SimOptions; material: keyword arguments of
    gs.materials.MPM.Elastic; velocity: initial velocity (m/s); gravity (m/s^2).
    """

    grid_density: float
    lower_bound: tuple[float, float, float]
    upper_bound: tuple[float, float, float]
    particle_size: float
    box_pos: tuple[float, float, float]
    box_size: tuple[float, float, float]
    frame_dt: float
    substeps: int
    material: dict
    velocity: tuple[float, float, float]
    gravity: tuple[float, float, float]

    @property
    def substep_dt(self) -> float:
        return self.frame_dt / self.substeps

    @property
    def boundary(self) -> tuple[np.ndarray, np.ndarray]:
        """Where Genesis keeps the particles: the box shrunk by MPM_BOUNDARY_CELLS cells."""
        pad = MPM_BOUNDARY_CELLS / self.grid_density
        return np.array(self.lower_bound) + pad, np.array(self.upper_bound) - pad

    @property
    def grid_nodes(self) -> tuple[int, int, int]:
        """Genesis' grid nodes per axis (its MPMSolver rounds the box to whole cells)."""
        lo = np.round(self.grid_density * np.array(self.lower_bound)).astype(int)
        hi = np.round(self.grid_density * np.array(self.upper_bound)).astype(int)
        return tuple(int(n) for n in hi - lo + 1)


def lattice_box(positions: np.ndarray, spacing: float) -> tuple[np.ndarray, np.ndarray]:
    """(centre, size) of the axis-aligned box whose cells of side ``spacing`` are centred on
    ``positions`` [N, 3]; ConfigError unless the positions are that full lattice."""
    lo, hi = positions.min(axis=0), positions.max(axis=0)
    steps = (positions - lo) / spacing
    counts = np.rint((hi - lo) / spacing).astype(int) + 1
    off = float(np.abs(steps - np.rint(steps)).max()) if len(positions) else 0.0
    if off > 1e-3 or int(np.prod(counts)) != len(positions):
        raise ConfigError(
            f"bench peer genesis: the {len(positions)} particles are not a full lattice of "
            f"spacing {spacing:.4g} m ({'x'.join(map(str, counts))} sites, off by up to "
            f"{off:.2g} spacings); Genesis' regular sampler can only reproduce such a body"
        )
    size = counts * spacing
    return (lo + hi) / 2.0, size


def genesis_bench_settings(workload) -> GenesisBenchSettings:
    """Genesis options that run ``workload`` (a bench_peer.PeerWorkload); ConfigError naming
    what Genesis cannot match."""
    if workload.family != "elastic":
        raise ConfigError(
            f"bench peer genesis: law {workload.family!r} is not mapped; it times the bench "
            "body's law, elastic (Genesis' Elastic, neo-Hookean)"
        )
    if abs(workload.spacing**3 - workload.particle_volume) > 1e-6 * workload.particle_volume:
        raise ConfigError(
            f"bench peer genesis: particle volume {workload.particle_volume:.4g} m^3 is not the "
            f"lattice spacing cubed ({workload.spacing:.4g}^3); Genesis' particle mass is "
            "rho x particle_size^3"
        )
    density = workload.grid / workload.extent
    pad = MPM_BOUNDARY_CELLS / density
    lower = [lo - pad for lo in workload.domain_lower]
    if workload.ground_height is not None:
        lower[2] = workload.ground_height - pad
    upper = [u + pad for u in workload.domain_upper]
    positions = workload.positions.detach().cpu().numpy().astype(np.float64)
    centre, size = lattice_box(positions, workload.spacing)
    v = workload.values
    settings = GenesisBenchSettings(
        grid_density=density,
        lower_bound=tuple(lower),
        upper_bound=tuple(upper),
        particle_size=workload.spacing,
        box_pos=tuple(float(c) for c in centre),
        box_size=tuple(float(s) for s in size),
        frame_dt=1.0 / workload.fps,
        substeps=workload.substeps,
        material=dict(E=v["E"], nu=v["nu"], rho=v["rho"], model="neohooken", sampler="regular"),
        velocity=tuple(workload.velocity),
        gravity=tuple(workload.gravity),
    )
    low, high = settings.boundary
    if not (np.all(positions > low) and np.all(positions < high)):
        raise ConfigError(
            f"bench peer genesis: particles span {positions.min(0).round(4).tolist()}.."
            f"{positions.max(0).round(4).tolist()} m, outside Genesis' MPM boundary "
            f"{low.round(4).tolist()}..{high.round(4).tolist()} m (the domain, floor at the "
            "ground)"
        )
    return settings


def settings_notes(settings: GenesisBenchSettings, workload) -> list[str]:
    """Lines for the table: how Genesis' run differs from MOSIV's or what it warns about."""
    notes = [
        f"grid {'x'.join(map(str, settings.grid_nodes))} nodes at {1 / settings.grid_density:.4g}"
        f" m (MOSIV: dx {workload.dx:.4g} m); floor = MPM boundary at the ground, frictionless",
    ]
    hint = GENESIS_DT_PER_DX / settings.grid_density
    if settings.substep_dt > hint:
        notes.append(
            f"substep dt {settings.substep_dt:.3g} s is above Genesis' suggested "
            f"{GENESIS_DT_PER_DX} s/m x dx = {hint:.3g} s (the same dt as MOSIV's)"
        )
    return notes


class GenesisPeer(BenchPeer):
    """Times Genesis' MPM on a bench workload (forward only; see the module docstring)."""

    def measure(self, workload) -> PeerTiming:
        settings = genesis_bench_settings(workload)
        gs = _engine(workload.device)
        with _log_to_stderr(gs):
            return self._measure(gs, settings, workload)

    def _measure(self, gs, settings: GenesisBenchSettings, workload) -> PeerTiming:
        rss0 = _rss_bytes()
        t0 = time.perf_counter()
        scene, body = _build(gs, settings)
        try:
            _place(body, workload)
            scene.step()  # warm-up: compiles (or loads) the step and read-back kernels
            body.get_particles_pos()
            warmup_s = time.perf_counter() - t0
            scene.reset()
            _place(body, workload)
            _sync(gs)
            t0 = time.perf_counter()
            frames = []
            for _ in range(workload.frames):
                scene.step()
                frames.append(body.get_particles_pos())  # as a MOSIV rollout records each frame
            final = frames[-1].detach().cpu().reshape(-1, 3)
            _sync(gs)
            forward_s = time.perf_counter() - t0
            rss1 = _rss_bytes()
            particles = int(body.n_particles)
        finally:
            scene.destroy()
        cpu = workload.device == "cpu"
        return PeerTiming(
            forward_s=forward_s,
            warmup_s=warmup_s,
            particles=particles,
            final_positions=final,
            peak_memory_bytes=(rss1 - rss0) if cpu and rss0 is not None else None,
            memory_note="resident memory the scene added (the first scene of a process also "
            "loads Genesis' kernels)"
            if cpu
            else "Genesis' GPU memory pool is not reported",
            gradients="forward only",
            notes=[GRADIENTS_NOTE, *settings_notes(settings, workload)],
        )


@contextlib.contextmanager
def _log_to_stderr(gs):
    """Genesis logs to stdout; while it runs, its lines go to stderr, so that the bench's
    stdout stays its table or JSON."""
    handler = gs.logger.handler
    previous = handler.setStream(sys.stderr)
    try:
        yield
    finally:
        handler.setStream(previous)


def _engine(device: str):
    """Genesis initialised on ``device``'s backend; StageNotAvailable if it is not installed
    or cannot run there, ConfigError if this process already runs it on another backend."""
    try:
        import genesis  # noqa: F401
    except ImportError as exc:
        raise StageNotAvailable(
            "bench peer 'genesis' needs the Genesis engine: pip install -e "
            f"'plugins/mosiv-genesis[engine]' (genesis-world); import failed: {exc}"
        ) from exc
    import genesis as gs

    was_initialised = getattr(gs, "_initialized", False)
    gs = _genesis("gpu" if device == "cuda" else "cpu")
    want = gs.cuda if device == "cuda" else gs.cpu
    if gs.backend != want:
        if was_initialised:
            raise ConfigError(
                f"bench peer genesis: Genesis already runs on {gs.backend} in this process and "
                f"cannot be started again on {device}; time {device} in its own process"
            )
        raise StageNotAvailable(
            f"bench peer genesis: Genesis found no CUDA device (it started on {gs.backend}); "
            "use --device cpu or a machine whose Genesis sees the GPU"
        )
    return gs


def _build(gs, s: GenesisBenchSettings):
    """The Genesis scene with one elastic Box body; returns (scene, body)."""
    scene = gs.Scene(
        sim_options=gs.options.SimOptions(dt=s.frame_dt, substeps=s.substeps, gravity=s.gravity),
        mpm_options=gs.options.MPMOptions(
            lower_bound=s.lower_bound,
            upper_bound=s.upper_bound,
            grid_density=s.grid_density,
            particle_size=s.particle_size,
        ),
        show_viewer=False,
    )
    body = scene.add_entity(
        material=gs.materials.MPM.Elastic(**s.material),
        morph=gs.morphs.Box(pos=s.box_pos, size=s.box_size),
        # particles drawn as points: no mesh skinning, which the bench would otherwise time
        surface=gs.surfaces.Default(vis_mode="particle"),
    )
    scene.build()
    return scene, body


def _place(body, workload) -> None:
    """The workload's exact positions and initial velocity on ``body``."""
    n = int(body.n_particles)
    if n != workload.particles:
        raise RuntimeError(
            f"bench peer genesis: Genesis sampled {n} particles for the body, the workload has "
            f"{workload.particles}; the lattice mapping (lattice_box) is off"
        )
    body.set_position(workload.positions.numpy().astype(np.float32))
    velocity = np.broadcast_to(np.asarray(workload.velocity, dtype=np.float32), (n, 3))
    body.set_velocity(np.ascontiguousarray(velocity))


def _sync(gs) -> None:
    """Wait for Genesis' kernels (its runtime, ``gs.qd``, queues them on the GPU)."""
    runtime = getattr(gs, "qd", None)
    if runtime is not None:
        runtime.sync()


def _rss_bytes() -> int | None:
    """The process's resident memory now (Linux /proc), or None elsewhere."""
    if not sys.platform.startswith("linux"):
        return None
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
