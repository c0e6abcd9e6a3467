"""Per-kernel time of one warp-mpm frame on the `mosiv bench sim` workload, forward or backward.

Usage (GPU machine):
    python benchmarks/warp_profile.py [--particles 1000000] [--grid 128] [--substeps 50]
    python benchmarks/warp_profile.py --backward [--ablate-parameter-gradients] [--json OUT]
    python benchmarks/warp_profile.py --backward --table-reads   # the adjoint before the copies
    python benchmarks/warp_profile.py --backward --unrolled-scatter-adjoint   # p2g's own adjoint
    python benchmarks/warp_profile.py --backward --family plasticine   # a law with an SVD

Forward: the summed CUDA time of each kernel over one frame (no graph capture, so Warp can
time every launch). Backward: one frame's adjoint as autograd.WarpRollout.backward runs it for
a one-frame rollout -- copy each particle's parameters and each grid node's coefficients
(once per rollout), load the frame's checkpoint, re-simulate the frame keeping every
substep's state, then per substep in reverse: zero the gradients, replay the substep under a
Warp tape, run the tape's adjoint kernels; then sum the per-particle parameter gradients per
object and the per-node ones per member and field (once per frame, torch, timed by its wall
clock) -- each phase timed on its own, summed per (phase, kernel) with launch counts, sorted,
with each row's share of the backward total. Beside it: the forward frame, the implied
particle-substeps/s of forward + backward, the same frame through the captured CUDA graphs that
rollouts replay, peak GPU memory, and a check that the profiled schedule gives the real path's
gradients. Timing is Warp's: ScopedTimer with cuda_filter=TIMING_ALL (kernels, memsets, copies)
on CUDA; on the CPU Warp has no per-kernel timing, so each phase is one launch group timed by
its wall clock, and the adjoint is timed per recorded launch.

Where the forward + backward time goes: suspects read off autograd.py, simulator.py and
kernels.py, for this profile to confirm or refute. Reference (docs/BENCHMARKS.md, H200, 1M
particles, grid 128, 50 substeps): forward 1.26e9 particle-substeps/s (40 ms a frame), forward +
backward 4.05e7 (2.47 s for 2 frames), so the backward takes about 1.2 s a frame, 24 ms a
substep, some 30 forward substeps' worth. Per substep it runs the forward twice more (the
re-simulation and the taped replay), zeroes gradients, and launches four adjoint kernels.

1. Contended atomics on the parameter adjoints. In Warp the adjoint of an array read a[i] is
   atomic_add(adj_a[i], ...) (native/array.h, adj_address), issued by every thread even when
   the value is zero. p2g read params[o] (5 floats), rho[o] and damping[b] in every particle
   thread and g2p read params[o] again: 12 atomic adds per particle and substep onto 7
   addresses (one object in the bench), 12 M same-address atomics a substep at 1M particles,
   which the L2 serialises, summed in float32 in schedule order. Confirmed by this profile on
   an H100: the adjoint p2g and g2p rows dwarfed their forward rows, and the profiled
   schedule's parameter gradients differed from the real path's far beyond round-off. Fixed:
   the taped p2g and g2p read each particle's own copy of its object's values
   (state.ParticleParams, 56 bytes a particle; kernels.parameter_rows), copied once per
   rollout (the "gather parameters" row), so their adjoints add into one address per
   particle; after each frame the per-particle gradients are summed per object in float64
   (torch, in a fixed order: the "reduce parameter gradients" row). Forward rollouts read the
   tables as before (the same kernels, per_particle = 0). The grid: measured on an H100 (1M
   particles, grid 128), the adjoint grid_free_velocity took 44.4 ms a frame, 7.1 without
   parameter gradients: every node with mass read its member's accel (vec3), two drag
   coefficients and the expression switch, some 6 float32 atomics per node onto 6 addresses.
   Fixed the same way: the taped grid_free_velocity reads each node's copy of accel and drag
   (state.NodeCoefficients, 40 bytes a node, 98 MB at grid 128; per_node = 1), gathered with
   the particles' copies, its gradients summed per member in float64 in the reduce row; the
   switch (only compared, so no gradient) from a copy without a gradient, which Warp's adjoint
   skips, as do the taped field_moments and other_centres. Measured on an H200: 43.3 -> 7.2
   ms a frame. The adjoint grid_boundaries (21 ms a frame on an H200, 7.7x its forward) read
   friction in every node with mass (field_sums' hand-written adjoint adds m times its zero
   adjoint there even where no two fields meet) and the ground friction and restitution on
   every ground-layer node with mass, from the tables. Fixed the same way: the taped
   grid_boundaries reads each node's copy of its object's friction (8 more bytes a node) and
   each ground-layer node's of the ground coefficients (16 bytes a node of the layers at or
   below the ground, per member: 1.7 MB at grid 128), summed in the reduce row. Measured on
   an H200: 21.1 -> 6.0 ms a frame. Not fixed: the expression's coefficients (when the term is on) are still
   read per node from the tables, their adjoints float32 atomics onto a few addresses.
   --table-reads profiles the taped kernels reading the tables, as before the copies
   (particles' and nodes'), for comparison. --ablate-parameter-gradients removes every
   parameter gradient (the copies' and the tables', friction's excepted), so Warp skips those
   atomics: what it recovers is what the parameter adjoints still cost.
2. Recomputation. Every substep's forward runs three times (rollout, re-simulation, taped
   replay) and each Warp adjoint kernel replays its forward body before its reverse sweep. That
   bounds it at a few forward substeps (about 2.5 ms of the 24): the re-simulation and replay
   rows measure it. The replay's G2P only recomputed what the re-simulation had already
   written into work[s + 1] (G2P's adjoint reads its inputs, not its outputs): MPMRun.record_g2p
   now puts it on the tape without running it, so the replay row is the grid update alone.
3. Adjoint scatter. The adjoint g2p atomically adds 27 vec3 per particle into grid_v's gradient
   (the forward P2G's pattern, 20 ms a frame in the forward profile): one distinct node per
   read, inherent to the scatter. Each read of a particle array in p2g used to become an atomic
   into its gradient (C[p] three times plus once per ground-layer node, F and the volume twice;
   x two or three times in g2p). Fixed: p2g and g2p read each particle array once per thread
   into a local (kernels.py, module docstring), so the adjoint sums each particle's uses in
   registers and adds once per array; the forward is the same arithmetic (bit for bit on the
   CPU), the gradients equal the previous kernels' to float32 round-off (F's gradient
   regrouped: tests/test_transfer_reads.py in the plugin). Not yet measured on a GPU; what is
   left of the adjoint rows after the ablation is the grid scatter and gather themselves.
4. SVD adjoint. Not on the bench workload: elastic is neo-Hookean (no SVD) with an identity
   return map. Plasticine, sand, non_newtonian and snow go through svd.proper_svd and its
   hand-written adjoint: --family measures them.
5. Per-substep tape overhead. Tape recording (Python, a stack inspection per launch) is paid
   only by this profiler's uncaptured launches; rollouts replay one captured graph per frame.
   The report puts the graph's wall per frame beside the kernel sum: what separates them is
   idle time inside the graph, not Python.
6. Memory traffic of the saved states and the zeroing. Per reverse substep: 5 particle gradient
   arrays (about 100 bytes a particle) and, on CUDA, 6 whole-grid gradient arrays and 4 value
   arrays (2.46 M nodes at grid 128): about 0.35 GB in all, some 0.15 ms of the 24 at H100
   bandwidth: the memset and memcpy rows. The 51 saved states (values and gradients, about 10 GB
   at 1M particles) cost memory, not time.
7. Register pressure of the adjoint kernels. P2G carried the law's stress and G2P its return
   map, switches over every law with SVD adjoints in several branches, and Warp's adjoint of
   the unrolled 27-node loops holds every node's values at once. Confirmed on an H200: the
   taped replay now runs the transfers split (transfer_kernels.py: a stress kernel and a
   deformation update per law beside a lean scatter and gather) and tapes the scatter as a
   loop (p2g_looped, whose adjoint replays one node at a time); the adjoint scatter went from
   73 to 21 ms a frame at 1M particles, the gather's from 34 to 21 (docs/BENCHMARKS.md).
   --unrolled-scatter-adjoint tapes the unrolled scatter instead, for comparison.
"""

