"""Kernels of the ``expression`` term: a discovered force law a = sum c phi on grid nodes.

The law and its features are defined in ``mosiv_framework.expression`` (docs/PHYSICS.md,
Physics terms); ``kernels.grid_free_velocity`` adds ``expression_acceleration`` to a node's
acceleration. The coefficients are a differentiable table (ObjectTables.expr_coef, one vec3
(a_x, a_y, a_z) per feature, per batch member); Warp differentiates the straight-line sum
below, so every coefficient's gradient is the node's adjoint velocity times dt times its
feature, accumulated over nodes and substeps.

The other objects' features (dp, dv) need each object's centre of mass and velocity at the
substep's start. They come from the grid after P2G: per field f, sum_i m_i = M_f,
sum_i m_i x_i = M_f c_f and sum_i (m v)_i = M_f u_f exactly, because quadratic B-spline weights
sum to 1 and reproduce linear functions (sum_i w_ip x_i = x_p), and APIC's affine part adds no
net momentum (sum_i w_ip (x_i - x_p) = 0). ``field_moments`` accumulates those sums and
``other_centres`` the sums over the other fields j != f of c_j and u_j, both with atomic adds,
whose adjoints Warp derives; a loop over fields accumulating locals would not be
differentiable (field_sums.py says why).
"""

from __future__ import annotations

import warp as wp

from mosiv_framework.expression import FEATURES
from mosiv_warp_mpm.laws import safe_norm
from mosiv_warp_mpm.node_window import node_index, window_count, window_ijk

N_FEATURES = wp.constant(len(FEATURES))
MOMENT_EPS = wp.constant(1.0e-12)  # kg: a field lighter than this has no centre


@wp.func
def expression_acceleration(
    coef: wp.array(dtype=wp.vec3),
    c0: int,
    x: wp.vec3,
    v: wp.vec3,
    t: float,
    h: float,
    dp: wp.vec3,
    dv: wp.vec3,
):
    # a = sum_k c_k phi_k over expression.FEATURES in their order: 1, x, y, z, h, v_x..v_z,
    # |v|v_x..|v|v_z, t, dp_x..dp_z, dv_x..dv_z; c_k = coef[c0 + k] = (c in a_x, a_y, a_z)
    s = safe_norm(v)
    a = coef[c0] + x[0] * coef[c0 + 1] + x[1] * coef[c0 + 2] + x[2] * coef[c0 + 3]
    a = a + h * coef[c0 + 4]
    a = a + v[0] * coef[c0 + 5] + v[1] * coef[c0 + 6] + v[2] * coef[c0 + 7]
    a = a + (s * v[0]) * coef[c0 + 8] + (s * v[1]) * coef[c0 + 9] + (s * v[2]) * coef[c0 + 10]
    a = a + t * coef[c0 + 11]
    a = a + dp[0] * coef[c0 + 12] + dp[1] * coef[c0 + 13] + dp[2] * coef[c0 + 14]
    a = a + dv[0] * coef[c0 + 15] + dv[1] * coef[c0 + 16] + dv[2] * coef[c0 + 17]
    return a


@wp.func
def node_expression(
    coef: wp.array(dtype=wp.vec3),
    b: int,
    field: int,
    x: wp.vec3,
    v: wp.vec3,
    t: float,
    up: wp.vec3,
    ground: float,
    rel_p: wp.array(dtype=wp.vec3),
    rel_v: wp.array(dtype=wp.vec3),
    rel_n: wp.array(dtype=float),
):
    # the expression at a node of field ``field`` (b F + f) of member b: h = x . up - ground,
    # dp = sum_{j != f} c_j - n x, dv = sum_{j != f} u_j - n v (n: other fields with mass)
    n = rel_n[field]
    dp = rel_p[field] - n * x
    dv = rel_v[field] - n * v
    return expression_acceleration(coef, b * N_FEATURES, x, v, t, wp.dot(x, up) - ground, dp, dv)


