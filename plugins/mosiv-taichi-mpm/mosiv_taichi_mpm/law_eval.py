"""Evaluate one law's Taichi functions on a batch of F (for the parity suite and tests)."""

import numpy as np
import taichi as ti
import torch

from mosiv_taichi_mpm.laws import LAW_IDS, LAW_PARAMS, MAX_LAW_PARAMS, kirchhoff_stress, return_map


@ti.kernel
def _evaluate(
    law: ti.template(),
    F: ti.types.ndarray(),
    L: ti.types.ndarray(),
    Jp: ti.types.ndarray(),
    P: ti.types.ndarray(),
    dt: ti.f32,
    tau: ti.types.ndarray(),
    F_new: ti.types.ndarray(),
    Jp_new: ti.types.ndarray(),
):
    """tau = stress(F), (F_new, Jp_new) = return_map(F) for every row of the batch."""
    for p in range(F.shape[0]):
        Fp = ti.Matrix.zero(ti.f32, 3, 3)
        Cp = ti.Matrix.zero(ti.f32, 3, 3)
        for i, j in ti.static(ti.ndrange(3, 3)):
            Fp[i, j] = F[p, i, j]
            Cp[i, j] = L[p, i, j]
        Pp = ti.Vector.zero(ti.f32, MAX_LAW_PARAMS)
        for i in ti.static(range(MAX_LAW_PARAMS)):
            Pp[i] = P[i]
        U, S, V = ti.svd(Fp)
        s = ti.Vector([S[0, 0], S[1, 1], S[2, 2]])
        t = kirchhoff_stress(law, law[0], Fp, U, s, Cp, Jp[p], Pp)
        Fn, _sn, jn = return_map(law, law[0], Fp, U, s, V, Jp[p], Pp, dt)
        for i, j in ti.static(ti.ndrange(3, 3)):
            tau[p, i, j] = t[i, j]
            F_new[p, i, j] = Fn[i, j]
        Jp_new[p] = jn


def evaluate_law(family, F, values, *, plastic_J=None, velocity_gradient=None, dt=1e-3):
    """(tau [N,3,3] Pa, F_new [N,3,3], plastic_J_new [N]) as float32 CPU tensors."""
    n = F.shape[0]
    P = np.zeros(MAX_LAW_PARAMS, np.float32)
    for j, name in enumerate(LAW_PARAMS[family]):
        P[j] = float(values[name])
    F32 = F.detach().to("cpu", torch.float32).contiguous()
    L = velocity_gradient if velocity_gradient is not None else torch.zeros(n, 3, 3)
    Jp = plastic_J if plastic_J is not None else torch.ones(n)
    out = (torch.zeros(n, 3, 3), torch.zeros(n, 3, 3), torch.zeros(n))
    _evaluate(
        (LAW_IDS[family],),
        F32,
        L.detach().to("cpu", torch.float32).contiguous(),
        Jp.detach().to("cpu", torch.float32).contiguous(),
        torch.from_numpy(P),
        float(dt),
        *out,
    )
    return out
