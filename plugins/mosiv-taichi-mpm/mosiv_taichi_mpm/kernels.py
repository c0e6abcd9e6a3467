"""Taichi kernels of one MLS-MPM substep (Hu et al. 2018, APIC, quadratic B-splines).

A substep from the particle state at substep boundary ``s`` to that at ``s + 1`` runs, in order:
``clear_grid`` -> ``stress(s)`` -> ``p2g(s, i = 0..2)`` -> ``grid_forces`` -> ``grid_contact`` ->
``clear_particle_velocity(s)`` -> ``g2p(s)`` -> ``advect(s)`` -> ``svd(s)`` -> ``plasticity(s)``.
Every kernel except ``svd`` is differentiated by Taichi (``kernel.grad``); ``svd_backward`` is the
hand-written adjoint of ``svd``. Kernels read and write disjoint fields so that the recorded
values survive until their adjoints run. ``check`` and ``detect_contact`` are forward-only.
Each kernel's body is a ``ti.func`` per particle or node (``forces_at``, ``contact_at``,
``svd_at``, ...) so that the one-call forward substep of forward_kernels.py runs the same code.

Kernels find boundary s's state in buffer ``state_at(s)`` and substep s's trial F in
``trial_at(s)``: the buffer of that index on differentiable fields, one of two (or the one) on
forward-only fields, which keep no history (fields.py).
"""

# no `from __future__ import annotations`: Taichi reads the annotations at runtime
import taichi as ti

from mosiv_taichi_mpm.fields import SimFields
from mosiv_taichi_mpm.grid_kernels import MASS_EPS, GridKernels
from mosiv_taichi_mpm.laws import J_MIN, kirchhoff_stress, return_map
from mosiv_taichi_mpm.svd_grad import svd_adjoint

#: (i, j) offsets of the stencil rows of 3 nodes: each is one top-level loop of g2p and of p2g
STENCIL_ROWS = tuple((i, j) for i in range(3) for j in range(3))
#: i offsets of the stencil planes of 9 nodes: each is one p2g kernel
STENCIL_PLANES = (0, 1, 2)

# divergence reasons (stored in the low 2 bits of div_code)
REASON_NONFINITE = 1
REASON_LEFT_DOMAIN = 2

FLOAT_BIG = 1e30  # |value| above this counts as non-finite (catches inf and, via compare, NaN)


@ti.func
def spline_weight(d):
    """Quadratic B-spline N(d) at d = (x_p - x_i)/dx, and dN/dx_i in cell units (the gradient
    with respect to the node position, so that sum m_p dN/dx_i is the grid mass gradient)."""
    # ti.select, not if/else: locals assigned in branches inside the dynamic stencil loop would
    # need Taichi's adstack in the adjoint kernel
    a = ti.abs(d)
    inner = a < 0.5
    w = ti.select(inner, 0.75 - a * a, 0.5 * (1.5 - a) ** 2)
    dw = ti.select(inner, 2.0 * d, (1.5 - a) * ti.select(d > 0.0, 1.0, -1.0))
    return w, dw


@ti.func
def stencil(fx, offset):
    """Weight of node base + offset for a particle at fx (cell units from base), its gradient
    (1/cell, with respect to the node position) and the offset vector in cells."""
    d = fx - ti.cast(offset, ti.f32)
    w0, g0 = spline_weight(d[0])
    w1, g1 = spline_weight(d[1])
    w2, g2 = spline_weight(d[2])
    return w0 * w1 * w2, ti.Vector([g0 * w1 * w2, w0 * g1 * w2, w0 * w1 * g2]), -d


@ti.func
def kelvin_voigt_tau(eta, F, L):
    """material_damping: tau_visc = eta J (L + L^T) (Pa), L = C, as the Newtonian law's."""
    J = ti.max(F.determinant(), J_MIN)
    return (eta * J) * (L + L.transpose())


