"""Adjoint of the 3x3 SVD F = U diag(s) V^T, written by hand.

Taichi's ``ti.svd`` cannot be differentiated by its autodiff, so the simulator runs the SVD in a
kernel of its own and calls ``svd_adjoint`` in that kernel's backward. With J = U^T dL/dU and
K = V^T dL/dV, skew parts A = J - J^T, B = K - K^T, the adjoint is

    dL/dF = U (diag(dL/ds) + X) V^T,
    X_ij = (A + B)_ij / (2 (s_j - s_i)) + (A - B)_ij / (2 (s_j + s_i))   (i != j).

Splitting 1/(s_j^2 - s_i^2) this way keeps the rotation part (the (A - B) term) exact when two
singular values coincide (e.g. F = I); only the (A + B) term, which vanishes for isotropic
functions at s_i = s_j, needs its denominator bounded away from zero.
"""

# no `from __future__ import annotations`: Taichi reads the annotations at runtime
import taichi as ti

DENOM_MIN = 1e-6  # smallest |s_j - s_i| and |s_j + s_i| used as a denominator


@ti.func
def _bounded(d):
    """d pushed away from 0 to at least DENOM_MIN in magnitude, keeping its sign (+ at 0)."""
    out = d
    if ti.abs(d) < DENOM_MIN:
        out = DENOM_MIN if d >= 0.0 else -DENOM_MIN
    return out


@ti.func
def svd_adjoint(U, s, V, gU, gs, gV):
    """dL/dF from (dL/dU, dL/ds, dL/dV) for F = U diag(s) V^T (see module docstring)."""
    J = U.transpose() @ gU
    K = V.transpose() @ gV
    A = J - J.transpose()
    B = K - K.transpose()
    X = ti.Matrix.zero(ti.f32, 3, 3)
    for i in ti.static(range(3)):
        X[i, i] = gs[i]
        for j in ti.static(range(3)):
            if ti.static(i != j):
                X[i, j] = 0.5 * (A[i, j] + B[i, j]) / _bounded(s[j] - s[i]) + 0.5 * (
                    A[i, j] - B[i, j]
                ) / _bounded(s[j] + s[i])
    return U @ X @ V.transpose()