from __future__ import annotations

import argparse
import json
import re
import time
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field

import torch
import warp as wp
from mosiv_warp_mpm.packing import pack_theta
from mosiv_warp_mpm.run import MPMRun
from mosiv_warp_mpm.simulator import init_warp, use_deterministic_atomics
from mosiv_warp_mpm.state import GridLayout, ParticleState
from warp_profile_report import TAPED_AS, ablation_report, kernel_table, report  # noqa: F401

from mosiv_framework.bench import bench_params, bench_particles, bench_world
from mosiv_framework.laws import FAMILIES, get_law
from mosiv_framework.types import ObjectParams, SimulationParams

#: the adjoint kernels of every substep of the default (elastic) workload: the stress and
#: deformation kernels are made per law, the scatter is taped as p2g_looped (the expression
#: term's field sums join them with several fields on CUDA)
ADJOINT_KERNELS = (
    "particle_stress_elastic",
    "p2g_looped",
    "grid_free_velocity",
    "grid_boundaries",
    "g2p",
    "update_deformation_elastic",
)

_HASH = re.compile(r"_[0-9a-f]{8}$")  # Warp's module-hash suffix of a kernel's name


@dataclass
class Row:
    """Timed activity of one name within one phase of the profiled frame."""

    phase: str
    name: str
    launches: int
    ms: float


