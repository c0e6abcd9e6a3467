"""Warp buffers of one rollout: particle states, the multi-field grid and per-object parameters.

Everything here is plain storage; kernels live in kernels.py and orchestration in simulator.py.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
import warp as wp

from mosiv_framework.particle_order import cell_keys, interleaved_cell_order
from mosiv_framework.types import World
from mosiv_warp_mpm.expression_kernels import N_FEATURES
from mosiv_warp_mpm.kernels import PAD, clear_box
from mosiv_warp_mpm.laws import N_SLOTS, vec5

PAD_CELLS = int(PAD)


@dataclass(frozen=True)
class GridLayout:
    """Regular grid over the scene domain plus PAD cells on each side.

    dx (m) = longest domain side / grid; ``nodes`` = node counts per axis; ``origin`` (m) is the
    position of node (0, 0, 0); ``fields`` = velocity fields (objects, or 1 when single-field).
    """

    dx: float
    origin: tuple[float, float, float]
    nodes: tuple[int, int, int]
    fields: int

    @classmethod
    def for_world(cls, world: World, *, grid: int, fields: int) -> GridLayout:
        dx = world.extent / grid
        cells = [
            max(1, math.ceil((u - lo) / dx - 1e-6)) + 2 * PAD_CELLS
            for lo, u in zip(world.domain_lower, world.domain_upper)
        ]
        origin = tuple(lo - PAD_CELLS * dx for lo in world.domain_lower)
        return cls(dx=dx, origin=origin, nodes=tuple(c + 1 for c in cells), fields=fields)

    @property
    def nodes_per_field(self) -> int:
        return self.nodes[0] * self.nodes[1] * self.nodes[2]

    @property
    def size(self) -> int:
        return self.fields * self.nodes_per_field

    def cell_keys(self, positions: torch.Tensor) -> torch.Tensor:
        """Linear cell index of each position [N, 3] (for sorting particles by cell)."""
        return cell_keys(positions, self.origin, self.dx, self.nodes)

    def scatter_order(self, positions: torch.Tensor) -> torch.Tensor:
        """A particle permutation for P2G (particle_order.interleaved_cell_order): cell by cell,
        but the k-th particles of all cells come before the (k+1)-th ones, so that the
        scatter's atomic adds seldom collide inside a GPU warp (measured in
        benchmarks/warp_profile.py)."""
        return interleaved_cell_order(self.cell_keys(positions))


class ParticleState:
    """Per-particle state: position x (m), velocity v (m/s), affine C (1/s), elastic F,
    plastic volume ratio plastic_J."""

    FIELDS = ("x", "v", "C", "F", "plastic_J")

    def __init__(self, n: int, device, *, requires_grad: bool = False):
        kw = {"device": device, "requires_grad": requires_grad}
        self.x = wp.zeros(n, dtype=wp.vec3, **kw)
        self.v = wp.zeros(n, dtype=wp.vec3, **kw)
        self.C = wp.zeros(n, dtype=wp.mat33, **kw)
        self.F = wp.zeros(n, dtype=wp.mat33, **kw)
        self.plastic_J = wp.zeros(n, dtype=float, **kw)

    def arrays(self) -> list[wp.array]:
        return [getattr(self, f) for f in self.FIELDS]

    def copy_from(self, other: ParticleState) -> None:
        for dst, src in zip(self.arrays(), other.arrays()):
            wp.copy(dst, src)

    def copy_grad_from(self, other: ParticleState) -> None:
        for dst, src in zip(self.arrays(), other.arrays()):
            wp.copy(dst.grad, src.grad)

    def zero_grad(self) -> None:
        for a in self.arrays():
            a.grad.zero_()

    def set_initial(self, x0: torch.Tensor, v0: torch.Tensor) -> None:
        """x, v from torch [N, 3]; F = I, C = 0, plastic_J = 1 (rest state of frame 0)."""
        wp.copy(self.x, wp.from_torch(x0.detach().float().contiguous(), dtype=wp.vec3))
        wp.copy(self.v, wp.from_torch(v0.detach().float().contiguous(), dtype=wp.vec3))
        eye = np.broadcast_to(np.eye(3, dtype=np.float32), (self.F.shape[0], 3, 3))
        self.F.assign(eye)
        self.C.zero_()
        self.plastic_J.fill_(1.0)

    def nbytes(self) -> int:
        """Bytes of the values (and gradients, when allocated) held by this state."""
        total = 0
        for a in self.arrays():
            total += a.capacity
            if a.grad is not None:
                total += a.grad.capacity
        return total


class ParticleParams:
    """Each particle's copy of the per-object values P2G and G2P read: law parameters ``params``
    [N] vec5, density ``rho`` [N] (kg/m^3) and material_damping viscosity ``damping`` [N]
    (Pa s), with gradients. The taped P2G and G2P read these (kernels.parameter_rows)
    instead of ObjectTables, so that their parameter adjoints add into one address per particle
    rather than into a handful shared by all particles (autograd.BackwardWorkspace reduces them
    per object). Memory: 7 float32 values and 7 gradients, 56 bytes a particle (56 MB at 1M
    particles), besides a backward workspace of about 10 KB a particle at 50 substeps."""

    FIELDS = ("params", "rho", "damping")

    def __init__(self, n: int, device):
        kw = {"device": device, "requires_grad": True}
        self.params = wp.zeros(n, dtype=vec5, **kw)
        self.rho = wp.zeros(n, dtype=float, **kw)
        self.damping = wp.zeros(n, dtype=float, **kw)

    def arrays(self) -> list[wp.array]:
        return [getattr(self, f) for f in self.FIELDS]

    def nbytes(self) -> int:
        """Bytes of the values and gradients."""
        return sum(a.capacity * (2 if a.grad is not None else 1) for a in self.arrays())


class NodeCoefficients:
    """Each grid node's copy of the per-member and per-object coefficients that the grid kernels
    read, with gradients: for grid_free_velocity its member's body acceleration ``accel`` [S]
    vec3 (m/s^2) and drag ``drag`` [2 S] (node n's linear coefficient (1/s) at 2 n, quadratic
    (1/m) at 2 n + 1), for grid_boundaries the contact ``friction`` [S] of its field's object,
    over the S = batch x GridLayout.size flat nodes (every field's, PAD layers included); the
    ground's ``ground_friction`` and ``ground_restitution`` [G] only on the ground layers, the
    nodes where grid_boundaries reads them (k <= MPMRun.ground_k: ``layers`` of them), once per
    member and spatial node, G = batch x NX x NY x layers (kernels.ground_row); and
    ``expr_switch`` [2 B], a copy of the expression switches without a gradient.

    The taped grid kernels read these instead of ObjectTables (their ``per_node`` flag), so that
    the coefficients' adjoints add into one address per node rather than into the member's or
    object's few, shared by every node with mass (autograd.BackwardWorkspace sums them per
    member and object). The switches are only compared (> 0.5), so their gradient is zero: a
    copy without one makes Warp skip the zero atomics that the tables' switch reads issued per
    node.

    Memory: 6 float32 values and 6 gradients, 48 bytes a node, and 16 bytes a ground-layer node
    per member: at grid 128 on the bench's cubic domain 135^3 = 2.46 M nodes per field (PAD
    layers included), 118 MB a field, and 6 ground layers of 135^2, 1.7 MB. The copies cover
    the whole grid even where the CPU visits a window of it (state.NodeBox): the window moves
    every substep, and nodes outside it are only never read.
    """

    FIELDS = ("accel", "drag", "friction", "ground_friction", "ground_restitution")

    def __init__(self, layout: GridLayout, batch: int, layers: int, device):
        kw = {"device": device, "requires_grad": True}
        nodes = batch * layout.size
        #: nodes per field, and ground-layer rows per member (kernels.gather_*_coefficients)
        self.field_nodes = layout.nodes_per_field
        self.member_rows = layout.nodes[0] * layout.nodes[1] * layers
        self.accel = wp.zeros(nodes, dtype=wp.vec3, **kw)
        self.drag = wp.zeros(2 * nodes, dtype=float, **kw)
        self.friction = wp.zeros(nodes, dtype=float, **kw)
        self.ground_friction = wp.zeros(batch * self.member_rows, dtype=float, **kw)
        self.ground_restitution = wp.zeros(batch * self.member_rows, dtype=float, **kw)
        self.expr_switch = wp.zeros(2 * batch, dtype=float, device=device)

    def arrays(self) -> list[wp.array]:
        """The copies with gradients, in FIELDS' order."""
        return [getattr(self, f) for f in self.FIELDS]

    def nbytes(self) -> int:
        """Bytes of the values and gradients (the switches' copy included)."""
        grads = sum(a.capacity * 2 for a in self.arrays())
        return grads + self.expr_switch.capacity


