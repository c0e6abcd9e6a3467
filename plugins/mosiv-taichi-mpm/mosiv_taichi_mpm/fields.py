"""Taichi field allocation for one problem size (particles, objects, grid, substeps).

All fields of a problem live in one SNode tree built with ``ti.FieldsBuilder`` so that they can
be freed together (``destroy``) when a later rollout needs another size.

Differentiable fields keep the particle state of every substep of one video frame (buffers
0..substeps) and an adjoint for every float field: Taichi's reverse-mode autodiff needs every
value a kernel read to still be there when its adjoint runs (the global data access rule), so
substep s+1 is written to fresh storage instead of overwriting substep s. Forward-only fields
(``differentiable=False``) have no adjoints and two state buffers that substeps take in turn
(s mod 2): nothing reads a substep's state once the next one is written, so their size does not
depend on the substep count.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import taichi as ti

from mosiv_framework.expression import NODE_FEATURES
from mosiv_taichi_mpm.laws import MAX_LAW_PARAMS

#: the expression term's node-local features (the other objects' ones are warp-mpm's only)
N_NODE_FEATURES = len(NODE_FEATURES)

#: empty grid cells added around the scene domain on every side; the slip walls live in them
PAD_CELLS = 3
#: sentinel of the divergence flags: no substep flagged yet
NO_DIVERGENCE = 2**30


@dataclass(frozen=True)
class Layout:
    """Sizes that fix the shapes of all fields (a new Layout means new fields and kernels).

    capacity: particle slots; n_objects: K; n_fields: grid velocity fields (K or 1);
    nodes: grid nodes per axis including the padding; substeps: per video frame;
    dx: cell size (m); origin: world position of node (0, 0, 0) (m).
    """

    capacity: int
    n_objects: int
    n_fields: int
    nodes: tuple[int, int, int]
    substeps: int
    dx: float
    origin: tuple[float, float, float]


def make_layout(
    *,
    n_particles: int,
    n_objects: int,
    single_field: bool,
    grid: int,
    substeps: int,
    domain_lower: tuple[float, float, float],
    domain_upper: tuple[float, float, float],
) -> Layout:
    """Grid geometry: dx = longest domain side / grid; other axes get ceil(extent / dx) cells."""
    extents = [u - lo for lo, u in zip(domain_lower, domain_upper)]
    if min(extents) <= 0:
        raise ValueError(
            f"world domain must have positive extent on every axis, got lower={domain_lower} "
            f"upper={domain_upper}"
        )
    dx = max(extents) / grid
    cells = [max(1, math.ceil(e / dx - 1e-6)) + 2 * PAD_CELLS for e in extents]
    nodes = tuple(c + 1 for c in cells)
    origin = tuple(lo - PAD_CELLS * dx for lo in domain_lower)
    # round the particle count up so nearby sizes reuse the compiled kernels
    capacity = max(256, -(-n_particles // 256) * 256)
    return Layout(
        capacity=capacity,
        n_objects=n_objects,
        n_fields=1 if single_field else n_objects,
        nodes=nodes,  # type: ignore[arg-type]
        substeps=substeps,
        dx=dx,
        origin=origin,  # type: ignore[arg-type]
    )


@ti.data_oriented
class SimFields:
    """Every field of one problem. ``differentiable``: every float field has a ``.grad``
    companion and each substep its own state buffer (see the module docstring); otherwise two
    state buffers and no adjoints, for rollouts that nothing differentiates."""

    def __init__(self, layout: Layout, *, differentiable: bool = True):
        self.layout = layout
        self.differentiable = differentiable
        #: particle-state buffers (x .. Jp): one per substep boundary, or two taking turns
        self.state_buffers = layout.substeps + 1 if differentiable else 2
        #: buffers of the trial F and its singular values, which only their own substep reads
        self.trial_buffers = layout.substeps if differentiable else 1
        f32, g = ti.f32, differentiable
        mat = ti.types.matrix(3, 3, f32)
        vec = ti.types.vector(3, f32)

        # particle state of substep s in buffer s (differentiable) or s mod 2: index [buffer, p]
        self.x = ti.field(vec, needs_grad=g)  # position (m)
        self.v = ti.field(vec, needs_grad=g)  # velocity (m/s)
        self.C = ti.field(mat, needs_grad=g)  # APIC affine velocity (1/s)
        self.F = ti.field(mat, needs_grad=g)  # elastic deformation gradient
        self.U = ti.field(mat, needs_grad=g)  # left rotation of F's SVD
        self.V = ti.field(mat, needs_grad=g)  # right rotation of F's SVD
        self.sig = ti.field(vec, needs_grad=g)  # singular values of F
        self.Jp = ti.field(f32, needs_grad=g)  # plastic volume ratio (snow)
        # per substep s = 0..S-1 (or one buffer): trial F = (I + dt C) F and its singular values
        self.F_trial = ti.field(mat, needs_grad=g)
        self.sig_trial = ti.field(vec, needs_grad=g)

        # per particle, recomputed every substep: mass (kg) and MLS affine momentum term
        self.pmass = ti.field(f32, needs_grad=g)
        self.affine = ti.field(mat, needs_grad=g)

        # differentiable fields only: each particle's copy of its object's law parameters and
        # density (``MPMKernels.spread_params``), which the stress and the return map read.
        # Reading the object's row instead, every particle's adjoint adds into the same few
        # addresses of law_p.grad and rho.grad every substep, and a GPU serialises those adds;
        # the copies' adjoints add into one address per particle, and their sum reaches the
        # object's row once per backward.
        self.p_law = ti.field(ti.types.vector(MAX_LAW_PARAMS, f32), needs_grad=g) if g else None
        self.p_rho = ti.field(f32, needs_grad=g) if g else None

        # constant per particle
        self.obj = ti.field(ti.i32)  # object index 0..K-1
        self.vol = ti.field(f32)  # rest volume (m^3)

        # grid, one velocity field per object (or one shared): index [g, i, j, k]
        self.m = ti.field(f32, needs_grad=g)  # mass (kg)
        self.mv = ti.field(vec, needs_grad=g)  # momentum incl. stress impulse (kg m/s)
        self.gm = ti.field(vec, needs_grad=g)  # mass gradient (kg/m) for contact normals
        # momentum without this substep's stress impulse (kg m/s), on ground-layer nodes only:
        # the arriving velocity that ground_restitution reflects
        self.pm = ti.field(vec, needs_grad=g)
        self.vf = ti.field(vec, needs_grad=g)  # velocity after body forces (m/s)
        self.vg = ti.field(vec, needs_grad=g)  # velocity after contact and boundaries (m/s)

        # parameters (differentiable), index [k] per object
        self.law_id = ti.field(ti.i32)
        self.law_p = ti.field(ti.types.vector(MAX_LAW_PARAMS, f32), needs_grad=g)
        self.rho = ti.field(f32, needs_grad=g)  # kg/m^3
        self.friction = ti.field(f32, needs_grad=g)
        self.v0 = ti.field(vec, needs_grad=g)  # initial velocity (m/s)
        self.ground_mu = ti.field(f32, needs_grad=g)
        self.gravity = ti.field(vec, needs_grad=g)  # m/s^2 (world or `gravity` term)
        self.wind = ti.field(vec, needs_grad=g)  # m/s^2
        self.lin_drag = ti.field(f32, needs_grad=g)  # 1/s
        self.quad_drag = ti.field(f32, needs_grad=g)  # 1/m
        self.damping = ti.field(f32, needs_grad=g)  # material_damping viscosity (Pa s)
        self.ground_e = ti.field(f32, needs_grad=g)  # ground_restitution coefficient
        # the expression term (mosiv_framework.expression): one vec3 (a_x, a_y, a_z) per
        # node-local feature, in NODE_FEATURES order; up and on are not differentiated
        self.expr_coef = ti.field(vec, needs_grad=g)
        self.expr_on = ti.field(ti.i32)  # 1 where the rollout has the term
        self.up = ti.field(vec)  # unit vector opposite gravity, for the height feature

        # diagnostics (forward only): first flagged substep * 4 + reason, per object
        self.div_code = ti.field(ti.i32)
        self.contact = ti.field(ti.i32)  # [K, K+1] object-object / ground contact this frame

        self._tree = self._place(layout)

    def _place(self, layout: Layout):
        """Place every field in one SNode tree, which ``destroy`` frees as a whole.

        Each particle and grid field gets its own dense block (structure of arrays), and on
        differentiable fields so does each one's adjoint: a kernel that reads x then reads the
        x of neighbouring particles from neighbouring addresses. Fields placed together would
        interleave per element (x, v, C, F, ... of particle 0, then of particle 1), so every
        read would stride over all of them; on an H200 the separate blocks made the forward
        kernels 2.8x faster at 1M particles (docs/BENCHMARKS.md, "taichi-mpm's forward").
        ``lazy_grad`` would put each adjoint in its value's block (value and adjoint
        interleaved, every read striding over both), so it is left only the small per-object
        and global parameter fields."""
        N, K = layout.capacity, layout.n_objects
        fb = ti.FieldsBuilder()

        def own_blocks(axes, shape, *fields):
            for fld in fields:
                fb.dense(axes, shape).place(fld)
                if self.differentiable:
                    fb.dense(axes, shape).place(fld.grad)

        state_shape = (self.state_buffers, N)
        own_blocks(ti.ij, state_shape, self.x, self.v, self.C, self.F, self.U, self.V)
        own_blocks(ti.ij, state_shape, self.sig, self.Jp)
        own_blocks(ti.ij, (self.trial_buffers, N), self.F_trial, self.sig_trial)
        for constant in (self.obj, self.vol):
            fb.dense(ti.i, N).place(constant)
        own_blocks(ti.i, N, self.pmass, self.affine)
        if self.differentiable:
            own_blocks(ti.i, N, self.p_law, self.p_rho)
        grid_shape = (layout.n_fields, *layout.nodes)
        own_blocks(ti.ijkl, grid_shape, self.m, self.mv, self.gm, self.pm, self.vf, self.vg)
        fb.dense(ti.i, K).place(
            self.law_id, self.law_p, self.rho, self.friction, self.v0, self.div_code
        )
        fb.place(self.ground_mu, self.gravity, self.wind, self.lin_drag, self.quad_drag)
        fb.place(self.damping, self.ground_e, self.expr_on, self.up)
        fb.dense(ti.i, N_NODE_FEATURES).place(self.expr_coef)
        fb.dense(ti.ij, (K, K + 1)).place(self.contact)
        if self.differentiable:
            fb.lazy_grad()  # the adjoints not placed above, beside their values
        return fb.finalize()

    #: the differentiable parameter fields, by the name the simulator maps tensors to
    def param_fields(self) -> dict[str, ti.Field]:
        return {
            "law_p": self.law_p,
            "rho": self.rho,
            "friction": self.friction,
            "v0": self.v0,
            "ground_mu": self.ground_mu,
            "gravity": self.gravity,
            "wind": self.wind,
            "lin_drag": self.lin_drag,
            "quad_drag": self.quad_drag,
            "damping": self.damping,
            "ground_e": self.ground_e,
            "expr_coef": self.expr_coef,
        }

    def nbytes(self) -> int:
        """Bytes held by these fields, read from their shapes: values, and on differentiable
        fields the adjoint of every float field (``_place``)."""
        total = 0
        for fld in vars(self).values():
            if not isinstance(fld, ti.Field):
                continue
            elements = math.prod(fld.shape) * getattr(fld, "n", 1) * getattr(fld, "m", 1)
            copies = 2 if self.differentiable and fld.dtype == ti.f32 else 1
            total += 4 * elements * copies  # every field is 32-bit
        return total

    def destroy(self) -> None:
        """Free the device memory of every field (they must not be used afterwards).

        Taichi 1.7 on CUDA can refuse to free a tree whose kernels were compiled (an internal
        assertion in its LLVM context); the fields are then left allocated until the Taichi
        runtime resets, which costs memory but keeps the rollout correct.
        """
        try:
            self._tree.destroy()
        except RuntimeError as exc:
            if "delete_snode_tree" not in str(exc):
                raise