@dataclass
class Profile:
    """What one run of this script measured (times in ms, rates in particle-substeps/s)."""

    mode: str  # "forward" or "backward"
    device: str
    timing: str  # "cuda activity" or "cpu wall per launch group"
    particles: int
    grid: int
    substeps: int
    family: str
    order: str
    parameter_reads: str  # the taped kernels read the particles' "copies" or the "tables"
    scatter_adjoint: str  # the replay's scatter taped "looped" (p2g_looped) or "unrolled"
    rows: list[Row]
    total_ms: float  # sum of the rows
    wall_ms: float  # wall of the timed phases (uncaptured launches, each phase synchronised)
    forward_ms: float  # the forward frame's activity sum (backward mode: as the forward mode)
    rate: float  # particle-substeps/s implied by the sums (forward + backward in backward mode)
    graph_forward_ms: float | None = None  # the real path's frame, CUDA graph on GPUs
    graph_backward_ms: float | None = None
    graph_rate: float | None = None
    memory: dict = field(default_factory=dict)
    gradient_check: dict = field(default_factory=dict)
    ablation: dict | None = None
    forward_rows: list[Row] = field(default_factory=list)  # backward mode: the forward frame's

    def phase_totals(self) -> dict[str, float]:
        out: dict[str, float] = {}
        for r in self.rows:
            out[r.phase] = out.get(r.phase, 0.0) + r.ms
        return out


class Recorder:
    """Sums timed activity per (phase, name) with Warp's ScopedTimer: on CUDA every kernel,
    memset and copy inside a phase (cuda_filter=TIMING_ALL); on the CPU, where Warp has no
    per-kernel timing, the phase's wall clock as one launch group named by the caller."""

    def __init__(self, cuda: bool):
        self.cuda = cuda
        self.sums: dict[tuple[str, str], list] = {}
        self.wall_ms = 0.0

    def add(self, phase: str, name: str, ms: float) -> None:
        entry = self.sums.setdefault((phase, name), [0, 0.0])
        entry[0] += 1
        entry[1] += ms

    @contextmanager
    def phase(self, phase: str, group: str = "all launches (wall)", *, wall: bool = False):
        """Time what runs inside as ``phase``; ``wall``: as one row of its wall clock on CUDA
        too (work Warp does not see, such as torch's)."""
        flt = wp.TIMING_ALL if self.cuda and not wall else 0
        with wp.ScopedTimer(phase, print=False, synchronize=True, cuda_filter=flt) as timer:
            if wall and self.cuda:
                torch.cuda.synchronize()
            yield
            if wall and self.cuda:
                torch.cuda.synchronize()
        self.wall_ms += timer.elapsed
        if not self.cuda or wall:
            self.add(phase, group, timer.elapsed)
            return
        for r in timer.timing_results:
            self.add(phase, _HASH.sub("", r.name), r.elapsed)

    def rows(self) -> list[Row]:
        rows = [Row(p, n, c, ms) for (p, n), (c, ms) in self.sums.items()]
        return sorted(rows, key=lambda r: -r.ms)