@dataclass(frozen=True)
class NodeBox:
    """The block of grid nodes a substep's grid kernels visit: ``lo`` (first node per axis)
    and ``dims`` (node counts per axis), the same block in every field.

    Only nodes in some particle's 3x3x3 stencil hold mass, and only those are read back. On the
    CPU, where Warp runs each kernel thread in turn, sweeping the whole grid cost 75 % of a
    rollout of 278 particles on a 48-cell grid; the box around the particles is a few percent
    of it (docs/BENCHMARKS.md, Simulator speed, CPU). On CUDA the run finds the same box on
    the device by default (MPMRun's ``window``: the table of Window), so that one frame stays
    one captured graph.
    """

    lo: tuple[int, int, int]
    dims: tuple[int, int, int]

    @classmethod
    def whole(cls, layout: GridLayout) -> NodeBox:
        return cls((0, 0, 0), tuple(layout.nodes))

    @classmethod
    def around(cls, positions: np.ndarray, layout: GridLayout) -> NodeBox:
        """The nodes of every stencil of ``positions`` [N, 3] (m), plus one node of margin
        each side, so that a stencil base rounded differently on the host than in the kernel
        still falls inside."""
        if positions.shape[0] == 0:
            return cls.whole(layout)
        xl = (positions.astype(np.float64) - np.asarray(layout.origin)) / layout.dx
        base = np.floor(xl - 0.5).astype(np.int64)  # kernels.cell_base
        return cls.from_bases(base.min(axis=0), base.max(axis=0), layout)

    @classmethod
    def from_bases(cls, low: np.ndarray, high: np.ndarray, layout: GridLayout) -> NodeBox:
        """The nodes of every stencil whose base (kernels.cell_base) lies between ``low`` and
        ``high`` per axis, plus one node of margin each side, clipped to the grid; the whole
        grid if ``low`` exceeds ``high`` (no particle counted)."""
        low, high = np.asarray(low, dtype=np.int64), np.asarray(high, dtype=np.int64)
        if (low > high).any():
            return cls.whole(layout)
        nodes = np.asarray(layout.nodes)
        lo = np.clip(low - 1, 0, nodes - 1)
        hi = np.clip(high + 3, 0, nodes - 1)  # stencil base + 2, plus the margin
        return cls(tuple(int(v) for v in lo), tuple(int(v) for v in hi - lo + 1))

    @property
    def count(self) -> int:
        """Nodes per field."""
        return self.dims[0] * self.dims[1] * self.dims[2]

    def is_whole(self, layout: GridLayout) -> bool:
        return self.lo == (0, 0, 0) and self.dims == tuple(layout.nodes)


