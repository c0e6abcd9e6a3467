"""Particle-grid transfers of MLS-MPM (Hu et al. 2018): each of P2G and G2P split in two kernels.

The backward's taped replay launches, in a substep, in order:

1. ``particle_stress`` of each law present: each particle's stress impulse -dt (4 / dx^2) V0 tau
   (tau the law's Kirchhoff stress plus the material_damping viscous stress), a 3x3 matrix a
   particle;
2. ``p2g``: the scatter of mass, momentum m v + (stress impulse + m C) dpos, contact normals
   and the ground layers' arriving momentum onto the 27 nodes around each particle;
3. the grid kernels (kernels.py);
4. ``g2p``: the gather of velocity v = sum w v_i and affine C = 4/dx^2 sum w v_i dpos^T, and
   the advection x += dt v;
5. ``update_deformation`` of each law present: F <- return_map((I + dt C) F) per particle, with
   the new C.

Why split: the laws' stress and return map are switches over every law, several through an
SVD with its hand-written adjoint. Inside the 27-node scatter and gather, Warp's adjoint of
such a kernel holds every branch's reverse code and the unrolled node loop at once, and the
register pressure of the largest branch sets the occupancy of every particle's adjoint, an
elastic body's too. Split, the scatter's and the gather's adjoints are short arithmetic over
the nodes, and the laws' adjoints run once per particle in kernels without the node loop. Those
kernels are made once per law (``PARTICLE_STRESS``, ``UPDATE_DEFORMATION``, from laws.STRESS_OF
and laws.RETURN_MAP_OF), each holding its own law's code only: a particle of another law returns
at once, so a scene launches each for the laws it has, and an elastic body's adjoint carries no
SVD.
What passes between the halves is one matrix a particle (the stress impulse) and the new C,
which the state holds anyway, so the backward's taped replay needs no extra saved state.

Rollouts that no tape records (forward rollouts, the backward's re-simulation) run the fused
forms ``p2g_fused`` and ``g2p_fused`` instead: the law's stress inside the scatter and its return
map inside the gather, two launches a substep fewer and no stress buffer, where a forward kernel
carrying every law's branches costs little. Only the taped replay runs the split kernels, for
their adjoints. Both forms compute the same values in the same order: bit for bit on the CPU
(tests/test_transfer_reads.py). They differ only for a particle that diverged: the fused G2P
resets x, v, C, F and plastic_J together, the split kernels reset x, v, C in the gather and F,
plastic_J in the update, each flagging the substep (the backward raises on a flag of its
re-simulation, so a replay never goes on from there).

Each kernel reads each particle array once per thread, into a local used from then on (Warp's
adjoint of a read a[p] is one atomic add into a's gradient per read in the code; kernels.py).
Law parameters, density and viscosity come from the per-object tables or, taped, from the
particle's copy (``per_particle``, kernels.parameter_rows).
"""

from __future__ import annotations

import warp as wp

from mosiv_framework.laws import FAMILIES
from mosiv_warp_mpm.kernels import (
    REASON_CFL,
    REASON_NONFINITE,
    bspline_slopes,
    bspline_weights,
    cell_base,
    kelvin_voigt_tau,
    parameter_rows,
)
from mosiv_warp_mpm.laws import RETURN_MAP_OF, STRESS_OF, kirchhoff_stress, return_map, vec5
from mosiv_warp_mpm.node_window import node_index