@ti.data_oriented
class MPMKernels(GridKernels):
    """Kernels bound to one ``SimFields`` and one set of material families.

    ``present_laws`` (tuple of law ids) selects which laws are compiled in; ``needs_svd`` says
    whether any of them uses the SVD of F (all but elastic and newtonian).
    """

    def __init__(self, fields: SimFields, present_laws: tuple[int, ...]):
        self.f = fields
        # kernels reach fields as attributes of self (Taichi resolves them at compile time)
        for name, value in vars(fields).items():
            if isinstance(value, ti.Field):
                setattr(self, name, value)
        lay = fields.layout
        self.present = tuple(sorted(present_laws))
        self.needs_svd = any(law not in (0, 3) for law in self.present)
        self.K = lay.n_objects
        self.G = lay.n_fields
        self.multi = lay.n_fields > 1
        self.nodes = lay.nodes
        self.dx = lay.dx
        self.inv_dx = 1.0 / lay.dx
        self.origin = ti.Vector(list(lay.origin), ti.f32)
        # particles are kept inside [1, nodes - 2] cells so the 3x3x3 stencil stays on the grid
        self.lo = 1.0
        self.hi = ti.Vector([n - 2.0 - 1e-3 for n in lay.nodes], ti.f32)
        #: forward-only fields: two state buffers taking turns, one trial buffer
        self.rotating = not fields.differentiable
        #: differentiable fields: particles read their own copies of the law parameters and
        #: density (fields.py, ``p_law``), which ``spread_params`` fills
        self.per_particle_params = fields.differentiable

    @ti.func
    def state_at(self, s):
        """The buffer of the particle state at substep boundary s: s on differentiable fields,
        s mod 2 on forward-only ones (boundary s + 1 overwrites s - 1, which nothing reads
        again). The branch is static: differentiable kernels index by s as they always did."""
        b = s
        if ti.static(self.rotating):
            b = s % 2
        return b

    @ti.func
    def trial_at(self, s):
        """The buffer of substep s's trial F and its singular values: s, or 0 on forward-only
        fields (only substep s's own svd and plasticity read them)."""
        t = s
        if ti.static(self.rotating):
            t = 0
        return t

    # ------------------------------------------------------------------------------------------
    # state transfer (not differentiated; the autograd function moves adjoints explicitly)
    # ------------------------------------------------------------------------------------------
    @ti.kernel
    def set_particles(self, n: ti.i32, obj: ti.types.ndarray(), vol: ti.types.ndarray()):
        for p in range(n):
            self.obj[p] = obj[p]
            self.vol[p] = vol[p]

    @ti.kernel
    def rest_state(self, n: ti.i32, x: ti.types.ndarray()):
        """Frame 0: x given, F = U = V = I, singular values 1, C = 0, plastic_J = 1."""
        for p in range(n):
            self.x[0, p] = ti.Vector([x[p, 0], x[p, 1], x[p, 2]])
            self.C[0, p] = ti.Matrix.zero(ti.f32, 3, 3)
            self.F[0, p] = ti.Matrix.identity(ti.f32, 3)
            self.U[0, p] = ti.Matrix.identity(ti.f32, 3)
            self.V[0, p] = ti.Matrix.identity(ti.f32, 3)
            self.sig[0, p] = ti.Vector([1.0, 1.0, 1.0])
            self.Jp[0, p] = 1.0

    @ti.kernel
    def spread_params(self, n: ti.i32):
        """Each particle's copy of its object's law parameters and density (differentiable
        fields only). Its adjoint sums the copies' adjoints into the objects' rows: one add per
        particle and backward, where reading the rows directly costs one per particle and
        substep, all into the same few addresses."""
        for p in range(n):
            k = self.obj[p]
            self.p_law[p] = self.law_p[k]
            self.p_rho[p] = self.rho[k]

    @ti.func
    def law_params_of(self, p, k):
        """The law parameters particle p of object k uses: its own copy on differentiable
        fields, its object's row otherwise. (Two static branches: a read of the row that a
        later assignment overwrote would still leave its adjoint's adds in the kernel.)"""
        if ti.static(self.per_particle_params):
            return self.p_law[p]
        else:
            return self.law_p[k]

    @ti.func
    def density_of(self, p, k):
        """The density (kg/m^3) particle p of object k uses; see ``law_params_of``."""
        if ti.static(self.per_particle_params):
            return self.p_rho[p]
        else:
            return self.rho[k]

    @ti.kernel
    def initial_velocity(self, n: ti.i32):
        """v(t=0) = v0 of the particle's object."""
        for p in range(n):
            self.v[0, p] = self.v0[self.obj[p]]

    @ti.kernel
    def transfer_state(
        self,
        s: ti.i32,
        n: ti.i32,
        to_fields: ti.template(),
        use_grad: ti.template(),
        x: ti.types.ndarray(),
        v: ti.types.ndarray(),
        C: ti.types.ndarray(),
        F: ti.types.ndarray(),
        U: ti.types.ndarray(),
        V: ti.types.ndarray(),
        sig: ti.types.ndarray(),
        Jp: ti.types.ndarray(),
    ):
        """Copy boundary s's state (values or adjoints) to (to_fields=False) or from flat
        arrays."""
        for p in range(n):
            a = self.state_at(s)
            for i in ti.static(range(3)):
                if ti.static(to_fields):
                    if ti.static(use_grad):
                        self.x.grad[a, p][i] = x[p, i]
                        self.v.grad[a, p][i] = v[p, i]
                        self.sig.grad[a, p][i] = sig[p, i]
                    else:
                        self.x[a, p][i] = x[p, i]
                        self.v[a, p][i] = v[p, i]
                        self.sig[a, p][i] = sig[p, i]
                else:
                    if ti.static(use_grad):
                        x[p, i] = self.x.grad[a, p][i]
                        v[p, i] = self.v.grad[a, p][i]
                        sig[p, i] = self.sig.grad[a, p][i]
                    else:
                        x[p, i] = self.x[a, p][i]
                        v[p, i] = self.v[a, p][i]
                        sig[p, i] = self.sig[a, p][i]
                for j in ti.static(range(3)):
                    if ti.static(to_fields):
                        if ti.static(use_grad):
                            self.C.grad[a, p][i, j] = C[p, i, j]
                            self.F.grad[a, p][i, j] = F[p, i, j]
                            self.U.grad[a, p][i, j] = U[p, i, j]
                            self.V.grad[a, p][i, j] = V[p, i, j]
                        else:
                            self.C[a, p][i, j] = C[p, i, j]
                            self.F[a, p][i, j] = F[p, i, j]
                            self.U[a, p][i, j] = U[p, i, j]
                            self.V[a, p][i, j] = V[p, i, j]
                    else:
                        if ti.static(use_grad):
                            C[p, i, j] = self.C.grad[a, p][i, j]
                            F[p, i, j] = self.F.grad[a, p][i, j]
                            U[p, i, j] = self.U.grad[a, p][i, j]
                            V[p, i, j] = self.V.grad[a, p][i, j]
                        else:
                            C[p, i, j] = self.C[a, p][i, j]
                            F[p, i, j] = self.F[a, p][i, j]
                            U[p, i, j] = self.U[a, p][i, j]
                            V[p, i, j] = self.V[a, p][i, j]
            if ti.static(to_fields):
                if ti.static(use_grad):
                    self.Jp.grad[a, p] = Jp[p]
                else:
                    self.Jp[a, p] = Jp[p]
            else:
                if ti.static(use_grad):
                    Jp[p] = self.Jp.grad[a, p]
                else:
                    Jp[p] = self.Jp[a, p]

    @ti.kernel
    def add_position_grad(self, s: ti.i32, n: ti.i32, g: ti.types.ndarray()):
        """dL/dx[s] += g (the loss gradient of the positions output at a frame boundary)."""
        for p in range(n):
            a = self.state_at(s)
            self.x.grad[a, p] += ti.Vector([g[p, 0], g[p, 1], g[p, 2]])

    @ti.kernel
    def clear_grid(self):
        """Zero the grid before a substep's transfer."""
        for I in ti.grouped(self.m):
            self.clear_node(I)

    @ti.kernel
    def clear_adjoints(self, n: ti.i32):
        """Zero the grid's adjoints and those of the particles' mass and affine term (which
        every substep's ``stress`` rewrites) before a substep's adjoints: one call, as the
        host's calls set the pace of a small backward."""
        for I in ti.grouped(self.m):
            self.m.grad[I] = 0.0
            self.mv.grad[I] = ti.Vector.zero(ti.f32, 3)
            self.gm.grad[I] = ti.Vector.zero(ti.f32, 3)
            self.pm.grad[I] = ti.Vector.zero(ti.f32, 3)
            self.vf.grad[I] = ti.Vector.zero(ti.f32, 3)
            self.vg.grad[I] = ti.Vector.zero(ti.f32, 3)
        for p in range(n):
            self.pmass.grad[p] = 0.0
            self.affine.grad[p] = ti.Matrix.zero(ti.f32, 3, 3)

    @ti.func
    def clear_node(self, I):
        """Zero grid node I = (field, i, j, l) before P2G adds into it."""
        self.m[I] = 0.0
        self.mv[I] = ti.Vector.zero(ti.f32, 3)
        if ti.static(self.multi):
            self.gm[I] = ti.Vector.zero(ti.f32, 3)
        self.pm[I] = ti.Vector.zero(ti.f32, 3)

    # ------------------------------------------------------------------------------------------
    # one substep
    # ------------------------------------------------------------------------------------------
    @ti.kernel
    def stress(self, s: ti.i32, n: ti.i32, dt: ti.f32):
        """Per particle: mass m_p = rho V0 and MLS affine term A = -dt 4/dx^2 V0 tau + m_p C,
        tau = the law's Kirchhoff stress + the ``material_damping`` viscous stress."""
        for p in range(n):
            mass, A = self.mass_and_affine(s, p, dt)
            self.pmass[p] = mass
            self.affine[p] = A

    @ti.func
    def mass_and_affine(self, s, p, dt):
        """Particle p's mass m_p = rho V0 (kg) and MLS affine term A = -dt 4/dx^2 V0 tau + m_p C
        at substep boundary s (shared with the one-call forward substep)."""
        a, k = self.state_at(s), self.obj[p]
        mass = self.density_of(p, k) * self.vol[p]
        tau = kirchhoff_stress(
            self.present, self.law_id[k], self.F[a, p], self.U[a, p], self.sig[a, p],
            self.C[a, p], self.Jp[a, p], self.law_params_of(p, k),
        )  # fmt: skip
        tau += kelvin_voigt_tau(self.damping[None], self.F[a, p], self.C[a, p])
        A = -dt * 4.0 * self.inv_dx * self.inv_dx * self.vol[p] * tau + mass * self.C[a, p]
        return mass, A

    @ti.func
    def stencil_cell(self, x):
        """The stencil's base node of a particle at x (m) and its offset from it, in cells."""
        xg = (x - self.origin) * self.inv_dx
        base = ti.cast(xg - 0.5, ti.i32)
        return base, xg - ti.cast(base, ti.f32)

    @ti.func
    def scatter_node(self, g, base, fx, offset, mass, mom, A, MC, ground_z):
        """One P2G node: m_i += w m_p; (m v)_i += w (m_p v_p + A dpos); with several fields
        (grad m)_i += m_p grad w (only multi-field contact reads it); on nodes at or below
        ground_z (m) the arriving momentum (p m)_i += w m_p (v_p + C dpos). mom = m_p v_p,
        MC = m_p C."""
        weight, grad_w, dcell = stencil(fx, offset)
        node = base + offset
        self.m[g, node[0], node[1], node[2]] += weight * mass
        self.mv[g, node[0], node[1], node[2]] += weight * (mom + A @ (dcell * self.dx))
        if ti.static(self.multi):  # only multi-field contact reads the mass gradient
            self.gm[g, node[0], node[1], node[2]] += (mass * self.inv_dx) * grad_w
        if self.origin[2] + node[2] * self.dx <= ground_z:  # for ground_restitution
            self.pm[g, node[0], node[1], node[2]] += weight * (mom + MC @ (dcell * self.dx))

    @ti.func
    def gather_node(self, g, base, fx, offset):
        """One G2P node's contributions to v (w v_i) and to C (4/dx^2 w v_i dpos^T)."""
        weight, _grad_w, dcell = stencil(fx, offset)
        node = base + offset
        gv = self.vg[g, node[0], node[1], node[2]]
        return weight * gv, (4.0 * self.inv_dx * weight) * gv.outer_product(dcell)

    @ti.kernel
    def p2g(self, s: ti.i32, n: ti.i32, i: ti.template(), ground_z: ti.f32):
        """MLS-MPM P2G over the 9 stencil nodes with offsets (i, 0..2, 0..2):
        m_i += w m_p; (m v)_i += w (m_p v_p + A dpos); with several fields (grad m)_i += m_p grad
        w; on nodes at or below ground_z (m) also the arriving momentum (p m)_i += w m_p (v_p +
        C dpos).

        The stencil is unrolled (Taichi's adjoint of a dynamic inner loop is wrong here). Each
        row (i, j, 0..2) is a top-level loop of its own, and the 27 nodes are split in three
        kernels, one a plane i, because the adjoint's compile time grows faster than linearly
        with kernel size: as nine top-level loops of one kernel (as ``g2p``), the build of a
        two-body rollout's adjoints had not finished after five minutes, where it otherwise
        takes about two (benchmarks/data/taichi_grid_adjoint_cpu/)."""
        for j in ti.static(range(3)):
            for p in range(n):
                a = self.state_at(s)
                g = self.obj[p] if ti.static(self.multi) else 0
                mass = self.pmass[p]
                base, fx = self.stencil_cell(self.x[a, p])
                mom = mass * self.v[a, p]
                MC = mass * self.C[a, p]
                for l in ti.static(range(3)):
                    offset = ti.Vector([i, j, l])
                    self.scatter_node(g, base, fx, offset, mass, mom, self.affine[p], MC, ground_z)

    @ti.kernel
    def clear_particle_velocity(self, s: ti.i32, n: ti.i32):
        """Zero v[s + 1] and C[s + 1] before ``g2p`` accumulates into them."""
        for p in range(n):
            b = self.state_at(s + 1)
            self.v[b, p] = ti.Vector.zero(ti.f32, 3)
            self.C[b, p] = ti.Matrix.zero(ti.f32, 3, 3)

    @ti.kernel
    def g2p(self, s: ti.i32, n: ti.i32):
        """G2P gather over the 27 stencil nodes: v += w v_i, C += 4/dx^2 w v_i dpos^T (APIC),
        accumulated into the fields. Each stencil row (i, j, 0..2) is a top-level loop of its
        own, which Taichi launches and differentiates on its own: one call a substep, and an
        adjoint that builds about as fast as nine one-row kernels (``p2g`` so written did not
        build in reasonable time: it is three kernels of three loops)."""
        for i, j in ti.static(STENCIL_ROWS):
            for p in range(n):
                a, b = self.state_at(s), self.state_at(s + 1)
                g = self.obj[p] if ti.static(self.multi) else 0
                base, fx = self.stencil_cell(self.x[a, p])
                for l in ti.static(range(3)):
                    dv, dC = self.gather_node(g, base, fx, ti.Vector([i, j, l]))
                    self.v[b, p] += dv
                    self.C[b, p] += dC

    @ti.kernel
    def advect(self, s: ti.i32, n: ti.i32, dt: ti.f32):
        """x += dt v (kept inside the padded grid), F_trial = (I + dt C) F."""
        for p in range(n):
            a, b, t = self.state_at(s), self.state_at(s + 1), self.trial_at(s)
            x_new = (self.x[a, p] + dt * self.v[b, p] - self.origin) * self.inv_dx
            x_new = ti.min(ti.max(x_new, self.lo), self.hi)
            self.x[b, p] = self.origin + x_new * self.dx
            self.F_trial[t, p] = (ti.Matrix.identity(ti.f32, 3) + dt * self.C[b, p]) @ self.F[a, p]

    @ti.kernel
    def svd(self, s: ti.i32, n: ti.i32):
        """F_trial = U diag(s) V^T with proper rotations (not differentiated by Taichi)."""
        for p in range(n):
            self.svd_at(s, p)

    @ti.func
    def svd_at(self, s, p):
        """``svd`` of particle p."""
        b, t = self.state_at(s + 1), self.trial_at(s)
        U, S, V = ti.svd(self.F_trial[t, p])
        self.U[b, p] = U
        self.V[b, p] = V
        self.sig_trial[t, p] = ti.Vector([S[0, 0], S[1, 1], S[2, 2]])

    @ti.kernel
    def svd_backward(self, s: ti.i32, n: ti.i32):
        """Hand-written adjoint of ``svd`` (svd_grad.py)."""
        for p in range(n):
            b, t = self.state_at(s + 1), self.trial_at(s)
            self.F_trial.grad[t, p] += svd_adjoint(
                self.U[b, p], self.sig_trial[t, p], self.V[b, p],
                self.U.grad[b, p], self.sig_trial.grad[t, p], self.V.grad[b, p],
            )  # fmt: skip

    @ti.kernel
    def plasticity(self, s: ti.i32, n: ti.i32, dt: ti.f32):
        """Return map of the particle's law: (F_trial, plastic_J) -> (F, s, plastic_J)."""
        for p in range(n):
            self.plasticity_at(s, p, dt)

    @ti.func
    def plasticity_at(self, s, p, dt):
        """``plasticity`` of particle p."""
        a, b, t = self.state_at(s), self.state_at(s + 1), self.trial_at(s)
        k = self.obj[p]
        F_new, s_new, Jp_new = return_map(
            self.present, self.law_id[k], self.F_trial[t, p], self.U[b, p], self.sig_trial[t, p],
            self.V[b, p], self.Jp[a, p], self.law_params_of(p, k), dt,
        )  # fmt: skip
        self.F[b, p] = F_new
        self.sig[b, p] = s_new
        self.Jp[b, p] = Jp_new

    @ti.kernel
    def copy_identity_svd(self, s: ti.i32, n: ti.i32):
        """Without SVD laws U, V are unused; keep them (and the trial s) defined anyway."""
        for p in range(n):
            self.identity_svd_at(s, p)

    @ti.func
    def identity_svd_at(self, s, p):
        """``copy_identity_svd`` of particle p."""
        b, t = self.state_at(s + 1), self.trial_at(s)
        self.U[b, p] = ti.Matrix.identity(ti.f32, 3)
        self.V[b, p] = ti.Matrix.identity(ti.f32, 3)
        self.sig_trial[t, p] = ti.Vector([1.0, 1.0, 1.0])

    # ------------------------------------------------------------------------------------------
    # diagnostics (forward only)
    # ------------------------------------------------------------------------------------------
    @ti.kernel
    def check(self, s: ti.i32, n: ti.i32, step: ti.i32):
        """Flag non-finite state or particles pinned at the grid clamp: div_code = step*4+reason."""
        for p in range(n):
            self.check_at(s, p, step)

    @ti.func
    def check_at(self, s, p, step):
        """``check`` of particle p at substep boundary s."""
        a = self.state_at(s)
        total = self.x[a, p].sum() + self.v[a, p].sum() + self.F[a, p].sum() + self.Jp[a, p]
        reason = 0
        if not (ti.abs(total) < FLOAT_BIG):
            reason = REASON_NONFINITE
        else:
            xg = (self.x[a, p] - self.origin) * self.inv_dx
            if (xg <= self.lo + 1e-4).any() or (xg >= self.hi - 1e-4).any():
                reason = REASON_LEFT_DOMAIN
        if reason != 0:
            ti.atomic_min(self.div_code[self.obj[p]], step * 4 + reason)

    @ti.kernel
    def detect_contact(self, ground_z: ti.f32, has_ground: ti.i32):
        """contact[a, b] = 1 where a and b share an approaching node; contact[a, K] for ground."""
        for i, j, l in ti.ndrange(*self.nodes):
            self.detect_contact_at(i, j, l, ground_z, has_ground)

    @ti.func
    def detect_contact_at(self, i, j, l, ground_z, has_ground):
        """``detect_contact`` at the nodes (i, j, l) of every field."""
        z = self.origin[2] + l * self.dx
        for a in ti.static(range(self.G)):
            if self.m[a, i, j, l] > MASS_EPS:
                if has_ground != 0 and z <= ground_z and self.vf[a, i, j, l][2] < 0.0:
                    self.contact[a, self.K] = 1
                for b in ti.static(range(self.G)):
                    if ti.static(a != b):
                        if self.m[b, i, j, l] > MASS_EPS:
                            nrm = self.gm[b, i, j, l] - self.gm[a, i, j, l]
                            rel = self.vf[a, i, j, l] - self.vf[b, i, j, l]
                            if rel.dot(nrm) > 0.0:
                                self.contact[a, b] = 1
                                self.contact[b, a] = 1