@dataclass
class Setup:
    run: MPMRun
    x0: torch.Tensor
    v0: torch.Tensor
    theta: torch.Tensor


def family_params(family: str, device) -> SimulationParams:
    """The bench's parameters (elastic defaults, v0, ground friction) with ``family``'s law."""
    base = bench_params(device, requires_grad=False)
    values = {
        name: torch.tensor(value, dtype=torch.float32, device=device)
        for name, value in get_law(family).defaults().items()
    }
    return SimulationParams(
        {1: ObjectParams(family, values)}, base.initial_velocity, base.ground_friction
    )


def build(args) -> Setup:
    """The bench workload's particles in the chosen order, loaded into a fresh MPMRun."""
    device = args.device
    dev = wp.device_to_torch(device)
    world = bench_world()
    particles = bench_particles(args.particles, grid=args.grid)
    layout = GridLayout.for_world(world, grid=args.grid, fields=1)
    x0 = particles.positions.to(dev)
    if args.order == "scatter":
        order = layout.scatter_order(x0)
    elif args.order == "cell":
        order = torch.argsort(layout.cell_keys(x0))
    elif args.order == "random":
        order = torch.randperm(x0.shape[0], device=dev)
    else:
        order = torch.arange(x0.shape[0], device=dev)
    n = x0.shape[0]
    run = MPMRun(
        layout=layout,
        world=world,
        substeps=args.substeps,
        device=device,
        object_ids=[1],
        families=[args.family],
        obj_index=torch.zeros(n, dtype=torch.int64, device=dev),
        volumes=particles.volumes.to(dev)[order],
        window=args.grid_window,
    )
    if args.backward:
        ws = run.backward_workspace()
        ws.gather_parameters = not args.table_reads
        ws.looped_scatter_adjoint = not args.unrolled_scatter_adjoint
    params = family_params(args.family, dev)
    theta = pack_theta(params, [1], world.gravity, dev)
    v0 = params.initial_velocity[1].expand(n, 3).contiguous()
    return Setup(run, x0[order].contiguous(), v0, theta)


def start_state(setup: Setup, frame: int) -> ParticleState:
    """The state at the start of ``frame`` (1-based): the initial state advanced frame - 1
    frames, copied into a checkpoint as a differentiable rollout keeps it."""
    run = setup.run
    run.tables.load(setup.theta)
    run.a.set_initial(setup.x0, setup.v0)
    for f in range(1, frame):
        run.advance_frame(f)
    ckpt = ParticleState(run.n, run.device)
    ckpt.copy_from(run.a)
    return ckpt


def time_forward(setup: Setup, rec: Recorder, start: ParticleState, frame: int) -> None:
    """One frame's forward launches from ``start``, uncaptured, as phase "forward"."""
    run = setup.run
    run.a.copy_from(start)
    run.begin_frame(frame, run.grid)
    with rec.phase("forward"):
        run._frame_launches()


def seed_loss(run: MPMRun) -> None:
    """d(loss)/d(end state) of the bench's loss (sum of the last frame's positions): 1 on x."""
    ws = run.backward_workspace()
    run.tables.zero_grad()
    ws.carry.zero_grad()
    ws.carry.x.grad.fill_(1.0)


