"""MLS-MPM grid kernels (Hu et al. 2018, APIC, quadratic B-splines) for several objects at once,
and the helpers the particle-grid transfers share (transfer_kernels.py holds the transfers).

Grid arrays are flat: field f, node (i, j, k) lives at ((f * NX + i) * NY + j) * NZ + k, with
NX, NY, NZ node counts. In multi-field mode field f is object index f; in single-field mode every
object uses field 0. Kernels never write an array they read, so Warp's tape can replay them.

Batched rollouts (batched.py) run B members of one scene in the same launches: particle p of
member b carries object index o = b K + k (K objects per member), so the per-object tables hold
B K rows, member-major, and object o's field is b F + f (F fields per member): B grids, one
after the other in the flat arrays. Per-member scalars (body acceleration, drag, damping, ground
coefficients) are indexed by b. A single rollout is the batch of one (b = 0).

P2G and G2P read the law parameters, density and viscosity from the per-object tables or, in
the backward's taped replay, from each particle's copy of them (``per_particle``,
parameter_rows): same values, same results, but uncontended parameter adjoints. Likewise
grid_free_velocity reads the body acceleration and drag, and grid_boundaries the contact
friction and the ground's friction and restitution, from the per-member and per-object tables
or, taped, from each node's copy (``per_node``, state.NodeCoefficients).

The transfers read each particle array once per thread, into a local used from then on: Warp's
adjoint of a read a[p] is an atomic add into a's gradient at p, one per read in the code (P2G
once read C[p] three times and once more in each of the 27 unrolled nodes), while a local's
adjoint sums its uses in registers and adds once. The forward is the same arithmetic on the
same values.
"""

from __future__ import annotations

import warp as wp

from mosiv_warp_mpm.expression_kernels import node_expression
from mosiv_warp_mpm.field_sums import field_sums
from mosiv_warp_mpm.laws import J_MIN, safe_norm, vec5
from mosiv_warp_mpm.node_window import node_index, window_count, window_ijk

PAD = wp.constant(3)  # boundary node layers outside the scene domain (slip walls)
MASS_EPS = wp.constant(1.0e-12)  # kg: nodes lighter than this carry no velocity
#: divergence reasons, stored in the low bits of the per-object flag (substep * 4 + reason)
REASON_NONFINITE = wp.constant(1)
REASON_CFL = wp.constant(2)
NO_FLAG = 2**30


