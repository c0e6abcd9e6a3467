"""3x3 SVD with proper rotations and a hand-written, well-conditioned adjoint (Warp).

``proper_svd(F)`` returns F = U diag(s) V^T with det U = det V = +1 (a reflection moves into the
sign of s_3; docs/PHYSICS.md, Singular value decomposition). Warp's built-in ``wp.svd3``
adjoint divides both of its terms by s_j^2 - s_i^2 clamped at a small epsilon, so wherever two singular values coincide -- F = I at
rest, isotropic compression, snow's clamped s -- gradients through U and V are O(1) wrong
(tests/test_svd.py measures 0.7 to 1.4 relative error there).

The adjoint here is the standard SVD derivative written so that only the part that really is
singular sees a small denominator. With dU = U Omega_U, dV = V Omega_V (both skew) and
P = U^T dF V, the off-diagonal entries satisfy P_ij + P_ji = (Omega_U + Omega_V)_ij (s_j - s_i)
and P_ij - P_ji = (Omega_U - Omega_V)_ij (s_j + s_i). Pairing these with A = skew(U^T dL/dU) and
B = skew(V^T dL/dV) gives

    dL/dF = U (diag(dL/ds) + X) V^T,
    X_ij = (A + B)_ij / (2 (s_j - s_i)) + (A - B)_ij / (2 (s_j + s_i))     (i != j).

The rotation part (A - B) keeps an exact, O(1) denominator at s_i = s_j, so U V^T (snow's R,
sand's projection) differentiates exactly there. The (A + B) part vanishes at s_i = s_j for every
function of F (the SVD's gauge freedom rotates U and V together there); below a gap of GAP its
1/(s_j - s_i) becomes a ramp to 0, so float32 round-off in A + B is not amplified. What is lost
below GAP is the finite limit of (A + B)/(s_j - s_i) (e.g. g'(s) for U diag(g(s)) V^T): it
depends on the function, not on the SVD, and only matters where F has singular values equal to
within 1e-5 -- in MPM, an F that is exactly I or an exact isotropic scaling of a rotation.
"""

from __future__ import annotations

import warp as wp

#: singular-value gap (s are O(1) for deformation gradients) below which 1/gap is replaced by a
#: ramp to 0: ~100 float32 ulps, so float32 round-off in A + B (~1e-7 of the adjoint) is amplified
#: at most 100x, and for |s_j - s_i| >= GAP the adjoint is the exact one
GAP = wp.constant(1.0e-5)


@wp.func
def _proper_svd_values(F: wp.mat33):
    # wp.svd3, then det U = det V = +1 by flipping the last column and the sign of s_3
    U = wp.mat33()
    s = wp.vec3()
    V = wp.mat33()
    wp.svd3(F, U, s, V)
    flip = wp.diag(wp.vec3(1.0, 1.0, -1.0))
    if wp.determinant(U) < 0.0:
        U = U * flip
        s = wp.vec3(s[0], s[1], -s[2])
    if wp.determinant(V) < 0.0:
        V = V * flip
        s = wp.vec3(s[0], s[1], -s[2])
    return U, s, V


@wp.func
def proper_svd(F: wp.mat33):
    # F = U diag(s) V^T with proper rotations U, V; adjoint: adj_proper_svd
    U, s, V = _proper_svd_values(F)
    return U, s, V


@wp.func
def gap_inverse(d: float):
    # 1/d for |d| >= GAP, else the linear ramp d / GAP^2 (continuous at |d| = GAP, 0 at d = 0)
    out = d / (GAP * GAP)
    if wp.abs(d) >= GAP:
        out = 1.0 / d
    return out


@wp.func
def svd_adjoint(U: wp.mat33, s: wp.vec3, V: wp.mat33, gU: wp.mat33, gs: wp.vec3, gV: wp.mat33):
    # dL/dF = U (diag(dL/ds) + X) V^T with X from the module docstring
    Ju = wp.transpose(U) * gU
    Kv = wp.transpose(V) * gV
    A = Ju - wp.transpose(Ju)
    B = Kv - wp.transpose(Kv)
    X = wp.diag(gs)
    for i in range(3):
        for j in range(3):
            if i != j:
                X[i, j] = 0.5 * (A[i, j] + B[i, j]) * gap_inverse(s[j] - s[i]) + 0.5 * (
                    A[i, j] - B[i, j]
                ) * gap_inverse(s[j] + s[i])
    return U * X * wp.transpose(V)


@wp.func_grad(proper_svd)
def adj_proper_svd(F: wp.mat33, adj_U: wp.mat33, adj_s: wp.vec3, adj_V: wp.mat33):
    # replaces Warp's svd3 adjoint (ill-conditioned at repeated singular values)
    U, s, V = _proper_svd_values(F)
    wp.adjoint[F] += svd_adjoint(U, s, V, adj_U, adj_s, adj_V)
