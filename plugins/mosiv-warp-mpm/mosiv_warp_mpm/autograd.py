"""Gradients of a rollout as a torch.autograd.Function, with memory bounded by frames.

Forward keeps one particle state per frame boundary (no tape). Backward walks the frames from
last to first; for each frame it re-simulates the frame from its checkpoint into per-substep
state buffers, then replays the substeps in reverse, each under its own short Warp tape, carrying
the adjoint of the particle state. The replay reruns only the grid update (the particles' stress
impulses and the scatter, in the split form of transfer_kernels.py: the grid and the impulses
are shared, so later substeps overwrote them); G2P goes on the tape without running, its output
already in the next state buffer. Because each substep writes a fresh state buffer and each
tape is consumed before the shared grid and stress buffer are reused, nothing a tape recorded
is overwritten before its adjoint runs. Memory: checkpoints grow with frames; the workspace
(substeps + 1 particle states, one grid and one stress buffer) is the same for every frame and
does not grow with the number of frames.

On CUDA one frame's adjoint (re-simulation, tapes and their reverse launches: some 40 launches
per substep, more with several laws) is captured once into a graph and replayed for every frame
and, because the simulator keeps the run, for every later rollout of the same layout: launched
from Python it cost about 2 ms per substep, far more than the kernels themselves.

Parameter gradients: in Warp the adjoint of a read a[i] is atomic_add(adj_a[i]), so taped
kernels reading the per-object tables in every particle thread would add every particle's
contribution into the same few addresses each substep: contended atomics (they dominated the
adjoint P2G and G2P on a GPU) summed in float32 in schedule order. Instead each particle gets its
own copy of its object's law parameters, density and viscosity once per backward
(state.ParticleParams, ``begin_parameters``), the taped P2G and G2P read the copy (their
adjoints add into one address per particle), and after each frame the per-particle gradients
are summed per object in float64 (``collect_parameter_gradients``). The same for the grid: the
taped grid_free_velocity read its member's body acceleration and drag in every node with mass,
and grid_boundaries its objects' friction there and its ground friction and restitution on the
ground layers, so each node gets its own copy (state.NodeCoefficients, 48 bytes a node and 16
a ground-layer node), summed per member and object in float64 after each frame;
grid_free_velocity reads the expression switches, whose gradient is zero (they are only
compared), from a copy without a gradient, so no atomics at all. Still read per node from the
tables, their adjoints float32 atomics onto a few addresses: the expression's coefficients.
"""

from __future__ import annotations

import torch
import warp as wp

from mosiv_warp_mpm import kernels as K
from mosiv_warp_mpm.state import Grid, NodeCoefficients, ParticleParams, ParticleState, Window


class WarpRollout(torch.autograd.Function):
    """(x0 [N,3], v0 [N,3], theta [P]) -> (positions [T+1,N,3], velocities [T+1,N,3]); for a
    run of B members (batched.py) x0 and v0 hold the B members' particles one after the other
    and theta is [B, P], one row per member."""

    @staticmethod
    def forward(ctx, run, simulator, frames: int, x0, v0, theta):
        pos, vel = run.forward(x0, v0, theta, frames, keep=True)
        ctx.run, ctx.simulator, ctx.frames = run, simulator, frames
        ctx.theta_device, ctx.theta_shape = theta.device, theta.shape
        simulator.last_memory = {"checkpoint_bytes": run.checkpoint_bytes()}
        ctx.mark_non_differentiable(vel)
        return pos, vel

    @staticmethod
    def backward(ctx, grad_pos, grad_vel):
        run = ctx.run
        ws = run.backward_workspace()
        torch_dev = wp.device_to_torch(run.device)
        run.tables.zero_grad()
        ws.carry.zero_grad()
        if grad_pos is None:
            grad_pos = torch.zeros(ctx.frames + 1, run.n, 3, device=torch_dev)
        grad_pos = grad_pos.to(torch_dev, torch.float32)
        carry_x = wp.to_torch(ws.carry.x.grad)
        ws.begin_parameters(run)
        try:
            for f in range(ctx.frames, 0, -1):
                carry_x += grad_pos[f]
                _warp_waits_for_torch(run.device)  # the graph reads carry_x
                ws.adjoint_frame(run, run.checkpoints[f - 1], frame=f)
                ws.collect_parameter_gradients(run)
        finally:
            run.release_checkpoints()  # the run may now serve the next differentiable rollout
        carry_x += grad_pos[0]
        ctx.simulator.last_memory["backward_workspace_bytes"] = ws.nbytes()
        run._sample_memory()
        grad_x0 = wp.to_torch(ws.carry.x.grad).clone()
        grad_v0 = wp.to_torch(ws.carry.v.grad).clone()
        grad_theta = run.tables.grad_theta().to(ctx.theta_device).view(ctx.theta_shape)
        return None, None, None, grad_x0, grad_v0, grad_theta


