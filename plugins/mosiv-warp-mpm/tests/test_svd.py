"""The hand-written SVD adjoint (mosiv_warp_mpm.svd) against float64 central differences.

Each case differentiates a function of F built from its SVD, <G, f(F)> for a random G, at F with
distinct, nearly repeated (gap 1e-3) and exactly repeated singular values. Warp's built-in svd3
adjoint is off by O(1) at repeated ones for the rotation U V^T and for snow's clamped
recomposition; these must hold to float32 accuracy here.
"""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp
from mosiv_warp_mpm.simulator import init_warp
from mosiv_warp_mpm.svd import proper_svd

init_warp()

HENCKY, ROTATION, CLAMPED = 0, 1, 2
LO, HI = 0.95, 1.05  # clamp band of the snow-like recomposition


@wp.kernel
def contract(
    which: int, F: wp.array(dtype=wp.mat33), G: wp.array(dtype=wp.mat33), out: wp.array(dtype=float)
):
    # out = <G, f(F)>: f = U diag(log s) V^T, U V^T, or U diag(clamp(s, LO, HI)) V^T
    i = wp.tid()
    U, s, V = proper_svd(F[i])
    d = wp.vec3(wp.clamp(s[0], LO, HI), wp.clamp(s[1], LO, HI), wp.clamp(s[2], LO, HI))
    if which == HENCKY:
        d = wp.vec3(wp.log(s[0]), wp.log(s[1]), wp.log(s[2]))
    M = U * wp.diag(d) * wp.transpose(V)
    if which == ROTATION:
        M = U * wp.transpose(V)
    out[i] = wp.ddot(G[i], M)


def reference(which: int, F: np.ndarray, G: np.ndarray) -> float:
    """The same function in float64 (all three are well defined at repeated singular values)."""
    U, s, Vt = np.linalg.svd(F)
    if which == ROTATION:
        return float((G * (U @ Vt)).sum())
    d = np.log(s) if which == HENCKY else np.clip(s, LO, HI)
    return float((G * (U @ np.diag(d) @ Vt)).sum())


def random_rotation(rng) -> np.ndarray:
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    return q * np.sign(np.linalg.det(q))


def warp_gradient(which: int, F: np.ndarray, G: np.ndarray) -> np.ndarray:
    Fa = wp.array(F[None].astype(np.float32), dtype=wp.mat33, requires_grad=True)
    Ga = wp.array(G[None].astype(np.float32), dtype=wp.mat33)
    out = wp.zeros(1, dtype=float, requires_grad=True)
    tape = wp.Tape()
    with tape:
        wp.launch(contract, dim=1, inputs=[which, Fa, Ga], outputs=[out])
    tape.backward(grads={out: wp.ones(1, dtype=float)})
    return Fa.grad.numpy()[0].astype(np.float64)


def difference_gradient(which: int, F: np.ndarray, G: np.ndarray, h: float = 1e-6) -> np.ndarray:
    out = np.zeros((3, 3))
    for a in range(3):
        for b in range(3):
            E = np.zeros((3, 3))
            E[a, b] = h
            out[a, b] = (reference(which, F + E, G) - reference(which, F - E, G)) / (2 * h)
    return out


CASES = [
    # (function, singular values): the log needs its values apart (its limit at s_i = s_j
    # depends on the function, which an SVD adjoint cannot see); rotation and clamped
    # recomposition must hold even at exactly repeated values
    (HENCKY, (1.2, 0.9, 0.7)),
    (HENCKY, (1.1, 1.101, 0.8)),
    (ROTATION, (1.2, 0.9, 0.7)),
    (ROTATION, (1.1, 1.1, 0.8)),
    (ROTATION, (1.0, 1.0, 1.0)),
    (CLAMPED, (1.1, 1.101, 0.8)),
    (CLAMPED, (1.1, 1.1, 0.8)),
    (CLAMPED, (0.9, 0.9, 0.9)),
]


@pytest.mark.parametrize(("which", "singular_values"), CASES)
def test_svd_adjoint_matches_differences(which, singular_values) -> None:
    rng = np.random.default_rng(7)
    worst = 0.0
    for _ in range(10):
        F = random_rotation(rng) @ np.diag(singular_values) @ random_rotation(rng).T
        F = F.astype(np.float32).astype(np.float64)  # differentiate at the float32 input
        G = rng.normal(size=(3, 3))
        ad, fd = warp_gradient(which, F, G), difference_gradient(which, F, G)
        worst = max(worst, float(np.linalg.norm(ad - fd) / np.linalg.norm(fd)))
    assert worst < 2e-3, f"SVD adjoint off by {worst:.3g} (relative) at s = {singular_values}"


def test_proper_svd_reconstructs_with_rotations() -> None:
    # an inverted F (det < 0): U, V are rotations and the reflection sits in the sign of s_3
    rng = np.random.default_rng(3)
    F = random_rotation(rng) @ np.diag([1.3, 0.8, -0.5]) @ random_rotation(rng).T

    @wp.kernel
    def decompose(
        F: wp.array(dtype=wp.mat33), out: wp.array(dtype=wp.mat33), dets: wp.array(dtype=wp.vec3)
    ):
        U, s, V = proper_svd(F[0])
        out[0] = U * wp.diag(s) * wp.transpose(V)
        dets[0] = wp.vec3(wp.determinant(U), wp.determinant(V), s[2])

    Fa = wp.array(F[None].astype(np.float32), dtype=wp.mat33)
    out = wp.zeros(1, dtype=wp.mat33)
    dets = wp.zeros(1, dtype=wp.vec3)
    wp.launch(decompose, dim=1, inputs=[Fa], outputs=[out, dets])
    np.testing.assert_allclose(out.numpy()[0], F, atol=1e-5)
    det_u, det_v, s3 = dets.numpy()[0]
    assert det_u == pytest.approx(1.0, abs=1e-5) and det_v == pytest.approx(1.0, abs=1e-5)
    assert s3 == pytest.approx(-0.5, abs=1e-5)
