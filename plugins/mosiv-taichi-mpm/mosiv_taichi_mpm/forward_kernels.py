"""Fused kernels for the forward substep: the same MLS-MPM transfer in fewer, larger kernels.

The kernels of ``kernels.py`` are shaped for Taichi's reverse mode: the 27-node stencil is split
into nine three-node kernels (the adjoint's compile time grows faster than linearly with kernel
size) and each step of the particle update is its own kernel, so every particle is read and its
B-spline weights recomputed nine times in P2G and nine times in G2P. Nothing here is
differentiated, so a substep becomes

``clear_grid`` -> ``p2g_fused(s)`` -> ``grid_forces`` -> ``grid_contact`` -> ``g2p_advect(s)``
-> ``svd(s)`` -> ``plasticity(s)``

with the same equations (the node and stress functions of ``kernels.py``), evaluated in the same
order per particle, writing the same per-substep fields. The reverse pass re-simulates a frame with these kernels too and then runs the split
kernels' adjoints, which recompute the substep's grid with the split P2G (the same sums in
another order of the particles' atomic adds).
"""

# no `from __future__ import annotations`: Taichi reads the annotations at runtime
import taichi as ti

from mosiv_taichi_mpm.kernels import MPMKernels


@ti.data_oriented
class FusedForwardKernels(MPMKernels):
    """``MPMKernels`` plus the fused forward P2G and G2P (forward only)."""

    @ti.kernel
    def p2g_fused(self, s: ti.i32, n: ti.i32, dt: ti.f32, ground_z: ti.f32):
        """``stress`` and the nine ``p2g`` kernels in one pass over the particles:
        tau = the law's Kirchhoff stress + the viscous stress, A = -dt 4/dx^2 V0 tau + m_p C,
        then over the 27 stencil nodes m_i += w m_p; (m v)_i += w (m_p v_p + A dpos);
        (grad m)_i += m_p grad w; on nodes at or below ground_z (m) the arriving momentum
        (p m)_i += w m_p (v_p + C dpos)."""
        for p in range(n):
            a = self.state_at(s)
            g = self.obj[p] if ti.static(self.multi) else 0
            mass, A = self.mass_and_affine(s, p, dt)
            base, fx = self.stencil_cell(self.x[a, p])
            mom = mass * self.v[a, p]
            MC = mass * self.C[a, p]
            for i, j, l in ti.static(ti.ndrange(3, 3, 3)):
                self.scatter_node(g, base, fx, ti.Vector([i, j, l]), mass, mom, A, MC, ground_z)

    @ti.kernel
    def g2p_advect(self, s: ti.i32, n: ti.i32, dt: ti.f32):
        """``clear_particle_velocity``, the nine ``g2p`` kernels and ``advect`` in one pass:
        v = sum w v_i and C = sum 4/dx^2 w v_i dpos^T over the 27 nodes (in the split kernels'
        order), then x += dt v (kept inside the padded grid) and F_trial = (I + dt C) F."""
        for p in range(n):
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
