"""Each Warp law (stress and return map) against the core's torch reference on random F.

F covers mild deformations, near-singular (one singular value ~1e-3) and strongly compressed
(J ~ 0.3) cases, and random rotations; parameters are drawn inside each law's bounds.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import warp as wp
from mosiv_warp_mpm.laws import LAW_IDS, LAW_PARAM_NAMES, N_SLOTS, evaluate_laws, vec5

from mosiv_framework.laws import FAMILIES, get_law

N_PER_KIND = 64
DT = 1e-4


def random_rotation(g: torch.Generator, n: int) -> torch.Tensor:
    q, r = torch.linalg.qr(torch.randn(n, 3, 3, generator=g, dtype=torch.float64))
    q = q * torch.sign(torch.diagonal(r, dim1=-2, dim2=-1))[:, None, :]
    det = torch.linalg.det(q)
    q[:, :, 2] *= det[:, None]
    return q


def random_F(seed: int) -> torch.Tensor:
    """[3 * N_PER_KIND, 3, 3] float64: mild, near-singular and strongly compressed F."""
    g = torch.Generator().manual_seed(seed)
    n = N_PER_KIND
    mild = torch.exp(0.2 * torch.randn(n, 3, generator=g, dtype=torch.float64))
    near_singular = torch.exp(0.1 * torch.randn(n, 3, generator=g, dtype=torch.float64))
    near_singular[:, 2] = 1e-3 * (1.0 + torch.rand(n, generator=g, dtype=torch.float64))
    compressed = 0.6 + 0.1 * torch.rand(n, 3, generator=g, dtype=torch.float64)  # J ~ 0.2-0.34
    s = torch.cat([mild, near_singular, compressed])
    U, V = random_rotation(g, 3 * n), random_rotation(g, 3 * n)
    return U @ torch.diag_embed(s) @ V.transpose(-1, -2)


def random_values(name: str, n: int, seed: int) -> dict[str, torch.Tensor]:
    """Per-particle parameter values drawn inside each ParamSpec's bounds (log-uniform if log)."""
    law = get_law(name)
    g = torch.Generator().manual_seed(seed)
    out = {}
    for spec in law.params:
        u = torch.rand(n, generator=g, dtype=torch.float64)
        lo, hi = spec.lower, spec.upper
        if spec.name == "nu":
            hi = min(hi, 0.45)
        if spec.log_scale:
            out[spec.name] = torch.exp(math.log(lo) + u * (math.log(hi) - math.log(lo)))
        else:
            out[spec.name] = lo + u * (hi - lo)
    return out


def run_warp(name: str, F: torch.Tensor, L: torch.Tensor, pj: torch.Tensor, values: dict):
    n = F.shape[0]
    slots = np.zeros((n, N_SLOTS), dtype=np.float32)
    for i, pname in enumerate(LAW_PARAM_NAMES[name]):
        slots[:, i] = values[pname].numpy()
    dev = "cpu"
    tau = wp.zeros(n, dtype=wp.mat33, device=dev)
    F_new = wp.zeros(n, dtype=wp.mat33, device=dev)
    pj_new = wp.zeros(n, dtype=float, device=dev)
    wp.launch(
        evaluate_laws,
        dim=n,
        inputs=[
            LAW_IDS[name],
            wp.array(slots, dtype=vec5, device=dev),
            wp.array(F.numpy().astype(np.float32), dtype=wp.mat33, device=dev),
            wp.array(L.numpy().astype(np.float32), dtype=wp.mat33, device=dev),
            wp.array(pj.numpy().astype(np.float32), dtype=float, device=dev),
            DT,
        ],
        outputs=[tau, F_new, pj_new],
        device=dev,
    )
    return (
        torch.from_numpy(tau.numpy()).double(),
        torch.from_numpy(F_new.numpy()).double(),
        torch.from_numpy(pj_new.numpy()).double(),
    )


def assert_close(got: torch.Tensor, ref: torch.Tensor, *, what: str, rtol: float) -> None:
    """Per-sample relative error against the sample's own magnitude (float32 vs float64)."""
    scale = ref.flatten(1).abs().amax(dim=1).clamp(min=1e-12)
    err = (got - ref).flatten(1).abs().amax(dim=1) / scale
    worst = int(err.argmax())
    assert err.max() < rtol, f"{what}: max relative error {err.max():.3g} at sample {worst}"


@pytest.mark.parametrize("name", FAMILIES)
def test_law_matches_torch_reference(name: str) -> None:
    wp.init()
    law = get_law(name)
    F = random_F(seed=LAW_IDS[name])
    n = F.shape[0]
    g = torch.Generator().manual_seed(100 + LAW_IDS[name])
    L = 5.0 * torch.randn(n, 3, 3, generator=g, dtype=torch.float64)
    pj = 0.8 + 0.4 * torch.rand(n, generator=g, dtype=torch.float64)
    values = random_values(name, n, seed=200 + LAW_IDS[name])

    tau, F_new, pj_new = run_warp(name, F, L, pj, values)
    tau_ref = law.kirchhoff_stress(F, values, plastic_J=pj, velocity_gradient=L)
    F_ref, pj_ref = law.return_map(F, values, plastic_J=pj, dt=DT)

    # Kirchhoff stress of near-singular/compressed F involves log(1e-3) and J^-6: float32 keeps
    # ~1e-6 relative precision per op, a few 1e-4 overall is the float32 budget here.
    assert_close(tau, tau_ref, what=f"{name} stress", rtol=2e-3)
    assert_close(F_new, F_ref, what=f"{name} return-map F", rtol=2e-3)
    assert_close(pj_new[:, None], pj_ref[:, None], what=f"{name} plastic_J", rtol=2e-3)