@wp.kernel
def field_moments(
    grid_m: wp.array(dtype=float),
    grid_mv: wp.array(dtype=wp.vec3),
    expr_switch: wp.array(dtype=float),
    origin: wp.vec3,
    dx: float,
    boxes: wp.array(dtype=wp.vec3i),
    row: int,
    stride: int,
    nodes: wp.vec3i,
    fields_per_member: int,
    moment_m: wp.array(dtype=float),
    moment_mx: wp.array(dtype=wp.vec3),
    moment_mv: wp.array(dtype=wp.vec3),
):
    """Per field (b F + f): M = sum m_i, sum m_i x_i and sum (m v)_i over the box's nodes.

    Args:
        grid_m, grid_mv: node mass (kg) and momentum (kg m/s) after P2G.
        expr_switch: per member (expression on, uses the other objects); only members with
            the second switch on are summed.
        origin, dx: node (0, 0, 0)'s position (m) and the node spacing (m).
        boxes, row, stride: the nodes visited (state.Window); nodes: the grid size.
        fields_per_member: F.

    Returns:
        moment_m [B F] (kg), moment_mx [B F] (kg m), moment_mv [B F] (kg m/s), accumulated
        (cleared by Grid.clear).
    """
    # the window's (field, node) pairs, field slowest, k fastest (node_window)
    t = wp.tid()
    count = window_count(boxes, row)
    if t % stride < count:  # as in kernels.grid_free_velocity
        for r in range(t % stride, count, stride):
            field_moment_at(
                t // stride, window_ijk(boxes, row, r), grid_m, grid_mv, expr_switch, origin,
                dx, nodes, fields_per_member, moment_m, moment_mx, moment_mv,
            )  # fmt: skip


@wp.func
def field_moment_at(
    field: int,
    c: wp.vec3i,
    grid_m: wp.array(dtype=float),
    grid_mv: wp.array(dtype=wp.vec3),
    expr_switch: wp.array(dtype=float),
    origin: wp.vec3,
    dx: float,
    nodes: wp.vec3i,
    fields_per_member: int,
    moment_m: wp.array(dtype=float),
    moment_mx: wp.array(dtype=wp.vec3),
    moment_mv: wp.array(dtype=wp.vec3),
):
    # field_moments' sums at node c of ``field``
    b = field // fields_per_member
    n = node_index(field, c[0], c[1], c[2], nodes)
    m = grid_m[n]
    if expr_switch[2 * b + 1] > 0.5 and m > 0.0:
        x = origin + dx * wp.vec3(float(c[0]), float(c[1]), float(c[2]))
        wp.atomic_add(moment_m, field, m)
        wp.atomic_add(moment_mx, field, m * x)
        wp.atomic_add(moment_mv, field, grid_mv[n])


@wp.kernel
def other_centres(
    moment_m: wp.array(dtype=float),
    moment_mx: wp.array(dtype=wp.vec3),
    moment_mv: wp.array(dtype=wp.vec3),
    expr_switch: wp.array(dtype=float),
    fields_per_member: int,
    rel_p: wp.array(dtype=wp.vec3),
    rel_v: wp.array(dtype=wp.vec3),
    rel_n: wp.array(dtype=float),
):
    """Per field f of member b: the sums over the member's other fields j of their centres
    of mass and velocities, and how many there are; one thread per (b, f, j).

    Args:
        moment_m, moment_mx, moment_mv: ``field_moments``'s sums.
        expr_switch: per member (expression on, uses the other objects).
        fields_per_member: F.

    Returns:
        rel_p [B F] sum_j c_j (m), rel_v [B F] sum_j u_j (m/s), rel_n [B F] the count,
        accumulated (cleared by Grid.clear).
    """
    t = wp.tid()
    F = fields_per_member
    b = t // (F * F)
    f = (t // F) % F
    j = t % F
    g = b * F + j
    m = moment_m[g]
    if expr_switch[2 * b + 1] > 0.5 and j != f and m > MOMENT_EPS:
        wp.atomic_add(rel_p, b * F + f, moment_mx[g] / m)
        wp.atomic_add(rel_v, b * F + f, moment_mv[g] / m)
        wp.atomic_add(rel_n, b * F + f, 1.0)


@wp.kernel
def evaluate_expression(
    coef: wp.array(dtype=wp.vec3),
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    t: wp.array(dtype=float),
    up: wp.vec3,
    ground: float,
    rel_p: wp.array(dtype=wp.vec3),
    rel_v: wp.array(dtype=wp.vec3),
    rel_n: wp.array(dtype=float),
    out: wp.array(dtype=wp.vec3),
):
    """``node_expression`` at given points (tests compare it with the torch reference).

    Args:
        coef: [N_FEATURES] coefficients (member 0); x, v, t: [N] positions (m), velocities
            (m/s), times (s); up, ground: the scene's up and ground height (m); rel_p, rel_v,
            rel_n: [N] the other objects' summed centres, velocities and count, per point.

    Returns:
        out: [N] accelerations (m/s^2).
    """
    p = wp.tid()
    out[p] = node_expression(coef, 0, p, x[p], v[p], t[p], up, ground, rel_p, rel_v, rel_n)