@wp.kernel
def clear_box(
    boxes: wp.array(dtype=wp.vec3i),
    row: int,
    stride: int,
    nodes: wp.vec3i,
    m: wp.array(dtype=float),
    mv: wp.array(dtype=wp.vec3),
    gm: wp.array(dtype=wp.vec3),
    pm: wp.array(dtype=wp.vec3),
    vs: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    with_velocities: int,
):
    # zero the grid arrays (or their gradients) on the window's nodes: one launch, not six
    t = wp.tid()
    count = window_count(boxes, row)
    if t % stride < count:
        for r in range(t % stride, count, stride):
            c = window_ijk(boxes, row, r)
            n = node_index(t // stride, c[0], c[1], c[2], nodes)
            m[n] = 0.0
            mv[n] = wp.vec3()
            gm[n] = wp.vec3()
            pm[n] = wp.vec3()
            if with_velocities != 0:
                vs[n] = wp.vec3()
                v[n] = wp.vec3()


@wp.func
def bspline_weights(fx: wp.vec3):
    # quadratic B-spline weights, row r = node base + r, column = axis
    w0 = 0.5 * wp.cw_mul(wp.vec3(1.5) - fx, wp.vec3(1.5) - fx)
    w1 = wp.vec3(0.75) - wp.cw_mul(fx - wp.vec3(1.0), fx - wp.vec3(1.0))
    w2 = 0.5 * wp.cw_mul(fx - wp.vec3(0.5), fx - wp.vec3(0.5))
    return wp.matrix_from_rows(w0, w1, w2)


@wp.func
def bspline_slopes(fx: wp.vec3):
    # d(weight)/d(fx) of the quadratic B-spline, same layout as bspline_weights
    return wp.matrix_from_rows(fx - wp.vec3(1.5), -2.0 * (fx - wp.vec3(1.0)), fx - wp.vec3(0.5))


@wp.func
def cell_base(xl: wp.vec3):
    # lowest of the 3 nodes per axis touched by a particle at grid coordinates xl (>= 1)
    return wp.vec3i(int(xl[0] - 0.5), int(xl[1] - 0.5), int(xl[2] - 0.5))


@wp.kernel
def stencil_base_bounds(
    x: wp.array(dtype=wp.vec3), origin: wp.vec3, dx: float, bounds: wp.array(dtype=int)
):
    """The lowest and highest stencil base (cell_base) per axis over all particles, into
    bounds[0:3] and bounds[3:6] (preset to +/- a large value): the node box a substep's grid
    kernels must visit (state.NodeBox.from_bases), found on the device: a CUDA run then keeps
    it there (node_window.box_from_bounds) or reads back 24 bytes per substep instead of every
    position (grid_window "particles"). A non-finite position (a
    diverged member, reset by the next G2P) counts for nothing."""
    p = wp.tid()
    xp = x[p]
    if not (wp.isfinite(xp[0]) and wp.isfinite(xp[1]) and wp.isfinite(xp[2])):
        return
    base = cell_base((xp - origin) / dx)
    # an atomic only where this base would move a bound: every thread's atomics land on the
    # same six addresses, which a million particles serialise; a plain read skips nearly all
    # of them once the bounds near the extremes (a stale read costs only an extra atomic)
    for a in range(3):
        if base[a] < bounds[a]:
            wp.atomic_min(bounds, a, base[a])
        if base[a] > bounds[3 + a]:
            wp.atomic_max(bounds, 3 + a, base[a])


@wp.func
def kelvin_voigt_tau(eta: float, F: wp.mat33, L: wp.mat33):
    # material_damping: tau_visc = eta J (L + L^T), L = C (the Newtonian law's viscous form)
    J = wp.max(wp.determinant(F), J_MIN)
    return (eta * J) * (L + wp.transpose(L))


@wp.func
def parameter_rows(p: int, o: int, objects_per_member: int, per_particle: int):
    # rows of particle p's values in the parameter arrays P2G and G2P read: the per-object
    # tables (ObjectTables: object o, member o // K) or, with per_particle, the particles' own
    # copies (ParticleParams: row p in both). The taped kernels read the copies: Warp's adjoint
    # of a read a[i] is atomic_add(adj_a[i]), so reading the tables would add every particle's
    # share into the same few addresses each substep (contended, and summed in float32 in
    # schedule order); the copies' adjoints land on one address per particle, summed per object
    # in float64 after each frame (autograd.BackwardWorkspace)
    q = o
    b = o // objects_per_member
    if per_particle != 0:
        q = p
        b = p
    return q, b


@wp.kernel
def gather_particle_params(
    obj: wp.array(dtype=int),
    params: wp.array(dtype=vec5),
    rho: wp.array(dtype=float),
    damping: wp.array(dtype=float),
    objects_per_member: int,
    particle_params: wp.array(dtype=vec5),
    particle_rho: wp.array(dtype=float),
    particle_damping: wp.array(dtype=float),
):
    # particle p's copy of what P2G and G2P read per object (state.ParticleParams): law
    # parameters and density of its object o, material_damping viscosity of its member o // K
    p = wp.tid()
    o = obj[p]
    particle_params[p] = params[o]
    particle_rho[p] = rho[o]
    particle_damping[p] = damping[o // objects_per_member]


@wp.kernel
def gather_node_coefficients(
    accel: wp.array(dtype=wp.vec3),
    drag: wp.array(dtype=float),
    friction: wp.array(dtype=float),
    member_nodes: int,
    field_nodes: int,
    node_accel: wp.array(dtype=wp.vec3),
    node_drag: wp.array(dtype=float),
    node_friction: wp.array(dtype=float),
):
    # flat node n's copy of what grid_free_velocity and grid_boundaries read per member or
    # object (state.NodeCoefficients): body acceleration and drag of member n // member_nodes
    # (member_nodes = GridLayout.size) and the friction row n // field_nodes (nodes per field),
    # the row grid_boundaries reads for the node's field (first + f)
    n = wp.tid()
    b = n // member_nodes
    node_accel[n] = accel[b]
    node_drag[2 * n] = drag[2 * b]
    node_drag[2 * n + 1] = drag[2 * b + 1]
    node_friction[n] = friction[n // field_nodes]


@wp.func
def ground_row(b: int, i: int, j: int, k: int, nodes: wp.vec3i, layers: int):
    # row of member b's ground-layer node (i, j, k), k < layers, in the nodes' ground copies
    return ((b * nodes[0] + i) * nodes[1] + j) * layers + k


@wp.kernel
def gather_ground_coefficients(
    ground_friction: wp.array(dtype=float),
    ground_restitution: wp.array(dtype=float),
    member_rows: int,
    node_friction: wp.array(dtype=float),
    node_restitution: wp.array(dtype=float),
):
    # ground-layer row g's copy (ground_row) of member g // member_rows's ground friction and
    # restitution (member_rows = NX NY ground layers, state.NodeCoefficients)
    g = wp.tid()
    b = g // member_rows
    node_friction[g] = ground_friction[b]
    node_restitution[g] = ground_restitution[b]


@wp.struct
class ExpressionInputs:
    """What the expression term reads at a node (expression_kernels.py): the switches (``on``,
    ObjectTables.expr_switch or, taped, its copy without a gradient NodeCoefficients.expr_switch;
    ``switch`` is a C++ keyword) and coefficients (ObjectTables), the other objects' summed
    centres (Grid), the frame's start time (s, MPMRun.clock), the substep within the frame, the
    grid origin (m) and spacing (m), the scene's up and its ground height (m)."""

    on: wp.array(dtype=float)
    coef: wp.array(dtype=wp.vec3)
    rel_p: wp.array(dtype=wp.vec3)
    rel_v: wp.array(dtype=wp.vec3)
    rel_n: wp.array(dtype=float)
    clock: wp.array(dtype=float)
    substep: int
    origin: wp.vec3
    dx: float
    up: wp.vec3
    ground: float


@wp.func
def free_velocity_at(
    field: int,
    c: wp.vec3i,
    grid_m: wp.array(dtype=float),
    grid_mv: wp.array(dtype=wp.vec3),
    accel: wp.array(dtype=wp.vec3),
    drag: wp.array(dtype=float),
    per_node: int,
    expr: ExpressionInputs,
    dt: float,
    nodes: wp.vec3i,
    fields_per_member: int,
    grid_vs: wp.array(dtype=wp.vec3),
):
    # grid_free_velocity at node c of ``field``
    n = node_index(field, c[0], c[1], c[2], nodes)
    b = field // fields_per_member  # batch member
    r = b
    if per_node != 0:
        r = n
    m = grid_m[n]
    vf = wp.vec3()
    if m > MASS_EPS:
        vs = grid_mv[n] / m
        a = accel[r] - drag[2 * r] * vs - drag[2 * r + 1] * safe_norm(vs) * vs
        if expr.on[2 * b] > 0.5:
            x = expr.origin + expr.dx * wp.vec3(float(c[0]), float(c[1]), float(c[2]))
            time = expr.clock[0] + float(expr.substep) * dt
            a = a + node_expression(
                expr.coef, b, field, x, vs, time, expr.up, expr.ground, expr.rel_p,
                expr.rel_v, expr.rel_n,
            )  # fmt: skip
        vf = vs + dt * a
    grid_vs[n] = vf


@wp.kernel
def grid_free_velocity(
    grid_m: wp.array(dtype=float),
    grid_mv: wp.array(dtype=wp.vec3),
    accel: wp.array(dtype=wp.vec3),
    drag: wp.array(dtype=float),
    per_node: int,
    expr: ExpressionInputs,
    dt: float,
    boxes: wp.array(dtype=wp.vec3i),
    row: int,
    stride: int,
    nodes: wp.vec3i,
    fields_per_member: int,
    grid_vs: wp.array(dtype=wp.vec3),
):
    # v = mv/m + dt (g + wind - c_lin v - c_quad |v| v + expression), on every field's nodes of
    # the window (node_window); the expression (a member's switch) at the node's position and
    # the substep's time.
    # per_node: accel and drag from the node's copies (row n, state.NodeCoefficients), not the
    # member's table row b: Warp's adjoint of a read a[i] is atomic_add(adj_a[i]), so the tables
    # would take every node's share on a few addresses (contended float32 atomics); the copies
    # take one address per node, summed per member in float64 after each frame
    # the guard keeps a thread without nodes out of the loop: Warp's adjoint of an empty
    # dynamic range ran its body once at the start before warp-lang 1.19 (range.h)
    t = wp.tid()
    count = window_count(boxes, row)
    if t % stride < count:
        for r in range(t % stride, count, stride):
            free_velocity_at(
                t // stride, window_ijk(boxes, row, r), grid_m, grid_mv, accel, drag,
                per_node, expr, dt, nodes, fields_per_member, grid_vs,
            )  # fmt: skip


@wp.func
def coulomb_contact(v: wp.vec3, v_cm: wp.vec3, normal: wp.vec3, mu: float):
    # approaching (v - v_cm).n > 0: drop the normal part, Coulomb-limit the tangential part
    rel = v - v_cm
    vn = wp.dot(rel, normal)
    out = v
    if vn > 0.0:
        rel_t = rel - vn * normal
        scale = wp.max(0.0, 1.0 - mu * vn / safe_norm(rel_t))
        out = v_cm + scale * rel_t
    return out


@wp.func
def ground_contact(v: wp.vec3, v_in: float, mu: float, e: float):
    # moving into the ground (v_z < 0): v_z <- e max(-v_in, 0), tangential speed cut by mu times
    # the normal change |v_z| + e max(-v_in, 0). v_in is the arriving normal velocity (momentum
    # before this substep's stress and body-force impulse): only arriving material bounces, so a
    # body pressed onto the table is stopped, not re-launched every substep (which pumped a stiff
    # ball from 1.5 J to 47 J at e = 1). e = 0 is the plain inelastic contact, bit for bit.
    out = v
    if v[2] < 0.0:
        vt = wp.vec3(v[0], v[1], 0.0)
        bounce = e * wp.max(-v_in, 0.0)
        out = wp.max(0.0, 1.0 - mu * ((-v[2]) + bounce) / safe_norm(vt)) * vt
        out = out + wp.vec3(0.0, 0.0, bounce)
    return out


@wp.func
def slip_walls(v: wp.vec3, i: int, j: int, k: int, nodes: wp.vec3i):
    # in the PAD outer node layers the outward normal component is removed
    out = v
    if (i < PAD and out[0] < 0.0) or (i > nodes[0] - 1 - PAD and out[0] > 0.0):
        out = wp.vec3(0.0, out[1], out[2])
    if (j < PAD and out[1] < 0.0) or (j > nodes[1] - 1 - PAD and out[1] > 0.0):
        out = wp.vec3(out[0], 0.0, out[2])
    if (k < PAD and out[2] < 0.0) or (k > nodes[2] - 1 - PAD and out[2] > 0.0):
        out = wp.vec3(out[0], out[1], 0.0)
    return out


@wp.func
def boundaries_at(
    b: int,
    c: wp.vec3i,
    grid_m: wp.array(dtype=float),
    grid_vs: wp.array(dtype=wp.vec3),
    grid_gm: wp.array(dtype=wp.vec3),
    grid_pm: wp.array(dtype=wp.vec3),
    n_fields: int,
    nodes: wp.vec3i,
    ground_on: int,
    ground_k: float,
    ground_layers: int,
    friction: wp.array(dtype=float),
    ground_friction: wp.array(dtype=float),
    ground_restitution: wp.array(dtype=float),
    per_node: int,
    grid_v: wp.array(dtype=wp.vec3),
):
    # grid_boundaries at spatial node c of batch member b, every field
    i = c[0]
    j = c[1]
    k = c[2]
    per_field = nodes[0] * nodes[1] * nodes[2]
    first = b * n_fields  # the member's first field, and its first object (multi-field)
    s = node_index(first, i, j, k, nodes)
    mu_first = first  # field f's friction at mu_first + f mu_stride (field_sums)
    mu_stride = 1
    r = b
    if per_node != 0:
        mu_first = s
        mu_stride = per_field
        r = ground_row(b, i, j, k, nodes, ground_layers)
    # sums over fields go through field_sums: Warp cannot differentiate a local variable
    # accumulated in a loop over the run-time field count
    m_tot, p_tot, g_tot, mu_tot, count = field_sums(
        grid_m, grid_vs, grid_gm, friction, mu_first, mu_stride, s, per_field, n_fields, -1,
        MASS_EPS,
    )  # fmt: skip
    for f in range(n_fields):
        n = f * per_field + s
        m = grid_m[n]
        v = grid_vs[n]
        if m > MASS_EPS:
            if count >= 2:
                # the other fields' sums, accumulated directly: subtracting f's share from
                # a total cancels catastrophically when f dominates the node's mass (and
                # rounds differently under CUDA's fused multiply-adds): wild coefficients
                m_other, p_other, g_other, mu_other, n_other = field_sums(
                    grid_m, grid_vs, grid_gm, friction, mu_first, mu_stride, s, per_field,
                    n_fields, f, MASS_EPS,
                )  # fmt: skip
                # outward normal of f against the others: normalize(gm_f - others' gm)
                d = grid_gm[n] - g_other
                normal = d / safe_norm(d)
                mu = 0.5 * (friction[mu_first + f * mu_stride] + mu_other / m_other)
                v = coulomb_contact(v, p_tot / m_tot, normal, mu)
            if ground_on != 0 and float(k) <= ground_k:
                v_in = grid_pm[n][2] / m
                v = ground_contact(v, v_in, ground_friction[r], ground_restitution[r])
            v = slip_walls(v, i, j, k, nodes)
        grid_v[n] = v


@wp.kernel
def grid_boundaries(
    grid_m: wp.array(dtype=float),
    grid_vs: wp.array(dtype=wp.vec3),
    grid_gm: wp.array(dtype=wp.vec3),
    grid_pm: wp.array(dtype=wp.vec3),
    n_fields: int,
    nodes: wp.vec3i,
    ground_on: int,
    ground_k: float,
    ground_layers: int,
    friction: wp.array(dtype=float),
    ground_friction: wp.array(dtype=float),
    ground_restitution: wp.array(dtype=float),
    per_node: int,
    boxes: wp.array(dtype=wp.vec3i),
    row: int,
    stride: int,
    grid_v: wp.array(dtype=wp.vec3),
):
    # multi-field Coulomb contact, ground plane and slip walls at the spatial nodes of the
    # window (node_window), threads per batch member, n_fields = fields per member.
    # per_node: friction from the nodes' copies (row n of field f's node), the ground's from the
    # ground-layer nodes' (ground_row, ground_layers = the layers k <= ground_k), not the tables'
    # rows first + f and b: as in grid_free_velocity, the tables' adjoints would be float32
    # atomics of every node with mass onto a few addresses
    t = wp.tid()
    count = window_count(boxes, row)
    if t % stride < count:  # as in grid_free_velocity
        for r in range(t % stride, count, stride):
            boundaries_at(
                t // stride, window_ijk(boxes, row, r), grid_m, grid_vs, grid_gm, grid_pm,
                n_fields, nodes, ground_on, ground_k, ground_layers, friction,
                ground_friction, ground_restitution, per_node, grid_v,
            )  # fmt: skip