#: threads per field of a grid kernel over a box found on the device (Window): about half of
#: an H200's resident threads, so a body's box keeps the GPU busy while a small one's launch
#: stays short; each thread takes every WINDOW_THREADS-th node of the box
WINDOW_THREADS = 2**17


@dataclass(frozen=True)
class Window:
    """The nodes a substep's grid kernels visit, as they read them (node_window): row ``row``
    of the run's box table ``boxes`` (MPMRun.boxes: per substep, the box's first node and node
    counts), launched with ``stride`` threads per field, thread t taking the box's nodes
    t % stride, t % stride + stride, ... of field t // stride.

    A box the host knows (NodeBox) is written into its row and launched with its own node
    count, one node a thread; a box the device finds from the particles (MPMRun's window
    "device") is launched with min(whole grid, WINDOW_THREADS) threads per field whatever its
    size, so that the launch sizes stay the same for every box and a frame stays one captured
    CUDA graph. ``whole``: the box is the whole grid, where clearing is a memset per array.
    """

    boxes: wp.array
    row: int
    stride: int
    whole: bool = False

    def inputs(self) -> list:
        """The grid kernels' window arguments: boxes, row, stride."""
        return [self.boxes, self.row, self.stride]


class Grid:
    """Per-field node mass (kg), momentum (kg m/s), mass gradient (kg/m), free and final
    velocities (m/s); flat arrays of GridLayout.size per batch member, ``batch`` grids one
    after the other (kernels.py, batched rollouts). Per field also its mass, first moment and
    momentum and the sums over the other fields' centres (the expression term's relative
    features, expression_kernels.py)."""

    def __init__(self, layout: GridLayout, device, *, requires_grad: bool = False, batch=1):
        kw = {"device": device, "requires_grad": requires_grad}
        size = batch * layout.size
        self.m = wp.zeros(size, dtype=float, **kw)
        self.mv = wp.zeros(size, dtype=wp.vec3, **kw)
        self.gm = wp.zeros(size, dtype=wp.vec3, **kw)
        self.pm = wp.zeros(size, dtype=wp.vec3, **kw)
        self.vs = wp.zeros(size, dtype=wp.vec3, **kw)
        self.v = wp.zeros(size, dtype=wp.vec3, **kw)
        fields = batch * layout.fields
        self.moment_m = wp.zeros(fields, dtype=float, **kw)
        self.moment_mx = wp.zeros(fields, dtype=wp.vec3, **kw)
        self.moment_mv = wp.zeros(fields, dtype=wp.vec3, **kw)
        self.rel_p = wp.zeros(fields, dtype=wp.vec3, **kw)
        self.rel_v = wp.zeros(fields, dtype=wp.vec3, **kw)
        self.rel_n = wp.zeros(fields, dtype=float, **kw)
        self.layout, self.device, self.batch = layout, device, batch
        #: whether the per-field sums may hold values of an earlier substep (``clear``'s
        #: ``sums``); ``clear_sums`` zeroes them
        self.sums_written = False

    def arrays(self) -> list[wp.array]:
        return [self.m, self.mv, self.gm, self.pm, self.vs, self.v]

    def field_arrays(self) -> list[wp.array]:
        """The per-field sums (one entry per field, not per node)."""
        return [self.moment_m, self.moment_mx, self.moment_mv, self.rel_p, self.rel_v, self.rel_n]

    def clear(self, window: Window, *, sums: bool) -> None:
        """Zero what P2G accumulates into, on the nodes of ``window``, and, when this substep
        computes them (``sums``: MPMRun.centres), the per-field sums."""
        arrays = [self.m, self.mv, self.gm, self.pm, self.vs, self.v]
        self._zero(arrays, window, velocities=False)
        if sums:
            for a in self.field_arrays():
                a.zero_()

    def clear_sums(self) -> None:
        """Zero the per-field sums' values, for substeps that read them without computing them
        (an expression without the other objects' features multiplies them by 0)."""
        for a in self.field_arrays():
            a.zero_()
        self.sums_written = False

    def zero_grad(self, window: Window, *, sums: bool) -> None:
        """Zero the gradients of the nodes of ``window`` and, with ``sums``, of the per-field
        sums (without, nothing reads theirs: only the sums' kernels back-propagate them)."""
        if self.m.grad is not None:
            self._zero([a.grad for a in self.arrays()], window, velocities=True)
            if sums:
                for a in self.field_arrays():
                    a.grad.zero_()

    def _zero(self, arrays: list[wp.array], window: Window, *, velocities: bool) -> None:
        if window.whole:  # a memset per array
            for a in arrays[: None if velocities else 4]:
                a.zero_()
            return
        wp.launch(
            clear_box,
            dim=self.batch * self.layout.fields * window.stride,
            inputs=[*window.inputs(), wp.vec3i(*self.layout.nodes), *arrays, int(velocities)],
            device=self.device,
        )