def _particle_stress(law: int, law_stress):
    """The particle_stress kernel of one law (``law_stress``: laws.STRESS_OF[law])."""

    def particle_stress(
        C: wp.array(dtype=wp.mat33),
        F: wp.array(dtype=wp.mat33),
        plastic_J: wp.array(dtype=float),
        volume: wp.array(dtype=float),
        obj: wp.array(dtype=int),
        law_of: wp.array(dtype=int),
        params: wp.array(dtype=vec5),
        damping: wp.array(dtype=float),
        dx: float,
        dt: float,
        objects_per_member: int,
        per_particle: int,
        stress: wp.array(dtype=wp.mat33),
    ):
        # stress impulse -dt (4 / dx^2) V0 (tau_law + tau_visc) of the particles of this law:
        # the MLS-MPM force on the grid is this matrix times each node's offset dpos, weighted
        p = wp.tid()
        o = obj[p]
        if law_of[o] != law:
            return
        q, b = parameter_rows(p, o, objects_per_member, per_particle)
        Cp = C[p]
        Fp = F[p]
        tau = law_stress(params[q], Fp, Cp, plastic_J[p])
        tau = tau + kelvin_voigt_tau(damping[b], Fp, Cp)
        inv_dx = 1.0 / dx
        stress[p] = (-dt * 4.0 * inv_dx * inv_dx * volume[p]) * tau

    return wp.kernel(particle_stress, name=f"particle_stress_{FAMILIES[law]}")


#: law id -> its particle_stress kernel
PARTICLE_STRESS = {law: _particle_stress(law, f) for law, f in STRESS_OF.items()}


def _scatter(
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    C: wp.array(dtype=wp.mat33),
    stress: wp.array(dtype=wp.mat33),
    volume: wp.array(dtype=float),
    obj: wp.array(dtype=int),
    field_of: wp.array(dtype=int),
    rho: wp.array(dtype=float),
    origin: wp.vec3,
    dx: float,
    nodes: wp.vec3i,
    with_normals: int,
    ground_k: float,
    objects_per_member: int,
    per_particle: int,
    grid_m: wp.array(dtype=float),
    grid_mv: wp.array(dtype=wp.vec3),
    grid_gm: wp.array(dtype=wp.vec3),
    grid_pm: wp.array(dtype=wp.vec3),
):
    # MLS-MPM P2G: m w, w (m v + (stress impulse + m C) dpos), m grad w (contact normals);
    # on ground-layer nodes also w (m v + m C dpos): the arriving momentum, before this
    # substep's stress impulse (kernels.ground_contact)
    p = wp.tid()
    o = obj[p]
    f = field_of[o]
    q, b = parameter_rows(p, o, objects_per_member, per_particle)
    xp = x[p]
    vp = v[p]
    Cp = C[p]
    m = rho[q] * volume[p]
    inv_dx = 1.0 / dx
    affine = stress[p] + m * Cp
    xl = (xp - origin) * inv_dx
    base = cell_base(xl)
    fx = xl - wp.vec3(float(base[0]), float(base[1]), float(base[2]))
    W = bspline_weights(fx)
    D = bspline_slopes(fx)
    mom = m * vp
    for i in range(3):
        for j in range(3):
            for k in range(3):
                w = W[i, 0] * W[j, 1] * W[k, 2]
                dpos = (wp.vec3(float(i), float(j), float(k)) - fx) * dx
                n = node_index(f, base[0] + i, base[1] + j, base[2] + k, nodes)
                wp.atomic_add(grid_m, n, w * m)
                wp.atomic_add(grid_mv, n, w * (mom + affine * dpos))
                if float(base[2] + k) <= ground_k:  # for ground_restitution (ground_contact)
                    wp.atomic_add(grid_pm, n, w * (mom + m * (Cp * dpos)))
                if with_normals != 0:  # contact normals matter only with several fields
                    grad_w = inv_dx * wp.vec3(
                        D[i, 0] * W[j, 1] * W[k, 2],
                        W[i, 0] * D[j, 1] * W[k, 2],
                        W[i, 0] * W[j, 1] * D[k, 2],
                    )
                    wp.atomic_add(grid_gm, n, m * grad_w)


p2g = wp.kernel(_scatter, name="p2g")