def profiled_adjoint(
    run: MPMRun, rec: Recorder, start: ParticleState, frame: int, *, parameters: bool = True
) -> None:
    """A one-frame rollout's backward (autograd.WarpRollout.backward, its frame's
    BackwardWorkspace._launches) phase by phase, each under the recorder (the profile's check
    compares its gradients with the real path's). ``parameters``: copy the particles'
    parameters and the nodes' coefficients before and sum their gradients after (off: the
    ablation, which copied them)."""
    ws = run.backward_workspace()
    if parameters:
        with rec.phase("gather parameters"):
            ws.begin_parameters(run)
    with rec.phase("load checkpoint"):
        ws.work[0].copy_from(start)
        run.begin_frame(frame, ws.grid)
    with rec.phase("re-simulation"):
        windows = ws.resimulate(run)
    with rec.phase("seed/finish copies"):
        ws.seed()
    for s in range(run.substeps - 1, -1, -1):
        with rec.phase("zero gradients"):
            ws.prepare_substep(run, s, windows[s])
        with rec.phase("taped replay"):
            tape = ws.record_substep(run, s, windows[s])
        run_tape_backward(rec, tape)
    with rec.phase("seed/finish copies"):
        ws.finish()
    run.check_divergence(frame)
    if parameters:
        with rec.phase("reduce parameter gradients", wall=True):
            ws.collect_parameter_gradients(run)


def run_tape_backward(rec: Recorder, tape: wp.Tape) -> None:
    """tape.backward(), as phase "adjoint". On the CPU each recorded launch goes through its
    own one-launch tape, so that its wall time is its own: Tape.backward runs the same
    adjoint launches in the same reverse order."""
    if rec.cuda:
        with rec.phase("adjoint"):
            tape.backward()
        return
    for launch in reversed(tape.launches):
        single = wp.Tape()
        single.launches = [launch]
        name = "recorded function" if callable(launch) else launch[0].key
        with rec.phase("adjoint", f"backward kernel {name}"):
            single.backward()


def gradients(run: MPMRun) -> dict[str, torch.Tensor]:
    """What one frame's adjoint produced: parameter gradients and d(loss)/d(start state)."""
    ws = run.backward_workspace()
    out = {"theta": run.tables.grad_theta()}
    for name in ("x", "v", "C", "F", "plastic_J"):
        out[name] = wp.to_torch(getattr(ws.carry, name).grad).detach().cpu().clone()
    return out


def compare(profiled: dict, real: dict) -> dict:
    """Largest difference of each gradient relative to the real path's largest magnitude."""
    out = {"bit_identical": all(torch.equal(profiled[k], real[k]) for k in real)}
    for k, ref in real.items():
        scale = float(ref.abs().max()) or 1.0
        out[f"{k}_max_rel_diff"] = float((profiled[k] - ref).abs().max()) / scale
    return out


def graph_frame_ms(setup: Setup, start: ParticleState, frame: int, reps: int) -> tuple:
    """Wall ms of one forward frame and one adjoint frame through the real path (captured CUDA
    graphs on GPUs: MPMRun.advance_frame, BackwardWorkspace.adjoint_frame), mean of ``reps``
    after a warm-up that captures and compiles; and the real path's gradients."""
    run = setup.run
    ws = run.backward_workspace()
    fwd, bwd = [], []
    for rep in range(reps + 1):
        run.a.copy_from(start)
        with wp.ScopedTimer("forward", print=False, synchronize=True) as t:
            run.advance_frame(frame)
        seed_loss(run)
        with wp.ScopedTimer("adjoint", print=False, synchronize=True) as b:
            ws.begin_parameters(run)  # once per rollout: here a one-frame one
            ws.adjoint_frame(run, start, frame=frame)
            ws.collect_parameter_gradients(run)
        if rep:
            fwd.append(t.elapsed)
            bwd.append(b.elapsed)
    return sum(fwd) / reps, sum(bwd) / reps, gradients(run)