def _warp_waits_for_torch(device: str) -> None:
    """Order Warp's stream after work already queued on torch's current stream (CUDA only)."""
    if wp.get_device(device).is_cuda:
        torch_stream = torch.cuda.current_stream(wp.device_to_torch(device))
        wp.get_stream(device).wait_stream(wp.stream_from_torch(torch_stream))


def _torch_waits_for_warp(device: str) -> None:
    """Order torch's current stream after work already queued on Warp's stream (CUDA only)."""
    if wp.get_device(device).is_cuda:
        torch_stream = torch.cuda.current_stream(wp.device_to_torch(device))
        torch_stream.wait_stream(wp.stream_to_torch(wp.get_stream(device)))


def segment_sums(values: torch.Tensor, index: torch.Tensor, count: int) -> torch.Tensor:
    """Sum the rows of ``values`` by segment.

    Args:
        values: [N, C] rows (float64 for an accurate sum).
        index: [N] segment of each row, in [0, count).
        count: number of segments.

    Returns:
        [count, C]: row s is the sum of the rows whose index is s. One masked torch.sum per
        segment (a tree reduction in a fixed order on every device, where index_add_ would add
        with atomics in schedule order on CUDA); the segments are a rollout's few objects.
    """
    rows = [torch.where((index == s)[:, None], values, 0.0).sum(0) for s in range(count)]
    return torch.stack(rows) if rows else values.new_zeros(0, values.shape[1])