#: the same scatter with its node loops left as loops (max_unroll 1), for the backward's taped
#: replay: Warp's adjoint of the unrolled scatter holds the values of all 27 nodes at once,
#: while a loop's adjoint replays one node at a time. Only recorded on tapes, never launched
#: forward (MPMRun.p2g runs the unrolled p2g): its forward's atomics in a dynamic loop could
#: exceed the records that deterministic atomics size per thread, its adjoint has none there
p2g_looped = wp.kernel(
    _scatter, name="p2g_looped", module="unique", module_options={"max_unroll": 1}
)


@wp.kernel
def g2p(
    x: wp.array(dtype=wp.vec3),
    obj: wp.array(dtype=int),
    field_of: wp.array(dtype=int),
    grid_v: wp.array(dtype=wp.vec3),
    origin: wp.vec3,
    dx: float,
    dt: float,
    nodes: wp.vec3i,
    substep: int,
    flag: wp.array(dtype=int),
    x_out: wp.array(dtype=wp.vec3),
    v_out: wp.array(dtype=wp.vec3),
    C_out: wp.array(dtype=wp.mat33),
):
    # MLS-MPM G2P: v = sum w v_i, C = 4/dx^2 sum w v_i dpos^T, x += dt v (F: update_deformation)
    p = wp.tid()
    o = obj[p]
    f = field_of[o]
    xp = x[p]
    inv_dx = 1.0 / dx
    xl = (xp - origin) * inv_dx
    base = cell_base(xl)
    fx = xl - wp.vec3(float(base[0]), float(base[1]), float(base[2]))
    W = bspline_weights(fx)
    vn = wp.vec3()
    Cn = wp.mat33()
    for i in range(3):
        for j in range(3):
            for k in range(3):
                w = W[i, 0] * W[j, 1] * W[k, 2]
                dpos = (wp.vec3(float(i), float(j), float(k)) - fx) * dx
                gv = grid_v[node_index(f, base[0] + i, base[1] + j, base[2] + k, nodes)]
                vn += w * gv
                Cn += (4.0 * inv_dx * inv_dx * w) * wp.outer(gv, dpos)
    xn = xp + dt * vn
    if not (wp.isfinite(xn) and wp.isfinite(vn) and wp.isfinite(Cn)):
        # keep the state usable (no out-of-grid index next substep); the host raises at frame end
        wp.atomic_min(flag, o, substep * 4 + REASON_NONFINITE)
        xn = xp
        vn = wp.vec3()
        Cn = wp.mat33()
    elif wp.length(dt * vn) > dx:
        # moving more than one cell per substep breaks the CFL condition of explicit MPM
        wp.atomic_min(flag, o, substep * 4 + REASON_CFL)
    # particles stay in the padded interior, so the 3x3x3 stencil never leaves the grid
    lo = origin + wp.vec3(2.0 * dx)
    hi = origin + dx * wp.vec3(float(nodes[0] - 3), float(nodes[1] - 3), float(nodes[2] - 3))
    x_out[p] = wp.vec3(
        wp.clamp(xn[0], lo[0], hi[0]), wp.clamp(xn[1], lo[1], hi[1]), wp.clamp(xn[2], lo[2], hi[2])
    )
    v_out[p] = vn
    C_out[p] = Cn


def _update_deformation(law: int, law_return_map):
    """The update_deformation kernel of one law (``law_return_map``: laws.RETURN_MAP_OF[law])."""

    def update_deformation(
        C_new: wp.array(dtype=wp.mat33),
        F: wp.array(dtype=wp.mat33),
        plastic_J: wp.array(dtype=float),
        obj: wp.array(dtype=int),
        law_of: wp.array(dtype=int),
        params: wp.array(dtype=vec5),
        per_particle: int,
        dt: float,
        substep: int,
        flag: wp.array(dtype=int),
        F_out: wp.array(dtype=wp.mat33),
        plastic_J_out: wp.array(dtype=float),
    ):
        # F <- return_map((I + dt C) F) with G2P's new C, for the particles of this law; the
        # law's parameters from the object's table row or, per_particle, the particle's copy
        p = wp.tid()
        o = obj[p]
        if law_of[o] != law:
            return
        q, b = parameter_rows(p, o, 1, per_particle)
        F_trial = (wp.identity(n=3, dtype=float) + dt * C_new[p]) * F[p]
        Fn, pj = law_return_map(params[q], F_trial, plastic_J[p], dt)
        if not (wp.isfinite(Fn) and wp.isfinite(pj)):
            wp.atomic_min(flag, o, substep * 4 + REASON_NONFINITE)
            Fn = wp.identity(n=3, dtype=float)
            pj = 1.0
        F_out[p] = Fn
        plastic_J_out[p] = pj

    return wp.kernel(update_deformation, name=f"update_deformation_{FAMILIES[law]}")