def memory(setup: Setup) -> dict:
    """Peak GPU memory (Warp's pool high-water mark over the process, torch's peak since the
    profile began) and the backward workspace's bytes (one frame's per-substep states and the
    grid, values and gradients)."""
    run, dev = setup.run, setup.run.device
    out = {"backward_workspace_bytes": run.backward_workspace().nbytes()}
    if wp.get_device(dev).is_cuda:
        out["torch_max_allocated_bytes"] = int(
            torch.cuda.max_memory_allocated(wp.device_to_torch(dev))
        )
        if wp.is_mempool_enabled(dev):
            out["warp_mempool_high_bytes"] = int(wp.get_mempool_used_mem_high(dev))
    return out


def without_parameter_gradients(setup: Setup, start: ParticleState, frame: int) -> dict:
    """The profiled adjoint again with every parameter gradient array removed (the particles'
    copies' and the tables'), so that Warp's adjoints skip their parameter atomics (suspect 1):
    ms per (phase, name) and total. The copies' values (the particles' and the nodes') are
    gathered first (the taped kernels read them); no gradient is summed. Friction keeps its
    gradient, the table's and the nodes' copy's: field_sums' hand-written adjoint writes into
    it unchecked (the copy's: one uncontended atomic per node with mass)."""
    run = setup.run
    ws = run.backward_workspace()
    ws.begin_parameters(run)
    arrays = [*vars(run.tables).values(), *ws.parameter_copies()]
    kept = (run.tables.friction, ws.node_coefficients.friction)
    tables = [
        a
        for a in arrays
        if isinstance(a, wp.array) and a.requires_grad and not any(a is k for k in kept)
    ]
    for a in tables:
        a.requires_grad = False
    try:
        ws.carry.zero_grad()
        ws.carry.x.grad.fill_(1.0)
        rec = Recorder(wp.get_device(run.device).is_cuda)
        profiled_adjoint(run, rec, start, frame, parameters=False)
    finally:
        for a in tables:
            a.requires_grad = True  # fresh zero gradients; the captured graph is not replayed
    rows = rec.rows()
    return {"rows": [asdict(r) for r in rows], "total_ms": sum(r.ms for r in rows)}


def profile_backward(setup: Setup, args) -> Profile:
    run, cuda = setup.run, wp.get_device(args.device).is_cuda
    start = start_state(setup, args.frame)
    if cuda:
        torch.cuda.reset_peak_memory_stats(wp.device_to_torch(args.device))
    g_fwd, g_bwd, real = graph_frame_ms(setup, start, args.frame, args.reps)
    seed_loss(run)
    profiled_adjoint(run, Recorder(cuda), start, args.frame)  # warm-up of the uncaptured path
    fwd = Recorder(cuda)
    time_forward(setup, fwd, start, args.frame)
    seed_loss(run)
    rec = Recorder(cuda)
    profiled_adjoint(run, rec, start, args.frame)
    check = compare(gradients(run), real)
    rows = rec.rows()
    total = sum(r.ms for r in rows)
    forward_ms = sum(r.ms for r in fwd.rows())
    work = run.n * run.substeps
    return Profile(
        mode="backward",
        **_workload(run, args, cuda),
        rows=rows,
        total_ms=total,
        wall_ms=rec.wall_ms,
        forward_ms=forward_ms,
        forward_rows=fwd.rows(),
        rate=work / ((forward_ms + total) / 1e3),
        graph_forward_ms=g_fwd,
        graph_backward_ms=g_bwd,
        graph_rate=work / ((g_fwd + g_bwd) / 1e3),
        memory=memory(setup),
        gradient_check=check,
        ablation=without_parameter_gradients(setup, start, args.frame) if args.ablate else None,
    )


def _workload(run, args, cuda: bool) -> dict:
    """The fields of a Profile that say what was timed and how, the same in both modes."""
    return {
        "device": args.device,
        "timing": "cuda activity" if cuda else "cpu wall per launch group",
        "particles": run.n,
        "grid": args.grid,
        "substeps": run.substeps,
        "family": args.family,
        "order": args.order,
        "parameter_reads": "tables" if args.table_reads else "copies",
        "scatter_adjoint": "unrolled" if args.unrolled_scatter_adjoint else "looped",
    }


