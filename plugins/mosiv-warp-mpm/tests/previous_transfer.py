"""The P2G and G2P kernels as they were before each was split in two (transfer_kernels.py,
module docstring: the laws' stress and return map moved into kernels of their own), kept
verbatim with the launches that drove them, so that test_transfer_reads.py can compare the
rollouts and gradients of both. Not used by the simulator."""

from __future__ import annotations

import warp as wp
from mosiv_warp_mpm.kernels import (
    REASON_CFL,
    REASON_NONFINITE,
    bspline_slopes,
    bspline_weights,
    cell_base,
    kelvin_voigt_tau,
    node_index,
    parameter_rows,
)
from mosiv_warp_mpm.laws import kirchhoff_stress, return_map, vec5


@wp.kernel
def p2g(
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
def g2p(
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


def fused_p2g(run, src, grid, gathered=None, stress=None, looped_on=None) -> None:
    """MPMRun.p2g as it was: one launch, the stress inside the scatter (``stress`` and
    ``looped_on`` unused: the launch goes on the tape being recorded, if any)."""
    lay, t = run.layout, run.tables
    origin, nodes = wp.vec3(*lay.origin), wp.vec3i(*lay.nodes)
    law_inputs = [t.params, t.rho, t.damping] if gathered is None else gathered.arrays()
    wp.launch(
        p2g,
        dim=run.n,
        inputs=[src.x, src.v, src.C, src.F, src.plastic_J, run.volume, run.obj]
        + [t.law_of, t.field_of, *law_inputs, origin, lay.dx, run.dt, nodes]
        + [int(lay.fields > 1), run.ground_k if run.ground_on else -1.0, t.k]
        + [int(gathered is not None)],
        outputs=[grid.m, grid.mv, grid.gm, grid.pm],
        device=run.device,
    )


def fused_g2p_launches(run, src, dst, grid, s, gathered=None, *, split=False) -> list[tuple]:
    """MPMRun._g2p_launches as it was: one launch, the return map inside the gather (also
    where the taped replay asks for the ``split`` form)."""
    lay, t = run.layout, run.tables
    origin, nodes = wp.vec3(*lay.origin), wp.vec3i(*lay.nodes)
    law_params = t.params if gathered is None else gathered.params
    inputs = [src.x, src.F, src.plastic_J, run.obj, t.law_of, t.field_of, law_params]
    inputs += [int(gathered is not None), grid.v, origin, lay.dx, run.dt, nodes, s, run.flag]
    return [(g2p, inputs, [dst.x, dst.v, dst.C, dst.F, dst.plastic_J])]