#: law id -> its update_deformation kernel
UPDATE_DEFORMATION = {law: _update_deformation(law, f) for law, f in RETURN_MAP_OF.items()}


# -- fused forms, for rollouts that are not taped -------------------------------------------


@wp.kernel
def p2g_fused(
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    C: wp.array(dtype=wp.mat33),
    F: wp.array(dtype=wp.mat33),
    plastic_J: wp.array(dtype=float),
    volume: wp.array(dtype=float),
    obj: wp.array(dtype=int),
    law_of: wp.array(dtype=int),
    field_of: wp.array(dtype=int),
    params: wp.array(dtype=vec5),
    rho: wp.array(dtype=float),
    damping: wp.array(dtype=float),
    origin: wp.vec3,
    dx: float,
    dt: float,
    nodes: wp.vec3i,
    with_normals: int,
    ground_k: float,
    objects_per_member: int,
    per_particle: int,
    grid_m: wp.array(dtype=float),
    grid_mv: wp.array(dtype=wp.vec3),
    grid_gm: wp.array(dtype=wp.vec3),
    grid_pm: wp.array(dtype=wp.vec3),
):
    # per_particle: read the particle's parameter copies, not the tables (parameter_rows).
    # MLS-MPM P2G: m w, w (m v + (-dt 4/dx^2 V0 tau + m C) dpos), m grad w (contact normals);
    # tau = the law's Kirchhoff stress + the material_damping viscous stress. On ground-layer
    # nodes also w (m v + m C dpos): the arriving momentum, before this substep's stress impulse
    p = wp.tid()
    o = obj[p]
    f = field_of[o]
    q, b = parameter_rows(p, o, objects_per_member, per_particle)
    # each particle array read once (module docstring): C is used three times and once per
    # ground-layer node, F and the volume twice
    xp = x[p]
    vp = v[p]
    Cp = C[p]
    Fp = F[p]
    Jp = plastic_J[p]
    vol = volume[p]
    m = rho[q] * vol
    inv_dx = 1.0 / dx
    tau = kirchhoff_stress(law_of[o], params[q], Fp, Cp, Jp)
    tau = tau + kelvin_voigt_tau(damping[b], Fp, Cp)
    affine = (-dt * 4.0 * inv_dx * inv_dx * vol) * tau + m * Cp
    xl = (xp - origin) * inv_dx
    base = cell_base(xl)
    fx = xl - wp.vec3(float(base[0]), float(base[1]), float(base[2]))
    W = bspline_weights(fx)
    D = bspline_slopes(fx)
    mom = m * vp
    for i in range(3):
        for j in range(3):
            for k in range(3):
                w = W[i, 0] * W[j, 1] * W[k, 2]
                grad_w = inv_dx * wp.vec3(
                    D[i, 0] * W[j, 1] * W[k, 2],
                    W[i, 0] * D[j, 1] * W[k, 2],
                    W[i, 0] * W[j, 1] * D[k, 2],
                )
                dpos = (wp.vec3(float(i), float(j), float(k)) - fx) * dx
                n = node_index(f, base[0] + i, base[1] + j, base[2] + k, nodes)
                wp.atomic_add(grid_m, n, w * m)
                wp.atomic_add(grid_mv, n, w * (mom + affine * dpos))
                if float(base[2] + k) <= ground_k:  # for ground_restitution (ground_contact)
                    wp.atomic_add(grid_pm, n, w * (mom + m * (Cp * dpos)))
                if with_normals != 0:  # contact normals matter only with several fields
                    wp.atomic_add(grid_gm, n, m * grad_w)