class ObjectTables:
    """Per-object constants (law id, velocity field) and differentiable parameters.

    ``params`` [K] vec5 law parameters, ``rho`` [K] kg/m^3, ``friction`` [K], ``ground_friction``
    [1], ``accel`` [1] body acceleration (gravity + wind, m/s^2), ``drag`` [2] (linear 1/s,
    quadratic 1/m), ``damping`` [1] Kelvin-Voigt viscosity of ``material_damping`` (Pa s),
    ``ground_restitution`` [1] (dimensionless), ``expr_switch`` [2] (the expression term is on;
    it uses the other objects) and ``expr_coef`` [N_FEATURES] vec3 (its coefficients,
    packing.pack_expression). The flat torch vector ``theta`` of the autograd function maps
    onto them in this order.

    With ``batch`` = B members every table holds B of these blocks, member-major (per-object
    tables B K rows, ``drag`` 2 B values), and ``law_ids``/``fields`` list all B K objects;
    ``theta`` is then [B, P], one row per member.
    """

    def __init__(self, law_ids: list[int], fields: list[int], device, *, batch: int = 1):
        if len(law_ids) % batch:
            raise ValueError(f"{len(law_ids)} object laws do not split into {batch} members")
        k = len(law_ids) // batch
        self.k, self.batch = k, batch
        self.law_of = wp.array(np.array(law_ids, dtype=np.int32), dtype=int, device=device)
        self.field_of = wp.array(np.array(fields, dtype=np.int32), dtype=int, device=device)
        kw = {"device": device, "requires_grad": True}
        self.params = wp.zeros(batch * k, dtype=vec5, **kw)
        self.rho = wp.zeros(batch * k, dtype=float, **kw)
        self.friction = wp.zeros(batch * k, dtype=float, **kw)
        self.ground_friction = wp.zeros(batch, dtype=float, **kw)
        self.accel = wp.zeros(batch, dtype=wp.vec3, **kw)
        self.drag = wp.zeros(2 * batch, dtype=float, **kw)
        self.damping = wp.zeros(batch, dtype=float, **kw)
        self.ground_restitution = wp.zeros(batch, dtype=float, **kw)
        self.expr_switch = wp.zeros(2 * batch, dtype=float, **kw)
        self.expr_coef = wp.zeros(batch * N_FEATURES, dtype=wp.vec3, **kw)
        #: whether some member has the expression term, and whether some member's expression
        #: uses the other objects (set by ``load``): the run launches what the term needs only then
        self.expression = False
        self.relative = False

    def _parts(self) -> list[tuple[wp.array, int]]:
        """(table, its values per member) in theta's order."""
        k = self.k
        return [
            (self.params, k * N_SLOTS),
            (self.rho, k),
            (self.friction, k),
            (self.ground_friction, 1),
            (self.accel, 3),
            (self.drag, 2),
            (self.damping, 1),
            (self.ground_restitution, 1),
            (self.expr_switch, 2),
            (self.expr_coef, 3 * N_FEATURES),
        ]

    @staticmethod
    def theta_size(k: int) -> int:
        return k * N_SLOTS + 2 * k + 1 + 3 + 2 + 1 + 1 + 2 + 3 * N_FEATURES

    def load(self, theta: torch.Tensor) -> None:
        """Copy the float32 parameter vector [P] (or [B, P], one row per member) into the
        Warp tables."""
        rows = theta.detach().float().cpu().numpy().reshape(self.batch, -1)
        at = 0
        for arr, size in self._parts():
            block = rows[:, at : at + size]
            arr.assign(block.reshape(arr.numpy().shape))
            if arr is self.expr_switch:
                self.expression = bool((block[:, 0] > 0.5).any())
                self.relative = bool((block[:, 1] > 0.5).any())
            at += size

    def zero_grad(self) -> None:
        for arr, _ in self._parts():
            arr.grad.zero_()

    def grad_theta(self) -> torch.Tensor:
        """The accumulated gradients as a flat float32 torch vector (CPU), theta's layout."""
        rows = [arr.grad.numpy().reshape(self.batch, -1) for arr, _ in self._parts()]
        return torch.from_numpy(np.concatenate(rows, axis=1).reshape(-1))
