"""The grid half of a substep: body forces, then contact (between objects, with the table, with
the walls), node by node.

The functions are written for Taichi's reverse mode, which differentiates ``grid_forces`` and
``grid_contact``: every local is assigned once, the Coulomb, table and wall cases are selected
rather than branched into (``pick``, ``slip_wall``), and each branch writes the node itself.
A node without mass is skipped before anything else is read: its velocity stays zero.

``grid_forces``' adjoint adds into the body-force parameters' gradients (gravity, wind, drag)
from every node with mass. Summing those in a kernel of their own instead, as reductions
(``ti.stop_grad`` on the parameters in ``grid_forces``), was slower on an H200: 20.5 + 25.4 ms
against 36.4 ms for the adjoint alone, 100 substeps at 97,336 particles (docs/BENCHMARKS.md).
"""

# no `from __future__ import annotations`: Taichi reads the annotations at runtime
import taichi as ti

MASS_EPS = 1e-12  # kg; grid nodes lighter than this count as empty
NORMAL_EPS = 1e-20  # guards normalisation of near-zero mass gradients
WALL_LAYERS = 3  # outer node layers with slip walls (contract)


@ti.func
def pick(cond, a, b):
    """a where cond holds, else b, component by component of two 3-vectors: a select, which
    Taichi's reverse mode takes without an adjoint stack (see ``GridKernels.forces_at``)."""
    return ti.Vector([ti.select(cond, a[d], b[d]) for d in ti.static(range(3))])


@ti.func
def slip_wall(v, node, n_nodes):
    """One velocity component v at node index ``node`` of ``n_nodes``: no outward component in
    the outer ``WALL_LAYERS`` layers on either side."""
    low = ti.select(node < WALL_LAYERS, ti.max(v, 0.0), v)
    return ti.select(node >= n_nodes - WALL_LAYERS, ti.min(low, 0.0), low)