@wp.kernel
def g2p_fused(
    x: wp.array(dtype=wp.vec3),
    F: wp.array(dtype=wp.mat33),
    plastic_J: wp.array(dtype=float),
    obj: wp.array(dtype=int),
    law_of: wp.array(dtype=int),
    field_of: wp.array(dtype=int),
    params: wp.array(dtype=vec5),
    per_particle: int,
    grid_v: wp.array(dtype=wp.vec3),
    origin: wp.vec3,
    dx: float,
    dt: float,
    nodes: wp.vec3i,
    substep: int,
    flag: wp.array(dtype=int),
    x_out: wp.array(dtype=wp.vec3),
    v_out: wp.array(dtype=wp.vec3),
    C_out: wp.array(dtype=wp.mat33),
    F_out: wp.array(dtype=wp.mat33),
    plastic_J_out: wp.array(dtype=float),
):
    # MLS-MPM G2P: v = sum w v_i, C = 4/dx^2 sum w v_i dpos^T, F <- return_map((I + dt C) F), x += dt v;
    # the law's parameters from the object's table row or, per_particle, the particle's copy
    p = wp.tid()
    o = obj[p]
    f = field_of[o]
    xp = x[p]  # read once (module docstring): the position is used two or three times
    inv_dx = 1.0 / dx
    xl = (xp - origin) * inv_dx
    base = cell_base(xl)
    fx = xl - wp.vec3(float(base[0]), float(base[1]), float(base[2]))
    W = bspline_weights(fx)
    vn = wp.vec3()
    Cn = wp.mat33()
    for i in range(3):
        for j in range(3):
            for k in range(3):
                w = W[i, 0] * W[j, 1] * W[k, 2]
                dpos = (wp.vec3(float(i), float(j), float(k)) - fx) * dx
                gv = grid_v[node_index(f, base[0] + i, base[1] + j, base[2] + k, nodes)]
                vn += w * gv
                Cn += (4.0 * inv_dx * inv_dx * w) * wp.outer(gv, dpos)
    F_trial = (wp.identity(n=3, dtype=float) + dt * Cn) * F[p]
    q, b = parameter_rows(p, o, 1, per_particle)
    Fn, pj = return_map(law_of[o], params[q], F_trial, plastic_J[p], dt)
    xn = xp + dt * vn
    finite = wp.isfinite(xn) and wp.isfinite(vn) and wp.isfinite(Fn) and wp.isfinite(Cn)
    finite = finite and wp.isfinite(pj)
    if not finite:
        # keep the state usable (no out-of-grid index next substep); the host raises at frame end
        wp.atomic_min(flag, o, substep * 4 + REASON_NONFINITE)
        xn = xp
        vn = wp.vec3()
        Cn = wp.mat33()
        Fn = wp.identity(n=3, dtype=float)
        pj = 1.0
    elif wp.length(dt * vn) > dx:
        # moving more than one cell per substep breaks the CFL condition of explicit MPM
        wp.atomic_min(flag, o, substep * 4 + REASON_CFL)
    # particles stay in the padded interior, so the 3x3x3 stencil never leaves the grid
    lo = origin + wp.vec3(2.0 * dx)
    hi = origin + dx * wp.vec3(float(nodes[0] - 3), float(nodes[1] - 3), float(nodes[2] - 3))
    x_out[p] = wp.vec3(
        wp.clamp(xn[0], lo[0], hi[0]), wp.clamp(xn[1], lo[1], hi[1]), wp.clamp(xn[2], lo[2], hi[2])
    )
    v_out[p] = vn
    C_out[p] = Cn
    F_out[p] = Fn
    plastic_J_out[p] = pj
