"""The warp-mpm Simulator: the substep/frame loop (input checks and packing: packing.py).

``MPMRun`` owns the Warp buffers of one rollout and knows how to advance a frame forward (CUDA
graph on GPUs) and how to back-propagate through one frame (see autograd.py for the schedule).
``WarpMPMSimulator`` is the component the registry hands out.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
import warp as wp

from mosiv_framework.errors import ConfigError, SimulationDiverged
from mosiv_framework.expression import up_vector
from mosiv_framework.interfaces import Simulator
from mosiv_framework.types import ParticleSet, SimulationParams, Trajectory, World
from mosiv_warp_mpm import expression_kernels as XK
from mosiv_warp_mpm import kernels as K
from mosiv_warp_mpm import laws as laws_module
from mosiv_warp_mpm.laws import LAW_IDS
from mosiv_warp_mpm.options import WarpMPMOptions

# re-exported: batched.py, tests and benchmarks import them from this module
from mosiv_warp_mpm.packing import TERMS, check_inputs, initial_velocities, pack_theta
from mosiv_warp_mpm.state import (
    Grid,
    GridLayout,
    NodeBox,
    NodeCoefficients,
    ObjectTables,
    ParticleParams,
    ParticleState,
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
        for module in (K, XK, laws_module):
            wp.set_module_options({"deterministic": mode}, module=module)
        _DETERMINISTIC = on


def resolve_device(name: str) -> str:
    """Warp device string for the ``device`` option ("auto" picks CUDA when available)."""
    if name == "auto":
        return "cuda:0" if wp.is_cuda_available() else "cpu"
    if name.startswith("cuda") and not wp.is_cuda_available():
        raise ConfigError(f"simulator warp-mpm: device={name!r} but Warp sees no CUDA device")
    return "cuda:0" if name == "cuda" else name


class MPMRun:
    """Buffers and loops of one rollout (fixed particles, objects, grid and substeps)."""

    def __init__(
        self,
        *,
        layout: GridLayout,
        world: World,
        substeps: int,
        device: str,
        object_ids: list[int],
        families: list[str],
        obj_index: torch.Tensor,
        volumes: torch.Tensor,
        windowed: bool | None = None,
        batch: int = 1,
    ):
        """``windowed``: whether grid kernels visit only the nodes around the particles
        (``active_box``); default: on the CPU only. ``batch``: members simulated together
        (batched.py); then ``families`` lists every member's objects, member-major, and
        ``obj_index`` holds b K + k for a particle of member b (kernels.py)."""
        self.layout, self.world, self.substeps, self.device = layout, world, substeps, device
        if windowed is None:
            windowed = not wp.get_device(device).is_cuda
        if windowed and wp.get_device(device).is_cuda:
            raise ConfigError("a windowed grid needs the CPU: CUDA replays one captured graph")
        self.windowed = windowed
        self.whole_box = NodeBox.whole(layout)
        self.object_ids, self.batch = object_ids, batch
        self.dt = 1.0 / (world.fps * substeps)
        self.n = int(obj_index.shape[0])
        k = len(object_ids)
        fields = list(range(k)) if layout.fields > 1 else [0] * k
        fields = [b * layout.fields + f for b in range(batch) for f in fields]
        law_ids = [LAW_IDS[f] for f in families]
        self.tables = ObjectTables(law_ids, fields, device, batch=batch)
        self.obj = wp.from_torch(obj_index.to(torch.int32).contiguous(), dtype=wp.int32)
        self.obj = wp.clone(self.obj, device=device)
        self.volume = wp.clone(wp.from_torch(volumes.float().contiguous()), device=device)
        self.flag = wp.full(batch * k, K.NO_FLAG, dtype=int, device=device)
        self.grid = Grid(layout, device, batch=batch)
        self.a = ParticleState(self.n, device)
        self.b = ParticleState(self.n, device)
        self.checkpoints: list[ParticleState] = []
        self._checkpoint_pool: list[ParticleState] = []  # reused between rollouts
        self._backward = None  # autograd.BackwardWorkspace, made on the first backward
        #: the frame's captured CUDA graph, per value of ``centres`` (the launches differ)
        self._graphs: dict[bool, wp.Graph] = {}
        self.ground_on = int(world.ground_height is not None)
        z0 = layout.origin[2]
        self.ground_k = ((world.ground_height or 0.0) - z0) / layout.dx + 1e-4
        #: the current frame's start time (s), read by the expression term (``set_clock``)
        self.clock = wp.zeros(1, dtype=float, device=device)
        self.up = wp.vec3(*up_vector(world.gravity).tolist())
        self.peak_sampler = None  # callable sampling device memory, set by the simulator

    def refresh(self, obj_index: torch.Tensor, volumes: torch.Tensor) -> None:
        """Load another particle set of the same size and objects into the existing buffers
        (in place, so a captured CUDA graph stays valid)."""
        wp.copy(self.obj, wp.from_torch(obj_index.to(torch.int32).contiguous(), dtype=wp.int32))
        wp.copy(self.volume, wp.from_torch(volumes.float().contiguous()))

    @property
    def centres(self) -> bool:
        """Whether this rollout's substeps sum the other objects' centres (``centre_sums``):
        with several fields and an expression that uses them (ObjectTables.relative, set by
        ``tables.load``). Otherwise neither the sums' kernels nor their memsets are launched,
        and a CUDA graph is captured per value of this flag."""
        return self.layout.fields > 1 and self.tables.relative

    def set_clock(self, frame: int) -> None:
        """The start time of ``frame`` (1-based: the frame that ``advance_frame(frame)`` makes),
        outside any captured graph, so that one graph serves every frame; only when some
        member has the expression term, its only reader."""
        if self.tables.expression:
            self.clock.fill_((frame - 1) / self.world.fps)

    def begin_frame(self, frame: int, grid: Grid) -> None:
        """Before ``frame``'s launches on ``grid``, outside any captured graph: the clock, and
        the per-field sums zeroed where an expression reads them without computing them (its
        other-object coefficients are 0) while an earlier rollout of this run left values."""
        self.set_clock(frame)
        if self.centres:
            grid.sums_written = True
        elif grid.sums_written and self.tables.expression:
            grid.clear_sums()

    # -- one substep -----------------------------------------------------------------------
    def expression_inputs(
        self, grid: Grid, s: int, switch: wp.array | None = None
    ) -> K.ExpressionInputs:
        """The expression term's kernel inputs at substep ``s`` of a frame; ``switch``: the
        switches to read instead of the table's (NodeCoefficients.expr_switch)."""
        expr = K.ExpressionInputs()
        expr.on = self.tables.expr_switch if switch is None else switch
        expr.coef = self.tables.expr_coef
        expr.rel_p, expr.rel_v, expr.rel_n = grid.rel_p, grid.rel_v, grid.rel_n
        expr.clock, expr.substep = self.clock, s
        expr.origin, expr.dx = wp.vec3(*self.layout.origin), self.layout.dx
        expr.up, expr.ground = self.up, float(self.world.ground_height or 0.0)
        return expr

    def centre_sums(self, grid: Grid, box: NodeBox, switch: wp.array | None = None) -> None:
        """The other objects' summed centres per field (expression_kernels.py), for an
        expression of the other objects' features: launched only when some member's expression
        uses them (``centres``; the kernels skip the other members). ``switch``: as in
        ``expression_inputs``."""
        if not self.centres:
            return
        if switch is None:
            switch = self.tables.expr_switch
        lay = self.layout
        box_lo, box_dims = wp.vec3i(*box.lo), wp.vec3i(*box.dims)
        wp.launch(
            XK.field_moments,
            dim=self.batch * lay.fields * box.count,
            inputs=[grid.m, grid.mv, switch, wp.vec3(*lay.origin), lay.dx]
            + [box_lo, box_dims, wp.vec3i(*lay.nodes), lay.fields],
            outputs=[grid.moment_m, grid.moment_mx, grid.moment_mv],
            device=self.device,
        )
        wp.launch(
            XK.other_centres,
            dim=self.batch * lay.fields * lay.fields,
            inputs=[grid.moment_m, grid.moment_mx, grid.moment_mv, switch, lay.fields],
            outputs=[grid.rel_p, grid.rel_v, grid.rel_n],
            device=self.device,
        )

    def active_box(self, state: ParticleState) -> NodeBox:
        """The grid nodes this substep from ``state`` can touch (state.NodeBox): the whole grid
        on CUDA (one captured graph per frame), the box around the particles on the CPU."""
        if not self.windowed:
            return self.whole_box
        return NodeBox.around(state.x.numpy(), self.layout)

    def substep(
        self, src: ParticleState, dst: ParticleState, grid: Grid, s: int, box: NodeBox
    ) -> None:
        """P2G, grid update (contact, ground, walls, terms) and G2P from src into dst; the grid
        kernels visit the nodes of ``box`` (``active_box(src)``), cleared beforehand."""
        self.grid_update(src, grid, s, box)
        inputs, outputs = self._g2p_args(src, dst, grid, s)
        wp.launch(K.g2p, dim=self.n, inputs=inputs, outputs=outputs, device=self.device)

    def record_g2p(
        self,
        tape: wp.Tape,
        src: ParticleState,
        dst: ParticleState,
        grid: Grid,
        s: int,
        gathered: ParticleParams | None = None,
    ) -> None:
        """Put substep ``s``'s G2P on ``tape`` without running it, for a replay whose ``dst``
        already holds G2P's result (the backward's re-simulation wrote it): G2P's adjoint reads
        only its inputs and its outputs' gradients, so running it again would only rewrite
        ``dst`` with the same values. ``gathered``: see ``grid_update``."""
        inputs, outputs = self._g2p_args(src, dst, grid, s, gathered)
        tape.record_launch(K.g2p, self.n, 0, inputs, outputs, self.device)

    def _g2p_args(
        self, src: ParticleState, dst: ParticleState, grid: Grid, s: int, gathered=None
    ) -> tuple:
        lay, t = self.layout, self.tables
        origin, nodes = wp.vec3(*lay.origin), wp.vec3i(*lay.nodes)
        law_params = t.params if gathered is None else gathered.params
        inputs = [src.x, src.F, src.plastic_J, self.obj, t.law_of, t.field_of, law_params]
        inputs += [int(gathered is not None), grid.v, origin, lay.dx, self.dt, nodes, s, self.flag]
        return inputs, [dst.x, dst.v, dst.C, dst.F, dst.plastic_J]

    def grid_update(
        self,
        src: ParticleState,
        grid: Grid,
        s: int,
        box: NodeBox,
        gathered: ParticleParams | None = None,
        coefficients: NodeCoefficients | None = None,
    ) -> None:
        """P2G from src, then the grid's free velocity and boundaries, on the nodes of ``box``
        (cleared beforehand): the grid velocities ``grid.v`` that G2P reads.

        ``gathered``: None, P2G reads the per-object tables (forward rollouts, re-simulation);
        else the particles' own copies of them (the taped replay, whose parameter adjoints then
        land on one address per particle: kernels.parameter_rows). ``coefficients``: likewise
        for grid_free_velocity's body acceleration and drag (the nodes' copies, ``per_node``)
        and the expression switches (a copy without a gradient). Same values, same results.
        """
        lay, t, dev = self.layout, self.tables, self.device
        origin, nodes = wp.vec3(*lay.origin), wp.vec3i(*lay.nodes)
        box_lo, box_dims = wp.vec3i(*box.lo), wp.vec3i(*box.dims)
        law_inputs = [t.params, t.rho, t.damping] if gathered is None else gathered.arrays()
        wp.launch(
            K.p2g,
            dim=self.n,
            inputs=[src.x, src.v, src.C, src.F, src.plastic_J, self.volume, self.obj]
            + [t.law_of, t.field_of, *law_inputs, origin, lay.dx, self.dt, nodes]
            + [int(lay.fields > 1), self.ground_k if self.ground_on else -1.0, t.k]
            + [int(gathered is not None)],
            outputs=[grid.m, grid.mv, grid.gm, grid.pm],
            device=dev,
        )
        c = coefficients
        switch = None if c is None else c.expr_switch
        self.centre_sums(grid, box, switch)
        coef_inputs = [t.accel, t.drag, 0] if c is None else [c.accel, c.drag, 1]
        wp.launch(
            K.grid_free_velocity,
            dim=self.batch * lay.fields * box.count,
            inputs=[grid.m, grid.mv, *coef_inputs, self.expression_inputs(grid, s, switch)]
            + [self.dt, box_lo, box_dims, nodes, lay.fields],
            outputs=[grid.vs],
            device=dev,
        )
        wp.launch(
            K.grid_boundaries,
            dim=self.batch * box.count,
            inputs=[grid.m, grid.vs, grid.gm, grid.pm, lay.fields, t.friction, nodes]
            + [self.ground_on, self.ground_k, t.ground_friction, t.ground_restitution]
            + [box_lo, box_dims],
            outputs=[grid.v],
            device=dev,
        )

    # -- forward ----------------------------------------------------------------------------
    def _frame_launches(self) -> None:
        self.flag.fill_(K.NO_FLAG)
        src, dst, sums = self.a, self.b, self.centres
        for s in range(self.substeps):
            box = self.active_box(src)
            self.grid.clear(box, sums=sums)
            self.substep(src, dst, self.grid, s, box)
            src, dst = dst, src
        if src is not self.a:  # odd substep count: the result sits in b
            self.a.copy_from(src)

    def advance_frame(self, frame: int, *, check: bool = True) -> None:
        """Advance state ``a`` by one video frame; raise SimulationDiverged if it blew up
        (``check``; batched runs read ``divergences`` per member instead).

        On CUDA the frame's launches are captured once (per value of ``centres``) into a graph
        and replayed, so the substep loop costs no Python per substep.
        """
        self.begin_frame(frame, self.grid)
        if wp.get_device(self.device).is_cuda:
            graph = self._graphs.get(self.centres)
            if graph is None:
                with wp.ScopedCapture(device=self.device, force_module_load=True) as capture:
                    self._frame_launches()
                graph = self._graphs[self.centres] = capture.graph
            wp.capture_launch(graph)
        else:
            self._frame_launches()
        if check:
            self.check_divergence(frame)

    def check_divergence(self, frame: int) -> None:
        """Raise SimulationDiverged for the earliest flagged substep of this frame (of the
        first member that has one)."""
        for err in self.divergences(frame):
            if err is not None:
                raise err

    def divergences(self, frame: int) -> list[SimulationDiverged | None]:
        """Per member: SimulationDiverged for its earliest flagged substep of this frame, or
        None."""
        flags = self.flag.numpy().reshape(self.batch, -1)
        if int(flags.min()) >= K.NO_FLAG:
            return [None] * self.batch
        return [
            self._divergence(frame, b, row) if int(row.min()) < K.NO_FLAG else None
            for b, row in enumerate(flags)
        ]

    def _divergence(self, frame: int, member: int, flags) -> SimulationDiverged:
        oi = int(flags.argmin())
        code = int(flags[oi])
        substep, reason = code // 4, code % 4
        obj_id = self.object_ids[oi]
        if reason == int(K.REASON_NONFINITE):
            why = "non-finite position, velocity or deformation gradient"
            advice = (
                f"Increase substeps (now {self.substeps}, dt={self.dt:.3g} s), lower the "
                f"stiffness (E / bulk_modulus / shear_modulus) of object {obj_id}, or check its "
                "parameters for extreme values."
            )
        else:
            why = (
                f"a particle moved more than one grid cell (dx={self.layout.dx:.3g} m) in a substep"
            )
            advice = (
                f"Increase substeps (now {self.substeps}) or use a coarser grid; very soft or very "
                f"stiff parameters of object {obj_id} can also cause it."
            )
        eta = float(self.tables.damping.numpy()[member])
        if eta > 0:  # explicit viscous stability: dt < rho dx^2 / (6 eta)
            rho = float(self.tables.rho.numpy()[member * len(self.object_ids) + oi])
            limit = rho * self.layout.dx**2 / (6.0 * eta)
            advice += (
                f" With material_damping viscosity={eta:g} Pa s the explicit step needs "
                f"dt < rho dx^2 / (6 eta) = {limit:.3g} s (now {self.dt:.3g} s)."
            )
        return SimulationDiverged(
            object_id=obj_id, frame=frame, substep=substep, reason=why, advice=advice
        )

    def forward(
        self, x0: torch.Tensor, v0: torch.Tensor, theta: torch.Tensor, frames: int, *, keep: bool
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Roll out ``frames`` frames; returns positions and velocities [frames+1, N, 3] (torch,
        on the run's device). ``keep`` stores frame-start checkpoints for the backward pass."""
        self.tables.load(theta)
        self.a.set_initial(x0, v0)
        dev = wp.device_to_torch(self.device)
        pos = torch.empty(frames + 1, self.n, 3, device=dev)
        vel = torch.empty(frames + 1, self.n, 3, device=dev)
        pos[0], vel[0] = wp.to_torch(self.a.x), wp.to_torch(self.a.v)
        self.checkpoints = []
        try:
            self._roll(pos, vel, frames, keep=keep)
        except BaseException:
            self.checkpoints = []  # no backward will come for this rollout
            raise
        return pos, vel

    def _roll(self, pos: torch.Tensor, vel: torch.Tensor, frames: int, *, keep: bool) -> None:
        for f in range(1, frames + 1):
            if keep:
                if len(self._checkpoint_pool) < f:
                    self._checkpoint_pool.append(ParticleState(self.n, self.device))
                ckpt = self._checkpoint_pool[f - 1]
                ckpt.copy_from(self.a)
                self.checkpoints.append(ckpt)
            self.advance_frame(f)
            pos[f], vel[f] = wp.to_torch(self.a.x), wp.to_torch(self.a.v)
            self._sample_memory()

    @property
    def awaiting_backward(self) -> bool:
        """True between a differentiable forward and its backward (the checkpoints are in use)."""
        return bool(self.checkpoints)

    def release_checkpoints(self) -> None:
        self.checkpoints = []

    def backward_workspace(self):
        """The adjoint's buffers (and captured graph), made once per run."""
        from mosiv_warp_mpm.autograd import BackwardWorkspace  # autograd imports this module

        if self._backward is None:
            self._backward = BackwardWorkspace(self)
        return self._backward

    def _sample_memory(self) -> None:
        if self.peak_sampler is not None:
            self.peak_sampler()

    def checkpoint_bytes(self) -> int:
        return sum(c.nbytes() for c in self.checkpoints)


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
        #: whether grid kernels visit only the nodes around the particles (MPMRun.active_box);
        #: None: on the CPU only. Results are the same either way (tests/test_grid_window.py)
        self.windowed_grid: bool | None = None
        # Rollouts of the same layout reuse a run: its buffers and captured CUDA graphs. One
        # for forward-only rollouts (evaluation, generation, benchmarks, line searches), one
        # for differentiable ones (identification's iterations)
        self._forward_run: MPMRun | None = None
        self._forward_key: tuple | None = None
        self._grad_run: MPMRun | None = None
        self._grad_key: tuple | None = None
        # and one for batched forward rollouts (batched.py)
        self._batch_run: MPMRun | None = None
        self._batch_key: tuple | None = None

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
            windowed=self.windowed_grid,
            batch=batch,
        )
        if wp.get_device(self.device).is_cuda:
            run.peak_sampler = self._sample_peak
        return run

    def scatter_layout(self, particles: ParticleSet, world: World) -> tuple:
        """The grid layout and the particles in scatter order (GridLayout.scatter_order):
        (layout, object ids, positions [N, 3], object index [N], volumes [N], and the inverse
        permutation that puts outputs back in the caller's order), on the run's device."""
        ids = particles.object_list
        fields = len(ids) if self.options.contact == "multi_field" else 1
        layout = GridLayout.for_world(world, grid=self.options.grid, fields=fields)
        dev = wp.device_to_torch(self.device)
        x0 = particles.positions.to(dev, torch.float32)
        order = layout.scatter_order(x0)
        inverse = torch.empty_like(order)
        inverse[order] = torch.arange(order.numel(), device=dev)
        # object id -> object index, vectorised (a Python loop costs ~0.2 s per 1M particles)
        id_values = torch.tensor(ids, device=dev)
        obj_index = torch.searchsorted(id_values, particles.object_ids.to(dev))[order]
        volumes = particles.volumes.to(dev)[order]
        return layout, ids, x0[order], obj_index, volumes, inverse

    def rollout_batch(
        self,
        particles: ParticleSet,
        params_list: Sequence[SimulationParams],
        *,
        world: World,
        frames: int,
    ) -> list[Trajectory | SimulationDiverged]:
        """All members in one simulation (batched.py); under autograd with parameters that
        require gradients, the differentiable per-member loop of the base class."""
        from mosiv_warp_mpm.batched import rollout_batch

        return rollout_batch(self, particles, params_list, world=world, frames=frames)

    def rollout(
        self, particles: ParticleSet, params: SimulationParams, *, world: World, frames: int
    ) -> Trajectory:
        from mosiv_warp_mpm.autograd import WarpRollout  # keeps the two modules one-way

        check_inputs(particles, params, world, frames, contact=self.options.contact)
        layout, ids, x0s, obj_index, volumes, inverse = self.scatter_layout(particles, world)
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
            positions=pos[:, inverse].to(out_dev),
            object_ids=particles.object_ids,
            fps=world.fps,
            velocities=vel[:, inverse].detach().to(out_dev),
        )
