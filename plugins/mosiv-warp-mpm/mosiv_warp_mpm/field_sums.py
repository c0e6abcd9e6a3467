"""Sums over the velocity fields at one grid node, with a hand-written adjoint (Warp).

Multi-field contact (docs/PHYSICS.md, Contact between objects) needs, at each node, sums over the
objects' fields of mass, momentum, mass gradient and mass-weighted friction. The number of fields is
only known at run time, so these are dynamic loops that accumulate into local variables -- and Warp
cannot differentiate a local variable mutated inside a dynamic loop: its reverse pass sees only the
final value (it logs "detected mutated variable ... during a dynamic for-loop"), so the adjoints of
every contact quantity came out wrong. ``field_sums`` keeps that loop in the forward pass and states
its (linear) adjoint explicitly in ``adj_field_sums``.
"""

from __future__ import annotations

import warp as wp


@wp.func
def field_sums(
    grid_m: wp.array(dtype=float),
    grid_vs: wp.array(dtype=wp.vec3),
    grid_gm: wp.array(dtype=wp.vec3),
    friction: wp.array(dtype=float),
    first: int,
    stride: int,
    node: int,
    per_field: int,
    n_fields: int,
    skip: int,
    mass_eps: float,
):
    # over fields f != skip with mass m_f > mass_eps at this node:
    # (sum m_f [kg], sum m_f v_f [kg m/s], sum grad m_f [kg/m], sum m_f mu_f [kg], count);
    # node is field 0's flat index and friction[first + f stride] is field f's coefficient:
    # in the per-object table, first is the member's first object (0 unless batched) and
    # stride 1; in the nodes' copies (state.NodeCoefficients), first is node, stride per_field
    m_sum = float(0.0)  # noqa: UP018 (Warp needs dynamic variables in a dynamic loop)
    p_sum = wp.vec3()
    g_sum = wp.vec3()
    mu_sum = float(0.0)  # noqa: UP018
    count = int(0)  # noqa: UP018
    for f in range(n_fields):
        n = f * per_field + node
        m = grid_m[n]
        if f != skip and m > mass_eps:
            m_sum += m
            p_sum += m * grid_vs[n]
            g_sum += grid_gm[n]
            mu_sum += m * friction[first + f * stride]
            count += 1
    return m_sum, p_sum, g_sum, mu_sum, count


@wp.func_grad(field_sums)
def adj_field_sums(
    grid_m: wp.array(dtype=float),
    grid_vs: wp.array(dtype=wp.vec3),
    grid_gm: wp.array(dtype=wp.vec3),
    friction: wp.array(dtype=float),
    first: int,
    stride: int,
    node: int,
    per_field: int,
    n_fields: int,
    skip: int,
    mass_eps: float,
    adj_m_sum: float,
    adj_p_sum: wp.vec3,
    adj_g_sum: wp.vec3,
    adj_mu_sum: float,
    adj_count: int,
):
    # each sum is linear per field: d/dm_f = 1, v_f, 0, mu_f; d/dv_f = m_f; d/dgrad m_f = 1;
    # d/dmu_f = m_f (array adjoints accumulate atomically: every node shares a table's
    # friction[first + f], so the taped kernel reads the nodes' own copies instead)
    for f in range(n_fields):
        n = f * per_field + node
        m = grid_m[n]
        row = first + f * stride
        if f != skip and m > mass_eps:
            wp.adjoint[grid_m][n] += (
                adj_m_sum + wp.dot(adj_p_sum, grid_vs[n]) + adj_mu_sum * (friction[row])
            )
            wp.adjoint[grid_vs][n] += m * adj_p_sum
            wp.adjoint[grid_gm][n] += adj_g_sum
            wp.adjoint[friction][row] += m * adj_mu_sum
