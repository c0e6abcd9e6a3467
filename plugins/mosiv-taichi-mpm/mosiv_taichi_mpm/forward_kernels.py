"""The forward substep as one kernel: the same MLS-MPM transfer in fewer passes and one call.

The kernels of ``kernels.py`` are shaped for Taichi's reverse mode: the 27-node stencil is split
into nine three-node passes (nine top-level loops of ``g2p``, and of ``p2g`` in three kernels:
the adjoint's compile time grows faster than linearly with a loop's size) and each step of the
particle update is its own kernel, so every particle is read and its B-spline weights
recomputed nine times in P2G and nine times in G2P. Nothing here is
differentiated, so a substep becomes one kernel, ``substep``, whose top-level loops Taichi runs
one after another on the device:

clear the grid -> P2G (stress and all 27 nodes) -> grid forces -> grid contact -> [contact
detection] -> G2P with advection, the SVD and the return map -> [divergence check]

with the same equations (the node and particle functions of ``kernels.py``), evaluated in the
same order per particle, writing the same per-substep fields. One call instead of one per pass
matters on a GPU: Taichi spends about 0.1 ms of Python per kernel call on this class, as long as
a whole pass over 1M particles takes (docs/BENCHMARKS.md, "taichi-mpm's forward"). The
reverse pass re-simulates a frame with this kernel too, and before each substep's adjoints
recomputes that substep's grid with ``grid_of_substep``: the first half of ``substep``, which
also stores what the split kernels' adjoints read of it (the particles' mass and affine term).
The split kernels' sums come in another order of the particles' atomic adds, so the two paths
agree to float32 round-off.
"""

# no `from __future__ import annotations`: Taichi reads the annotations at runtime
import taichi as ti

from mosiv_taichi_mpm.kernels import MPMKernels


@ti.data_oriented
class FusedForwardKernels(MPMKernels):
    """``MPMKernels`` plus the one-call forward substep and the one-call grid of a substep
    (neither differentiated)."""

    @ti.kernel
    def substep(
        self,
        s: ti.i32,
        n: ti.i32,
        dt: ti.f32,
        pm_level: ti.f32,
        time: ti.f32,
        ground_h: ti.f32,
        ground_z: ti.f32,
        has_ground: ti.i32,
        diagnostics: ti.template(),
    ):
        """From the particle state at substep boundary s to that at s + 1. ``pm_level`` (m):
        the height up to which P2G records the arriving momentum; ``time`` (s) and ``ground_h``
        (m): grid_forces' clock and ground height; ``ground_z``, ``has_ground``: the table of
        grid_contact; ``diagnostics``: also detect contacts (several fields) and flag
        divergence, as the split path's ``detect_contact`` and ``check``."""
        for I in ti.grouped(self.m):
            self.clear_node(I)
        for p in range(n):
            self.p2g_particle(s, p, dt, pm_level, False)
        for I in ti.grouped(self.m):
            self.forces_at(I, dt, time, ground_h)
        for i, j, l in ti.ndrange(*self.nodes):
            self.contact_at(i, j, l, ground_z, has_ground)
        if ti.static(diagnostics and self.multi):
            for i, j, l in ti.ndrange(*self.nodes):
                self.detect_contact_at(i, j, l, ground_z, has_ground)
        for p in range(n):
            self.g2p_advect_particle(s, p, dt)
            if ti.static(self.needs_svd):
                self.svd_at(s, p)
            else:
                self.identity_svd_at(s, p)
            self.plasticity_at(s, p, dt)
            if ti.static(diagnostics):
                self.check_at(s + 1, p, s)

    @ti.kernel
    def grid_of_substep(
        self,
        s: ti.i32,
        n: ti.i32,
        dt: ti.f32,
        pm_level: ti.f32,
        time: ti.f32,
        ground_h: ti.f32,
        ground_z: ti.f32,
        has_ground: ti.i32,
    ):
        """Substep s's grid as the split ``clear_grid``, ``stress``, three ``p2g``,
        ``grid_forces`` and ``grid_contact`` leave it for their adjoints, in one call: the
        reverse pass recomputes it before every substep's adjoints (six calls fewer a
        substep). Arguments as ``substep``'s."""
        for I in ti.grouped(self.m):
            self.clear_node(I)
        for p in range(n):
            self.p2g_particle(s, p, dt, pm_level, True)
        for I in ti.grouped(self.m):
            self.forces_at(I, dt, time, ground_h)
        for i, j, l in ti.ndrange(*self.nodes):
            self.contact_at(i, j, l, ground_z, has_ground)

    @ti.func
    def p2g_particle(self, s, p, dt, ground_z, keep: ti.template()):
        """``stress`` and the three ``p2g`` kernels for particle p:
        tau = the law's Kirchhoff stress + the viscous stress, A = -dt 4/dx^2 V0 tau + m_p C,
        then over the 27 stencil nodes m_i += w m_p; (m v)_i += w (m_p v_p + A dpos);
        (grad m)_i += m_p grad w (several fields only); on nodes at or below ground_z (m) the
        arriving momentum (p m)_i += w m_p (v_p + C dpos). ``keep``: also store m_p and A as
        ``stress`` does, for the split kernels' adjoints."""
        a = self.state_at(s)
        g = self.obj[p] if ti.static(self.multi) else 0
        mass, A = self.mass_and_affine(s, p, dt)
        if ti.static(keep):
            self.pmass[p] = mass
            self.affine[p] = A
        base, fx = self.stencil_cell(self.x[a, p])
        mom = mass * self.v[a, p]
        MC = mass * self.C[a, p]
        for i, j, l in ti.static(ti.ndrange(3, 3, 3)):
            self.scatter_node(g, base, fx, ti.Vector([i, j, l]), mass, mom, A, MC, ground_z)

    @ti.func
    def g2p_advect_particle(self, s, p, dt):
        """``clear_particle_velocity``, ``g2p``'s nine row loops and ``advect`` for particle p:
        v = sum w v_i and C = sum 4/dx^2 w v_i dpos^T over the 27 nodes (in the split kernels'
        order), then x += dt v (kept inside the padded grid) and F_trial = (I + dt C) F."""
        a, b, t = self.state_at(s), self.state_at(s + 1), self.trial_at(s)
        g = self.obj[p] if ti.static(self.multi) else 0
        base, fx = self.stencil_cell(self.x[a, p])
        v = ti.Vector.zero(ti.f32, 3)
        C = ti.Matrix.zero(ti.f32, 3, 3)
        for i, j, l in ti.static(ti.ndrange(3, 3, 3)):
            dv, dC = self.gather_node(g, base, fx, ti.Vector([i, j, l]))
            v += dv
            C += dC
        self.v[b, p] = v
        self.C[b, p] = C
        x_new = (self.x[a, p] + dt * v - self.origin) * self.inv_dx
        x_new = ti.min(ti.max(x_new, self.lo), self.hi)
        self.x[b, p] = self.origin + x_new * self.dx
        self.F_trial[t, p] = (ti.Matrix.identity(ti.f32, 3) + dt * C) @ self.F[a, p]