class BackwardWorkspace:
    """Buffers of one frame's adjoint: a particle state per substep boundary (values and
    gradients), one grid, one buffer of stress impulses and ``carry``, whose gradient holds
    d(loss)/d(state) at a frame boundary. Kept by the run so the captured graph stays valid
    between rollouts."""

    def __init__(self, run):
        n, dev = run.n, run.device
        self.work = [ParticleState(n, dev, requires_grad=True) for _ in range(run.substeps + 1)]
        self.grid = Grid(run.layout, dev, requires_grad=True, batch=run.batch)
        self.carry = ParticleState(n, dev, requires_grad=True)
        #: the taped replay's stress impulses (transfer_kernels.particle_stress), one substep's
        #: at a time: each tape is consumed before the next substep's replay rewrites them
        self.stress = wp.zeros(n, dtype=wp.mat33, device=dev, requires_grad=True)
        #: each particle's copy of its object's parameters, read by the taped P2G and G2P
        self.gathered = ParticleParams(n, dev)
        #: each grid node's copy of its member's body acceleration and drag, its object's
        #: friction and (on the ground layers) its member's ground coefficients, read by the
        #: taped grid kernels, and the expression switches without a gradient
        self.node_coefficients = NodeCoefficients(run.layout, run.batch, run.ground_layers, dev)
        #: False: the taped kernels read the per-object tables instead, every particle's and
        #: node's parameter adjoint added by float32 atomics into the tables' few gradient
        #: entries each substep (the accumulation before the copies; tests and warp_profile.py
        #: compare)
        self.gather_parameters = True
        #: True: the replay's scatter goes on the tape as transfer_kernels.p2g_looped, whose
        #: adjoint replays one node at a time; False: as the unrolled p2g that ran
        self.looped_scatter_adjoint = True
        #: float64 [B K, 7] per-object sums of the law parameters', density's and viscosity's
        #: gradients over the frames back-propagated so far, [B, 7] per-member sums of the body
        #: acceleration's, drag's, ground friction's and restitution's, and [B F] per-field
        #: sums of the friction's (``collect_parameter_gradients``)
        self._parameter_sums: torch.Tensor | None = None
        self._coefficient_sums: torch.Tensor | None = None
        self._friction_sums: torch.Tensor | None = None
        self._obj: torch.Tensor | None = None
        #: the captured adjoint, per value of MPMRun.centres, gather_parameters and
        #: looped_scatter_adjoint (the launches differ: a graph captured with the copies would
        #: replay them after the switch to the tables, and leave the tables' gradients at zero)
        self._graphs: dict[tuple[bool, bool, bool], wp.Graph] = {}

    def nbytes(self) -> int:
        grid = sum(a.capacity * 2 for a in self.grid.arrays())
        copies = self.gathered.nbytes() + self.node_coefficients.nbytes()
        stress = self.stress.capacity * 2
        return sum(w.nbytes() for w in self.work) + grid + copies + stress

    def parameter_copies(self) -> list[wp.array]:
        """The particles' and the nodes' parameter copies that have gradients."""
        return [*self.gathered.arrays(), *self.node_coefficients.arrays()]

    def begin_parameters(self, run) -> None:
        """Before a rollout's backward (after ``run.tables.zero_grad``): copy each particle's
        object's law parameters, density and viscosity into ``gathered`` and each node's
        coefficients and the expression switches into ``node_coefficients`` (the tables hold
        the rollout's values until its backward ends), zero their gradients and the sums."""
        if not self.gather_parameters:
            return
        t = run.tables
        wp.launch(
            K.gather_particle_params,
            dim=run.n,
            inputs=[run.obj, t.params, t.rho, t.damping, t.k],
            outputs=self.gathered.arrays(),
            device=run.device,
        )
        self._gather_node_coefficients(run)
        for a in self.parameter_copies():
            a.grad.zero_()
        self._obj = wp.to_torch(run.obj).long()
        dev = wp.device_to_torch(run.device)
        self._parameter_sums = torch.zeros(t.batch * t.k, 7, dtype=torch.float64, device=dev)
        self._coefficient_sums = torch.zeros(t.batch, 7, dtype=torch.float64, device=dev)
        fields = t.batch * run.layout.fields
        self._friction_sums = torch.zeros(fields, dtype=torch.float64, device=dev)

    def _gather_node_coefficients(self, run) -> None:
        """The nodes' copies of the tables' grid coefficients (state.NodeCoefficients)."""
        t, c = run.tables, self.node_coefficients
        wp.launch(
            K.gather_node_coefficients,
            dim=c.accel.shape[0],
            inputs=[t.accel, t.drag, t.friction, run.layout.size, c.field_nodes],
            outputs=[c.accel, c.drag, c.friction],
            device=run.device,
        )
        wp.launch(
            K.gather_ground_coefficients,
            dim=c.ground_friction.shape[0],
            inputs=[t.ground_friction, t.ground_restitution, c.member_rows],
            outputs=[c.ground_friction, c.ground_restitution],
            device=run.device,
        )
        wp.copy(c.expr_switch, t.expr_switch)

    def collect_parameter_gradients(self, run) -> None:
        """After a frame's adjoint: sum the particles' parameter gradients per object and the
        nodes' coefficient gradients per member or field in float64 into the rollout's sums,
        zero them for the next frame, and write the sums into the tables' gradients (float32;
        viscosity summed over each member's objects), where ObjectTables.grad_theta reads
        them. The expression switches' gradient stays the tables' (zero: only compared)."""
        if not self.gather_parameters:
            return
        _torch_waits_for_warp(run.device)
        g = self.gathered
        grads = [wp.to_torch(a.grad) for a in g.arrays()]
        per_particle = torch.cat([grads[0], grads[1][:, None], grads[2][:, None]], dim=1)
        sums = self._parameter_sums
        sums += segment_sums(per_particle.double(), self._obj, sums.shape[0])
        for grad in grads:
            grad.zero_()
        t = run.tables
        wp.to_torch(t.params.grad).copy_(sums[:, :5])
        wp.to_torch(t.rho.grad).copy_(sums[:, 5])
        wp.to_torch(t.damping.grad).copy_(sums[:, 6].view(t.batch, t.k).sum(1))
        self._collect_coefficient_gradients(run)
        _warp_waits_for_torch(run.device)  # later Warp work reads or zeroes these arrays

    def _collect_coefficient_gradients(self, run) -> None:
        """The nodes' coefficient gradients summed in float64 into the rollout's sums and the
        tables' gradients, the nodes' zeroed: body acceleration, drag and the ground's per
        member (the copies are member-major: member b's nodes, or its ground-layer rows, are
        one block), friction per field (the friction row grid_boundaries reads for field f of
        member b is b F + f: each object's own in multi-field mode, unused in single-field
        mode). One torch.sum per array, a fixed-order reduction, where index_add_ would add in
        schedule order on CUDA.
        """
        t, c = run.tables, self.node_coefficients
        grads = [wp.to_torch(a.grad) for a in c.arrays()]
        accel, drag, friction, ground_friction, ground_restitution = grads
        per_member = [
            accel.view(t.batch, -1, 3),
            drag.view(t.batch, -1, 2),
            ground_friction.view(t.batch, c.member_rows, 1),  # no rows without a ground
            ground_restitution.view(t.batch, c.member_rows, 1),
        ]
        sums = self._coefficient_sums
        sums += torch.cat([g.sum(1, dtype=torch.float64) for g in per_member], dim=1)
        self._friction_sums += friction.view(-1, c.field_nodes).sum(1, dtype=torch.float64)
        for grad in grads:
            grad.zero_()
        wp.to_torch(t.accel.grad).copy_(sums[:, :3])
        wp.to_torch(t.drag.grad).copy_(sums[:, 3:5].reshape(-1))
        wp.to_torch(t.ground_friction.grad).copy_(sums[:, 5])
        wp.to_torch(t.ground_restitution.grad).copy_(sums[:, 6])
        rows = self._friction_sums.shape[0]  # B F: every row in multi-field mode
        wp.to_torch(t.friction.grad)[:rows].copy_(self._friction_sums)

    def adjoint_frame(self, run, start: ParticleState, *, frame: int) -> None:
        """carry.grad: d(loss)/d(state at the frame's end) -> d(loss)/d(state at its start);
        parameter gradients accumulate in run.tables. Raises SimulationDiverged if the
        re-simulated frame blew up."""
        self.work[0].copy_from(start)
        run.begin_frame(frame, self.grid)
        if run.graphed:
            key = (run.centres, self.gather_parameters, self.looped_scatter_adjoint)
            graph = self._graphs.get(key)
            if graph is None:
                with wp.ScopedCapture(device=run.device, force_module_load=True) as capture:
                    self._launches(run)
                graph = self._graphs[key] = capture.graph
            wp.capture_launch(graph)
        else:
            self._launches(run)
        run.check_divergence(frame)

    def _launches(self, run) -> None:
        """Everything after loading work[0]: re-simulate the frame keeping every substep's
        state, then run the substeps' adjoints in reverse, one short tape each. The phases are
        separate methods so that benchmarks/warp_profile.py can time each of them."""
        windows = self.resimulate(run)
        self.seed()
        for s in range(run.substeps - 1, -1, -1):
            self.prepare_substep(run, s, windows[s])
            self.record_substep(run, s, windows[s]).backward()
            # no tape.reset(): it would zero every gradient, parameters included
        self.finish()

    def resimulate(self, run) -> list[Window]:
        """Advance work[0] through the frame into work[1..S] (one shared grid); returns each
        substep's node window (its box in the run's table, row s, until the next frame)."""
        work, grid = self.work, self.grid
        run.flag.fill_(K.NO_FLAG)
        windows = []
        for s in range(run.substeps):
            windows.append(run.substep_window(work[s], s))
            grid.clear(windows[s], sums=run.centres)
            run.substep(work[s], work[s + 1], grid, s, windows[s])
        return windows

    def seed(self) -> None:
        """d(loss)/d(state at the frame's end), held by ``carry``, onto the last substep's state."""
        self.work[-1].copy_grad_from(self.carry)

    def prepare_substep(self, run, s: int, window: Window) -> None:
        """Zero what substep ``s``'s adjoint accumulates into (its input state's, the stress
        impulses' and the grid's gradients) and the grid values its replay accumulates into."""
        self.work[s].zero_grad()
        self.stress.grad.zero_()
        self.grid.zero_grad(window, sums=run.centres)
        self.grid.clear(window, sums=run.centres)

    def record_substep(self, run, s: int, window: Window) -> wp.Tape:
        """Substep ``s`` (work[s] -> work[s + 1]) on a fresh tape, ready for ``backward``: its
        grid update runs again, rebuilding the grid that later substeps overwrote (the scatter
        recorded as its looped form with ``looped_scatter_adjoint``); its G2P is only recorded,
        since the re-simulation already wrote G2P's result into work[s + 1].
        Both read the particles' parameter copies (``gathered``) and the grid the nodes' copies
        (``node_coefficients``) unless ``gather_parameters`` is off."""
        gathered = self.gathered if self.gather_parameters else None
        coefficients = self.node_coefficients if self.gather_parameters else None
        tape = wp.Tape()
        looped_on = tape if self.looped_scatter_adjoint else None
        with tape:
            run.grid_update(
                self.work[s], self.grid, s, window, gathered, coefficients, self.stress, looped_on
            )
        run.record_g2p(tape, self.work[s], self.work[s + 1], self.grid, s, gathered)
        return tape

    def finish(self) -> None:
        """d(loss)/d(state at the frame's start) from work[0] into ``carry``."""
        self.carry.copy_grad_from(self.work[0])
