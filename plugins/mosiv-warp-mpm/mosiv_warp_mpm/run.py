"""One rollout's Warp buffers and launches: ``MPMRun``.

An ``MPMRun`` owns the particle, grid and parameter buffers of one rollout (or of a batch of
rollouts of one scene) and knows how to advance a frame forward (a CUDA graph on GPUs), where a
simulation diverged (object, frame, substep), and what the backward needs (autograd.py holds
the schedule). ``WarpMPMSimulator`` (simulator.py) makes one per rollout shape and drives it.
"""

from __future__ import annotations

import math

import numpy as np
import torch
import warp as wp

from mosiv_framework.errors import SimulationDiverged
from mosiv_framework.expression import up_vector
from mosiv_framework.types import World
from mosiv_warp_mpm import expression_kernels as XK
from mosiv_warp_mpm import kernels as K
from mosiv_warp_mpm import node_window as NW
from mosiv_warp_mpm import transfer_kernels as T
from mosiv_warp_mpm.laws import LAW_IDS
from mosiv_warp_mpm.options import GRID_WINDOWS
from mosiv_warp_mpm.state import (
    WINDOW_THREADS,
    Grid,
    GridLayout,
    NodeBox,
    NodeCoefficients,
    ObjectTables,
    ParticleParams,
    ParticleState,
    Window,
)

#: where the grid kernels' node box comes from (MPMRun's ``window``): grid_window's choices
WINDOWS = tuple(w for w in GRID_WINDOWS if w != "auto")

#: a stencil base beyond any grid: the bounds' start, left as it is when no particle counts
_NO_BASE = 2**30


