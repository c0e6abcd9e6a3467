"""The warp-mpm Simulator: the substep/frame loop (input checks and packing: packing.py).

``WarpMPMSimulator`` is the component the registry hands out; it makes an ``MPMRun`` (run.py),
which owns one rollout's Warp buffers, per rollout shape and drives it.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
import warp as wp

from mosiv_framework.errors import ConfigError, SimulationDiverged
from mosiv_framework.interfaces import Simulator
from mosiv_framework.particle_order import scatter_ordered
from mosiv_framework.types import ParticleSet, SimulationParams, Trajectory, World
from mosiv_warp_mpm import expression_kernels as XK
from mosiv_warp_mpm import kernels as K
from mosiv_warp_mpm import laws as laws_module
from mosiv_warp_mpm import transfer_kernels as T
from mosiv_warp_mpm.laws import LAW_IDS
from mosiv_warp_mpm.options import WarpMPMOptions
from mosiv_warp_mpm.packing import TERMS, check_inputs, initial_velocities, pack_theta
from mosiv_warp_mpm.run import MPMRun
from mosiv_warp_mpm.state import (
    GridLayout,
)

_WARP_READY = False


def init_warp() -> None:
    """Initialise Warp once per process (quietly)."""
    global _WARP_READY
    if not _WARP_READY:
        wp.config.quiet = True  # older Warp
        # newer Warp logs its banner and module loads at INFO on stdout, where they broke
        # ``mosiv bench sim --json``
        if hasattr(wp, "LOG_WARNING"):
            wp.config.log_level = max(wp.config.log_level, wp.LOG_WARNING)
        wp.init()
        _WARP_READY = True


#: the deterministic setting this process's warp-mpm kernels were given (None: not yet)
_DETERMINISTIC: bool | None = None


def use_deterministic_atomics(on: bool) -> None:
    """Compile this plugin's kernels with Warp's deterministic atomics (``on``) or ordinary ones.

    Float atomics summed in whatever order the GPU schedules them make two runs of the same
    rollout differ in the last bits, and a chaotic rollout (fracture, contact) or a long
    identification grows that into visible differences. RUN_TO_RUN records the updates and
    reduces them in a fixed order instead. The setting belongs to the Warp modules, not to a
    simulator, so a process that asks for both is refused rather than silently mixed.
    """
    global _DETERMINISTIC
    if _DETERMINISTIC is not None and _DETERMINISTIC != on:
        raise ConfigError(
            f"simulator warp-mpm: deterministic={on} after deterministic={_DETERMINISTIC} in "
            "the same process; Warp compiles the kernels one way per process: give every "
            "warp-mpm simulator of the run the same setting (the recipe's simulator and "
            "scene.source.simulator_options) or run them in separate processes"
        )
    if _DETERMINISTIC is None:
        mode = wp.DeterministicMode.RUN_TO_RUN if on else wp.DeterministicMode.NOT_GUARANTEED
        for module in (K, T, XK, laws_module, T.p2g_looped.module):
            wp.set_module_options({"deterministic": mode}, module=module)
        _DETERMINISTIC = on


def resolve_device(name: str) -> str:
    """Warp device string for the ``device`` option ("auto" picks CUDA when available)."""
    if name == "auto":
        return "cuda:0" if wp.is_cuda_available() else "cpu"
    if name.startswith("cuda") and not wp.is_cuda_available():
        raise ConfigError(
            f"simulator warp-mpm: device={name!r} but Warp sees no CUDA device; use device=cpu "
            "(or auto)"
        )
    return "cuda:0" if name == "cuda" else name


class WarpMPMSimulator(Simulator):
    """Differentiable multi-object MLS-MPM on Warp (docs/PHYSICS.md, MLS-MPM scheme)."""

    supported_laws = frozenset(LAW_IDS)
    supported_terms = frozenset(TERMS)

    def __init__(self, options: WarpMPMOptions | None = None, **kwargs):
        self.options = options if options is not None else WarpMPMOptions(**kwargs)
        init_warp()
        use_deterministic_atomics(self.options.deterministic)
        self.device = resolve_device(self.options.device)
        #: bytes held for the last differentiable rollout: checkpoints (forward) and the
        #: backward's one-frame workspace; filled by autograd.py
        self.last_memory: dict[str, int] = {}
        self._peak = 0
        # Rollouts of the same layout reuse a run: its buffers and captured CUDA graphs. One
        # for forward-only rollouts (evaluation, generation, benchmarks, line searches), one
        # for differentiable ones (identification's iterations)
        self._forward_run: MPMRun | None = None
        self._forward_key: tuple | None = None
        self._grad_run: MPMRun | None = None
        self._grad_key: tuple | None = None
        # and one each for batched forward and batched differentiable rollouts (batched.py)
        self._batch_run: MPMRun | None = None
        self._batch_key: tuple | None = None
        self._grad_batch_run: MPMRun | None = None
        self._grad_batch_key: tuple | None = None

    @property
    def torch_device(self) -> torch.device:
        # wp.device_to_torch returns a device string; the interface promises a torch.device
        return torch.device(wp.device_to_torch(self.device))

    @property
    def deterministic(self) -> bool:
        # CUDA sums atomics in schedule order unless asked not to; the CPU runs them in order
        return self.options.deterministic or not wp.get_device(self.device).is_cuda

    # -- memory ----------------------------------------------------------------------------
    def reset_peak_memory(self) -> None:
        if wp.get_device(self.device).is_cuda:
            torch.cuda.reset_peak_memory_stats()
            self._peak = wp.get_mempool_used_mem_current(self.device)

    def _sample_peak(self) -> None:
        self._peak = max(self._peak, wp.get_mempool_used_mem_current(self.device))

    def peak_memory_bytes(self) -> int | None:
        """Peak CUDA memory since reset_peak_memory (Warp pool + torch); None on CPU."""
        if not wp.get_device(self.device).is_cuda:
            return None
        self._sample_peak()
        return int(self._peak + torch.cuda.max_memory_allocated())

    # -- law kernels, for the parity suite -------------------------------------------------
    def evaluate_law(self, family, F, values, *, plastic_J, velocity_gradient, dt):
        """The Warp stress and return-map functions of ``family`` on given inputs (float32)."""
        from mosiv_warp_mpm.laws import LAW_PARAM_NAMES, N_SLOTS, evaluate_laws, vec5

        n = F.shape[0]
        slots = torch.zeros(n, N_SLOTS, dtype=torch.float32)
        for i, name in enumerate(LAW_PARAM_NAMES[family]):
            slots[:, i] = torch.as_tensor(values[name], dtype=torch.float32).expand(n)

        def arr(t, dtype):
            return wp.array(t.detach().cpu().float().numpy(), dtype=dtype, device=self.device)

        tau = wp.zeros(n, dtype=wp.mat33, device=self.device)
        F_new = wp.zeros(n, dtype=wp.mat33, device=self.device)
        pj_new = wp.zeros(n, dtype=float, device=self.device)
        wp.launch(
            evaluate_laws,
            dim=n,
            inputs=[
                LAW_IDS[family],
                arr(slots, vec5),
                arr(F, wp.mat33),
                arr(velocity_gradient, wp.mat33),
                arr(plastic_J, float),
                float(dt),
            ],
            outputs=[tau, F_new, pj_new],
            device=self.device,
        )
        return tuple(torch.from_numpy(a.numpy()) for a in (tau, F_new, pj_new))

    # -- rollout ---------------------------------------------------------------------------
    def _new_run(self, layout, world, ids, families, obj_index, volumes, batch=1) -> MPMRun:
        run = MPMRun(
            layout=layout,
            world=world,
            substeps=self.options.substeps,
            device=self.device,
            object_ids=ids,
            families=families,
            obj_index=obj_index,
            volumes=volumes,
            window=self._window(batch),
            window_threads=self._window_threads(layout),
            batch=batch,
        )
        if wp.get_device(self.device).is_cuda:
            run.peak_sampler = self._sample_peak
        return run

    def _window_threads(self, layout) -> int | None:
        """Threads a field of a device window's grid kernels (state.WINDOW_THREADS when None).
        With deterministic atomics one node a thread (the whole grid's count): Warp sizes the
        records of a deterministic launch by one per atomic and thread, and inside a captured
        graph drops the updates of threads that loop over several nodes without an error."""
        return layout.nodes_per_field if self.options.deterministic else None

    def _window(self, batch: int) -> str | None:
        """Which grid nodes a run visits (options.grid_window, run.WINDOWS); None ("auto")
        leaves it to MPMRun: the box around the particles, launched at its own size on the CPU
        (Warp runs the threads one after another) and kept on the device on CUDA, where it was
        1.1-2.7x faster than the whole grid for forward plus backward from 2,000 to 1M
        particles, and 1.6x the box read back for 16 batched members (docs/BENCHMARKS.md, Grid
        window on CUDA)."""
        del batch  # the same choice for single and batched rollouts
        if self.options.grid_window != "auto":
            return self.options.grid_window
        return None

    def scatter_layout(self, particles: ParticleSet, world: World) -> tuple:
        """The grid layout, the object ids and the particles in scatter order
        (particle_order.scatter_ordered, GridLayout.scatter_order's order) on the run's
        device: (layout, ids, ScatterOrdered)."""
        ids = particles.object_list
        fields = len(ids) if self.options.contact == "multi_field" else 1
        layout = GridLayout.for_world(world, grid=self.options.grid, fields=fields)
        ordered = scatter_ordered(
            particles,
            ids,
            origin=layout.origin,
            dx=layout.dx,
            nodes=layout.nodes,
            device=wp.device_to_torch(self.device),
        )
        return layout, ids, ordered

    def rollout_batch(
        self,
        particles: ParticleSet,
        params_list: Sequence[SimulationParams],
        *,
        world: World,
        frames: int,
    ) -> list[Trajectory | SimulationDiverged]:
        """All members in one simulation (batched.py), differentiable under autograd."""
        from mosiv_warp_mpm.batched import rollout_batch

        return rollout_batch(self, particles, params_list, world=world, frames=frames)

    def rollout(
        self, particles: ParticleSet, params: SimulationParams, *, world: World, frames: int
    ) -> Trajectory:
        from mosiv_warp_mpm.autograd import WarpRollout  # keeps the two modules one-way

        check_inputs(particles, params, world, frames, contact=self.options.contact)
        layout, ids, ordered = self.scatter_layout(particles, world)
        x0s, obj_index, volumes = ordered.positions, ordered.obj_index, ordered.volumes
        dev, out_dev = x0s.device, particles.positions.device
        v0 = initial_velocities(params, ids, obj_index)
        theta = pack_theta(params, ids, world.gravity, dev)
        families = [params.objects[k].family for k in ids]
        needs_grad = torch.is_grad_enabled() and any(t.requires_grad for t in (x0s, v0, theta))
        key = (layout, world, self.options.substeps, tuple(ids), tuple(families), len(x0s))
        if needs_grad:
            # A differentiable rollout owns its run until its backward pass has finished; a
            # run still waiting for one (a second rollout before backward, or an abandoned
            # graph) is left to its rollout and replaced.
            run = self._grad_run
            if run is None or self._grad_key != key or run.awaiting_backward:
                run = self._new_run(layout, world, ids, families, obj_index, volumes)
                self._grad_run, self._grad_key = run, key
            else:
                run.refresh(obj_index, volumes)
            pos, vel = WarpRollout.apply(run, self, frames, x0s, v0, theta)
        else:  # cheap path: no checkpoints, no tape, buffers and CUDA graph reused
            if self._forward_key != key:
                self._forward_run = self._new_run(layout, world, ids, families, obj_index, volumes)
                self._forward_key = key
            else:
                self._forward_run.refresh(obj_index, volumes)
            pos, vel = self._forward_run.forward(x0s, v0, theta, frames, keep=False)
        return Trajectory(
            positions=ordered.to_caller(pos).to(out_dev),
            object_ids=particles.object_ids,
            fps=world.fps,
            velocities=ordered.to_caller(vel.detach()).to(out_dev),
        )