def profile_forward(setup: Setup, args) -> Profile:
    run, cuda = setup.run, wp.get_device(args.device).is_cuda
    start = start_state(setup, args.frame)
    warm = Recorder(cuda)
    time_forward(setup, warm, start, args.frame)  # compile and warm up
    rec = Recorder(cuda)
    t0 = time.perf_counter()
    time_forward(setup, rec, start, args.frame)
    wall = time.perf_counter() - t0
    rows = rec.rows()
    total = sum(r.ms for r in rows)
    return Profile(
        mode="forward",
        **_workload(run, args, cuda),
        rows=rows,
        total_ms=total,
        wall_ms=wall * 1e3,
        forward_ms=total,
        rate=run.n * run.substeps / wall,
    )


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--particles", type=int, default=1_000_000)
    ap.add_argument("--grid", type=int, default=128)
    ap.add_argument("--substeps", type=int, default=50)
    ap.add_argument(
        "--order",
        choices=["scatter", "cell", "lattice", "random"],
        default="scatter",
        help="particle order: GridLayout.scatter_order (what rollouts use), sorted by grid cell, "
        "as generated, or shuffled",
    )
    ap.add_argument("--backward", action="store_true", help="profile one frame's adjoint")
    ap.add_argument("--device", default=None, help="cuda:N or cpu (default: cuda:0 if present)")
    ap.add_argument("--family", choices=FAMILIES, default="elastic", help="the cube's law")
    ap.add_argument("--frame", type=int, default=1, help="which frame (1-based) to profile")
    ap.add_argument("--reps", type=int, default=3, help="real-path frames timed (backward)")
    ap.add_argument("--deterministic", action="store_true", help="Warp's deterministic atomics")
    ap.add_argument(
        "--grid-window",
        choices=["whole", "particles", "device"],
        default=None,
        help="which grid nodes the grid kernels visit (warp-mpm's grid_window; default: the "
        "run's own choice, the device's box on CUDA)",
    )
    ap.add_argument(
        "--ablate-parameter-gradients",
        dest="ablate",
        action="store_true",
        help="backward: also profile the adjoint without the parameter tables' gradients",
    )
    ap.add_argument(
        "--table-reads",
        dest="table_reads",
        action="store_true",
        help="backward: the taped kernels read the per-object tables, as before the particles' "
        "and the nodes' parameter copies (BackwardWorkspace.gather_parameters off), for "
        "comparison",
    )
    ap.add_argument(
        "--unrolled-scatter-adjoint",
        dest="unrolled_scatter_adjoint",
        action="store_true",
        help="backward: tape the replay's scatter as the unrolled p2g, not p2g_looped "
        "(BackwardWorkspace.looped_scatter_adjoint off), for comparison",
    )
    ap.add_argument("--target", type=float, default=3e8, help="particle-substeps/s to compare")
    ap.add_argument("--json", default=None, help="also write the profile to this JSON file")
    args = ap.parse_args(argv)
    for flag in ("table_reads", "unrolled_scatter_adjoint"):
        if getattr(args, flag) and not args.backward:
            ap.error(f"--{flag.replace('_', '-')} profiles the backward: add --backward")
    for name in ("particles", "grid", "substeps", "frame", "reps"):
        if getattr(args, name) < 1:
            ap.error(f"--{name} must be at least 1, got {getattr(args, name)}")
    return args


def main(argv: list[str] | None = None) -> Profile:
    args = parse_args(argv)
    init_warp()
    use_deterministic_atomics(args.deterministic)
    if args.device is None:
        args.device = "cuda:0" if wp.is_cuda_available() else "cpu"
    if args.device.startswith("cuda") and not wp.is_cuda_available():
        raise SystemExit(f"--device {args.device}: Warp sees no CUDA device (use --device cpu)")
    setup = build(args)
    profile = profile_backward(setup, args) if args.backward else profile_forward(setup, args)
    if args.json:  # first, so that the measurement survives a failing report
        with open(args.json, "w") as fh:
            json.dump(asdict(profile), fh, indent=1)
    print(report(profile, args.target))
    return profile


if __name__ == "__main__":
    main()