def _ground(world: World, layout: GridLayout) -> tuple[int, float, int]:
    """(whether there is a ground, its height in grid coordinates ground_k, the node layers
    k <= ground_k where the ground contact acts); the kernels compare in float32, so the layer
    count comes from ground_k rounded as they see it."""
    on = int(world.ground_height is not None)
    ground_k = ((world.ground_height or 0.0) - layout.origin[2]) / layout.dx + 1e-4
    top = math.floor(float(np.float32(ground_k))) if on else -1
    return on, ground_k, min(max(top + 1, 0), layout.nodes[2])


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
        window: str | None = None,
        window_threads: int | None = None,
        batch: int = 1,
    ):
        """``window`` (WINDOWS): which nodes a substep's grid kernels visit. "whole": the whole
        grid; "particles": the box around the particles, found on the host each substep (read
        from the positions on the CPU, reduced on the device and read back on CUDA, launching
        without a captured graph); "device": the same box, found and kept on the device, the
        launches of a fixed size (state.Window: ``window_threads`` threads a field, default
        WINDOW_THREADS), so a CUDA frame stays one captured graph. Default: "particles" on the
        CPU, "device" on CUDA. ``batch``: members simulated together (batched.py); then
        ``families`` lists every member's objects, member-major, and ``obj_index`` holds
        b K + k for a particle of member b (kernels.py)."""
        self.layout, self.world, self.substeps, self.device = layout, world, substeps, device
        self.is_cuda = is_cuda = wp.get_device(device).is_cuda
        if window is None:
            window = "device" if is_cuda else "particles"
        if window not in WINDOWS:
            raise ValueError(f"window={window!r}: valid values are {list(WINDOWS)}")
        self.window = window
        #: threads a field of the device window's launches (state.Window)
        threads = WINDOW_THREADS if window_threads is None else window_threads
        self.device_stride = min(layout.nodes_per_field, threads)
        self.windowed = window != "whole"
        #: whether a frame's launches are captured once into a CUDA graph and replayed: the
        #: graph fixes every launch's size and argument, so a box read back on the host has none
        self.graphed = is_cuda and window != "particles"
        #: the stencil bases' bounds that a box found on the device comes from (kernels)
        self._bounds = self._bounds_start = None
        if self.windowed:  # min, then max, per axis: start above and below every base
            start = [_NO_BASE] * 3 + [-_NO_BASE] * 3
            self._bounds_start = wp.array(start, dtype=int, device=device)
            self._bounds = wp.zeros(6, dtype=int, device=device)
        self.whole_box = NodeBox.whole(layout)
        #: the box table the grid kernels read (state.Window): per substep, the box's first
        #: node and node counts; every row the whole grid until a window writes it
        rows = [(0, 0, 0), layout.nodes] * substeps
        self.boxes = wp.array(np.asarray(rows, dtype=np.int32), dtype=wp.vec3i, device=device)
        self.object_ids, self.batch = object_ids, batch
        self.dt = 1.0 / (world.fps * substeps)
        self.n = int(obj_index.shape[0])
        k = len(object_ids)
        fields = list(range(k)) if layout.fields > 1 else [0] * k
        fields = [b * layout.fields + f for b in range(batch) for f in fields]
        law_ids = [LAW_IDS[f] for f in families]
        self.tables = ObjectTables(law_ids, fields, device, batch=batch)
        #: the laws present: the per-law stress and deformation kernels launched each substep
        self.laws = sorted(set(law_ids))
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
        self.ground_on, self.ground_k, self.ground_layers = _ground(world, layout)
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

    def centre_sums(self, grid: Grid, window: Window, switch: wp.array | None = None) -> None:
        """The other objects' summed centres per field (expression_kernels.py), for an
        expression of the other objects' features: launched only when some member's expression
        uses them (``centres``; the kernels skip the other members). ``switch``: as in
        ``expression_inputs``."""
        if not self.centres:
            return
        if switch is None:
            switch = self.tables.expr_switch
        lay = self.layout
        wp.launch(
            XK.field_moments,
            dim=self.batch * lay.fields * window.stride,
            inputs=[grid.m, grid.mv, switch, wp.vec3(*lay.origin), lay.dx]
            + [*window.inputs(), wp.vec3i(*lay.nodes), lay.fields],
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

    def substep_window(self, state: ParticleState, s: int) -> Window:
        """The nodes substep ``s`` from ``state`` visits (state.Window), its box in row ``s`` of
        ``boxes``: with window "device" found there by two launches (no read-back, so a
        captured graph holds them), else ``active_box``'s, written there from the host."""
        if self.window == "device":
            self._reduce_bounds(state)
            wp.launch(
                NW.box_from_bounds,
                dim=1,
                inputs=[self._bounds, wp.vec3i(*self.layout.nodes), self.boxes, s],
                device=self.device,
            )
            return Window(self.boxes, s, self.device_stride)
        if self.window == "whole":  # the rows hold the whole grid from the start
            return Window(self.boxes, s, self.layout.nodes_per_field, whole=True)
        box = self.active_box(state)
        wp.launch(
            NW.set_box_row,
            dim=1,
            inputs=[self.boxes, s, wp.vec3i(*box.lo), wp.vec3i(*box.dims)],
            device=self.device,
        )
        return Window(self.boxes, s, box.count, whole=box.is_whole(self.layout))

    def active_box(self, state: ParticleState) -> NodeBox:
        """The grid nodes this substep from ``state`` can touch (state.NodeBox), as the host
        sees them: the whole grid unless ``windowed``, else the box around the particles (read
        from the positions on the CPU, from ``device_box`` on CUDA)."""
        if not self.windowed:
            return self.whole_box
        if self.is_cuda:
            return self.device_box(state)
        return NodeBox.around(state.x.numpy(), self.layout)

    def device_box(self, state: ParticleState) -> NodeBox:
        """The box around ``state``'s particles from their stencil bases' bounds, reduced on
        the device (kernels.stencil_base_bounds): 24 bytes cross to the host, not N positions.
        The same box as NodeBox.around up to float32 rounding at a cell's edge, which the
        box's margin of one node absorbs."""
        self._reduce_bounds(state)
        bounds = self._bounds.numpy()
        return NodeBox.from_bases(bounds[:3], bounds[3:], self.layout)

    def _reduce_bounds(self, state: ParticleState) -> None:
        """The lowest and highest stencil base per axis of ``state``'s particles, into
        ``_bounds`` on the device (kernels.stencil_base_bounds)."""
        wp.copy(self._bounds, self._bounds_start)
        lay = self.layout
        wp.launch(
            K.stencil_base_bounds,
            dim=self.n,
            inputs=[state.x, wp.vec3(*lay.origin), lay.dx],
            outputs=[self._bounds],
            device=self.device,
        )

    def substep(
        self,
        src: ParticleState,
        dst: ParticleState,
        grid: Grid,
        s: int,
        window: Window,
        stress: wp.array | None = None,
    ) -> None:
        """P2G, grid update (contact, ground, walls, terms) and G2P from src into dst; the grid
        kernels visit the nodes of ``window`` (``substep_window(src, s)``), cleared
        beforehand. ``stress``: None, the fused transfers (transfer_kernels.py: the laws inside
        the scatter and the gather); else the split ones that the backward's replay tapes, the
        particles' stress impulses passing through this buffer. The same values either way,
        but for a diverged particle's reset (transfer_kernels.py)."""
        self.grid_update(src, grid, s, window, stress=stress)
        split = stress is not None
        for kernel, inputs, outputs in self._g2p_launches(src, dst, grid, s, split=split):
            wp.launch(kernel, dim=self.n, inputs=inputs, outputs=outputs, device=self.device)

    def record_g2p(
        self,
        tape: wp.Tape,
        src: ParticleState,
        dst: ParticleState,
        grid: Grid,
        s: int,
        gathered: ParticleParams | None = None,
    ) -> None:
        """Put substep ``s``'s G2P (the gather, then the deformation update) on ``tape`` without
        running it, for a replay whose ``dst`` already holds G2P's result (the backward's
        re-simulation wrote it): their adjoints read only their inputs and their outputs'
        gradients, so running them again would only rewrite ``dst`` with the same values (the
        update's input C is the gather's output, already in ``dst``). ``gathered``: see
        ``grid_update``."""
        launches = self._g2p_launches(src, dst, grid, s, gathered, split=True)
        for kernel, inputs, outputs in launches:
            tape.record_launch(kernel, self.n, 0, inputs, outputs, self.device)

    def _g2p_launches(
        self,
        src: ParticleState,
        dst: ParticleState,
        grid: Grid,
        s: int,
        gathered: ParticleParams | None = None,
        *,
        split: bool = False,
    ) -> list[tuple]:
        """(kernel, inputs, outputs) of G2P's launches (transfer_kernels.py): the fused gather
        and return map, or, ``split``, the gather, then each law's deformation update."""
        lay, t = self.layout, self.tables
        origin, nodes = wp.vec3(*lay.origin), wp.vec3i(*lay.nodes)
        law_params = t.params if gathered is None else gathered.params
        per_particle = int(gathered is not None)
        outputs = [dst.x, dst.v, dst.C, dst.F, dst.plastic_J]
        if not split:
            inputs = [src.x, src.F, src.plastic_J, self.obj, t.law_of, t.field_of, law_params]
            inputs += [per_particle, grid.v, origin, lay.dx, self.dt, nodes, s, self.flag]
            return [(T.g2p_fused, inputs, outputs)]
        gather = [src.x, self.obj, t.field_of, grid.v, origin, lay.dx, self.dt, nodes, s]
        launches = [(T.g2p, gather + [self.flag], outputs[:3])]
        update = [dst.C, src.F, src.plastic_J, self.obj, t.law_of, law_params]
        update += [per_particle, self.dt, s, self.flag]
        for law in self.laws:
            launches.append((T.UPDATE_DEFORMATION[law], update, outputs[3:]))
        return launches

    def p2g(
        self,
        src: ParticleState,
        grid: Grid,
        gathered: ParticleParams | None = None,
        stress: wp.array | None = None,
        looped_on: wp.Tape | None = None,
    ) -> None:
        """P2G from src onto ``grid`` (transfer_kernels.py). ``stress``: None, the fused
        scatter with each particle's stress inside; else the split form: each law's particles'
        stress impulses into ``stress`` (one launch per law present), then the scatter.
        ``gathered``: see ``grid_update``. ``looped_on``: the tape being recorded, on which the
        split scatter goes as ``p2g_looped`` (for its adjoint), while the unrolled ``p2g``
        computes the grid: the same inputs and outputs, the same values."""
        lay, t, dev = self.layout, self.tables, self.device
        origin, nodes = wp.vec3(*lay.origin), wp.vec3i(*lay.nodes)
        params, rho, damping = (
            [t.params, t.rho, t.damping] if gathered is None else gathered.arrays()
        )
        per_particle = int(gathered is not None)
        ground_k = self.ground_k if self.ground_on else -1.0
        outputs = [grid.m, grid.mv, grid.gm, grid.pm]
        if stress is None:
            inputs = [src.x, src.v, src.C, src.F, src.plastic_J, self.volume, self.obj]
            inputs += [t.law_of, t.field_of, params, rho, damping, origin, lay.dx, self.dt]
            inputs += [nodes, int(lay.fields > 1), ground_k, t.k, per_particle]
            wp.launch(T.p2g_fused, self.n, inputs, outputs, device=dev)
            return
        inputs = [src.C, src.F, src.plastic_J, self.volume, self.obj, t.law_of, params]
        inputs += [damping, lay.dx, self.dt, t.k, per_particle]
        for law in self.laws:
            kernel = T.PARTICLE_STRESS[law]
            wp.launch(kernel, dim=self.n, inputs=inputs, outputs=[stress], device=dev)
        inputs = [src.x, src.v, src.C, stress, self.volume, self.obj, t.field_of, rho]
        inputs += [origin, lay.dx, nodes, int(lay.fields > 1), ground_k, t.k, per_particle]
        tape_unrolled = looped_on is None  # else the looped twin goes on the tape instead
        wp.launch(T.p2g, self.n, inputs, outputs, device=dev, record_tape=tape_unrolled)
        if not tape_unrolled:
            looped_on.record_launch(T.p2g_looped, self.n, 0, inputs, outputs, dev)

    def grid_update(
        self,
        src: ParticleState,
        grid: Grid,
        s: int,
        window: Window,
        gathered: ParticleParams | None = None,
        coefficients: NodeCoefficients | None = None,
        stress: wp.array | None = None,
        looped_on: wp.Tape | None = None,
    ) -> None:
        """P2G from src (``p2g``), then the grid's free velocity and boundaries, on the nodes of
        ``window`` (cleared beforehand): the grid velocities ``grid.v`` that G2P reads.

        ``gathered``: None, P2G reads the per-object tables (forward rollouts, re-simulation);
        else the particles' own copies of them (the taped replay, whose parameter adjoints then
        land on one address per particle: kernels.parameter_rows). ``coefficients``: likewise
        for grid_free_velocity's body acceleration and drag and grid_boundaries' friction and
        ground coefficients (the nodes' copies, ``per_node``) and the expression switches (a
        copy without a gradient). Same values, same results. ``stress``, ``looped_on``: see
        ``p2g``.
        """
        lay, t, dev = self.layout, self.tables, self.device
        nodes = wp.vec3i(*lay.nodes)
        self.p2g(src, grid, gathered, stress, looped_on)
        c = coefficients
        switch = None if c is None else c.expr_switch
        self.centre_sums(grid, window, switch)
        coef_inputs = [t.accel, t.drag, 0] if c is None else [c.accel, c.drag, 1]
        bound = t if c is None else c
        bound_inputs = [bound.friction, bound.ground_friction, bound.ground_restitution]
        wp.launch(
            K.grid_free_velocity,
            dim=self.batch * lay.fields * window.stride,
            inputs=[grid.m, grid.mv, *coef_inputs, self.expression_inputs(grid, s, switch)]
            + [self.dt, *window.inputs(), nodes, lay.fields],
            outputs=[grid.vs],
            device=dev,
        )
        wp.launch(
            K.grid_boundaries,
            dim=self.batch * window.stride,
            inputs=[grid.m, grid.vs, grid.gm, grid.pm, lay.fields, nodes, self.ground_on]
            + [self.ground_k, self.ground_layers, *bound_inputs, int(c is not None)]
            + window.inputs(),
            outputs=[grid.v],
            device=dev,
        )

    # -- forward ----------------------------------------------------------------------------
    def _frame_launches(self) -> None:
        self.flag.fill_(K.NO_FLAG)
        src, dst, sums = self.a, self.b, self.centres
        for s in range(self.substeps):
            window = self.substep_window(src, s)
            self.grid.clear(window, sums=sums)
            self.substep(src, dst, self.grid, s, window)
            src, dst = dst, src
        if src is not self.a:  # odd substep count: the result sits in b
            self.a.copy_from(src)

    def advance_frame(self, frame: int, *, check: bool = True) -> None:
        """Advance state ``a`` by one video frame; raise SimulationDiverged if it blew up
        (``check``; batched runs read ``divergences`` per member instead).

        On CUDA the frame's launches are captured once (per value of ``centres``) into a graph
        and replayed, so the substep loop costs no Python per substep (unless the window is
        found on the host: ``graphed``).
        """
        self.begin_frame(frame, self.grid)
        if self.graphed:
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