@ti.data_oriented
class GridKernels:
    """Grid-node kernels of ``MPMKernels`` (which provides the fields and the grid's shape)."""

    @ti.kernel
    def grid_forces(self, dt: ti.f32, time: ti.f32, ground_h: ti.f32):
        """v = (m v)/m + dt (gravity + wind - c_lin v - c_quad |v| v + expression) on nodes
        with mass; ``time`` (s) since frame 0 at this substep, ``ground_h`` (m) the ground's
        height (0 without one) for the expression's height feature."""
        for I in ti.grouped(self.m):
            self.forces_at(I, dt, time, ground_h)

    @ti.func
    def forces_at(self, I, dt, time, ground_h):
        """``grid_forces`` at node I = (field, i, j, l). Every local is assigned once and each
        branch writes the node itself: Taichi's reverse mode turns a local that is stored again
        after being read into an adjoint stack (``AdStackAllocaStmt``) unless its
        simplification removes the local first, which it cannot across a branch."""
        if self.m[I] > MASS_EPS:
            vel = self.mv[I] / self.m[I]
            speed = ti.sqrt(vel.dot(vel) + NORMAL_EPS)
            acc = (self.gravity[None] + self.wind[None]) - (
                self.lin_drag[None] * vel + self.quad_drag[None] * speed * vel
            )
            if self.expr_on[None] != 0:
                node = self.origin + self.dx * ti.Vector([I[1], I[2], I[3]], ti.f32)
                extra = self._expression(node, vel, speed, time, ground_h)
                self.vf[I] = vel + dt * (acc + extra)
            else:
                self.vf[I] = vel + dt * acc
        else:
            self.vf[I] = ti.Vector.zero(ti.f32, 3)

    @ti.func
    def _expression(self, x, v, speed, time, ground_h):
        """a = sum_k c_k phi_k over expression.NODE_FEATURES in their order: 1, x, y, z, h,
        v_x..v_z, |v|v_x..|v|v_z, t; c_k = expr_coef[k] = (c in a_x, a_y, a_z)."""
        h = x.dot(self.up[None]) - ground_h
        a = self.expr_coef[0] + x[0] * self.expr_coef[1] + x[1] * self.expr_coef[2]
        a += x[2] * self.expr_coef[3] + h * self.expr_coef[4]
        a += v[0] * self.expr_coef[5] + v[1] * self.expr_coef[6] + v[2] * self.expr_coef[7]
        a += (speed * v[0]) * self.expr_coef[8] + (speed * v[1]) * self.expr_coef[9]
        a += (speed * v[2]) * self.expr_coef[10]
        return a + time * self.expr_coef[11]

    @ti.func
    def _coulomb(self, rel, normal, mu):
        """Remove the approaching normal part of rel and apply Coulomb friction mu (tangential
        change at most mu times the normal change; full stop beyond). Both outcomes are
        computed and one is selected (no branch: see ``forces_at``)."""
        vn = rel.dot(normal)
        tangent = rel - vn * normal
        t_norm = ti.sqrt(tangent.dot(tangent) + NORMAL_EPS)
        return pick(vn > 0.0, tangent * ti.max(1.0 - mu * vn / t_norm, 0.0), rel)

    @ti.func
    def _ground(self, vel, v_in, mu, e):
        """Table contact (outward normal -e_z), ``_coulomb`` at e = 0: moving down (v_z < 0),
        v_z <- e max(-v_in, 0) and the tangential speed drops by mu (|v_z| + e max(-v_in, 0))
        (full stop beyond). v_in (m/s) is the arriving normal velocity, before this substep's
        stress and body-force impulse: only arriving material bounces, a body pressed onto the
        table is stopped rather than re-launched every substep (which pumps energy)."""
        vn = -vel[2]
        tangent = ti.Vector([vel[0], vel[1], 0.0])
        t_norm = ti.sqrt(tangent.dot(tangent) + NORMAL_EPS)
        bounce = e * ti.max(-v_in, 0.0)
        scale = ti.max(1.0 - mu * (vn + bounce) / t_norm, 0.0)
        landed = ti.Vector([tangent[0] * scale, tangent[1] * scale, bounce])
        return pick(vn > 0.0, landed, vel)

    @ti.func
    def _walls(self, i, j, l, vel):
        """Slip walls: no outward normal velocity in the outer ``WALL_LAYERS`` node layers."""
        node = ti.Vector([i, j, l])
        return ti.Vector([
            slip_wall(vel[d], node[d], self.nodes[d]) for d in ti.static(range(3))
        ])  # fmt: skip

    @ti.kernel
    def grid_contact(self, ground_z: ti.f32, has_ground: ti.i32):
        """Multi-field contact (mu = (mu_a + mu_b)/2, free separation), ground, slip walls."""
        for i, j, l in ti.ndrange(*self.nodes):
            self.contact_at(i, j, l, ground_z, has_ground)

    @ti.func
    def contact_at(self, i, j, l, ground_z, has_ground):
        """``grid_contact`` at the nodes (i, j, l) of every field. A field without mass at the
        node gets zero velocity (as ``forces_at`` leaves it: contact, ground and walls keep a
        zero velocity zero) without reading anything else."""
        m_tot = 0.0
        mom = ti.Vector.zero(ti.f32, 3)
        grad_sum = ti.Vector.zero(ti.f32, 3)
        fric_mass = 0.0
        n_with_mass = 0
        for g in ti.static(range(self.G)):  # straight-line sums: no adjoint stack
            m_tot += self.m[g, i, j, l]
            mom += self.m[g, i, j, l] * self.vf[g, i, j, l]
            if ti.static(self.multi):
                grad_sum += self.gm[g, i, j, l]
                fric_mass += self.m[g, i, j, l] * self.friction[g]
            n_with_mass += ti.select(self.m[g, i, j, l] > MASS_EPS, 1, 0)
        v_cm = mom / ti.max(m_tot, MASS_EPS)
        z = self.origin[2] + l * self.dx
        below = ti.select(z <= ground_z, has_ground, 0)
        for g in ti.static(range(self.G)):
            m_g = self.m[g, i, j, l]
            if m_g > MASS_EPS:
                vel = self.vf[g, i, j, l]
                if ti.static(self.multi):
                    if n_with_mass >= 2:
                        # outward normal of object g: towards the others' mass, away from its own
                        raw = grad_sum - 2.0 * self.gm[g, i, j, l]
                        nrm = raw / ti.sqrt(raw.dot(raw) + NORMAL_EPS)
                        mu_other = (fric_mass - m_g * self.friction[g]) / ti.max(
                            m_tot - m_g, MASS_EPS
                        )
                        mu = 0.5 * (self.friction[g] + mu_other)
                        self._ground_and_walls(
                            g, i, j, l, v_cm + self._coulomb(vel - v_cm, nrm, mu), below
                        )
                    else:
                        self._ground_and_walls(g, i, j, l, vel, below)
                else:
                    self._ground_and_walls(g, i, j, l, vel, below)
            else:
                self.vg[g, i, j, l] = ti.Vector.zero(ti.f32, 3)

    @ti.func
    def _ground_and_walls(self, g, i, j, l, vel, below):
        """Field g's node (i, j, l) after its contact velocity ``vel``: the table where
        ``below`` (the node at or under it), then the walls, written to ``vg``."""
        if below != 0:
            # outward normal of the table is -e_z: moving down = approaching it
            v_in = self.pm[g, i, j, l][2] / ti.max(self.m[g, i, j, l], MASS_EPS)
            landed = self._ground(vel, v_in, self.ground_mu[None], self.ground_e[None])
            self.vg[g, i, j, l] = self._walls(i, j, l, landed)
        else:
            self.vg[g, i, j, l] = self._walls(i, j, l, vel)
