"""Batched 3x3 linear algebra shared by the constitutive laws (pure torch, differentiable).

Everything works on [N, 3, 3] matrices and [N, 3] singular-value vectors, in any float dtype.
Functions of the SVD go through ``svd_map``, whose backward stays exact when singular values
coincide (F = I, pure dilation, uniaxial states), where torch's SVD backward divides by zero.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence

import torch
from torch.autograd.function import once_differentiable

Tensor = torch.Tensor

#: singular values are clamped to at least this before taking log (docs/PHYSICS.md)
SINGULAR_MIN = 1e-4
#: J = det F is clamped to at least this where a law takes log(J) or J^-6: keeps inverted or
#: crushed elements finite; the fluid's 6 J^-7 bulk_modulus stays below float32's 3.4e38
J_MIN = 1e-4
#: added under square roots so that the norm of a zero vector has a finite gradient
_NORM_EPS = 1e-30


@torch.no_grad()
def proper_svd(F: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """SVD of [N, 3, 3] F with proper rotations: U [N,3,3], s [N,3], V [N,3,3]; no gradient.

    s is sorted by magnitude; s_3 is negative when det F < 0 (an inverted element). Differentiable
    quantities go through ``svd_map``.
    """
    U, s, Vh = torch.linalg.svd(F)
    V = Vh.transpose(-1, -2)
    # A reflection in U (or V) moves into the sign of the last column and of s_3; the product
    # U diag(s) V^T is unchanged.
    sign_u = torch.where(torch.linalg.det(U) < 0, -1.0, 1.0).to(F.dtype)
    sign_v = torch.where(torch.linalg.det(V) < 0, -1.0, 1.0).to(F.dtype)
    ones = torch.ones_like(s[:, :2])
    last_u = torch.cat([ones, sign_u[:, None]], dim=1)
    last_v = torch.cat([ones, sign_v[:, None]], dim=1)
    return U * last_u[:, None, :], s * last_u * last_v, V * last_v[:, None, :]


def compose(U: Tensor, s: Tensor, V: Tensor) -> Tensor:
    """U diag(s) V^T for [N, 3, 3] U, V and [N, 3] s."""
    return (U * s[:, None, :]) @ V.transpose(-1, -2)


def _offdiag_mask(x: Tensor) -> Tensor:
    return 1.0 - torch.eye(3, dtype=x.dtype, device=x.device)


class _SVDMap(torch.autograd.Function):
    """G = U diag(h(s, *params)) V^T and R = U V^T, with an exact backward at repeated s.

    h must be isotropic (permuting s permutes h). In the frame P = U^T dF V the derivative is
    dG_ij = sym(P)_ij (h_i - h_j)/(s_i - s_j) + skew(P)_ij (h_i + h_j)/(s_i + s_j) for i != j and
    dG_ii = dh_i; the first divided difference tends to dh_i/ds_i - dh_i/ds_j when s_i = s_j,
    which is what torch's SVD backward cannot do (it divides by s_j^2 - s_i^2).
    """

    @staticmethod
    def forward(ctx, F: Tensor, h_fn: Callable[..., Tensor], *params: Tensor):
        U, s, V = proper_svd(F)
        h = h_fn(s, *params)
        ctx.h_fn = h_fn
        ctx.save_for_backward(U, s, V, *params)
        ctx.mark_non_differentiable(s)
        return compose(U, h, V), U @ V.transpose(-1, -2), s

    @staticmethod
    @once_differentiable
    def backward(ctx, gG: Tensor, gR: Tensor, _gs: Tensor):
        U, s, V, *params = ctx.saved_tensors
        wants = [ctx.needs_input_grad[2 + k] for k in range(len(params))]
        Ut, off = U.transpose(-1, -2), _offdiag_mask(s)
        PG = Ut @ gG @ V
        with torch.enable_grad():
            s_in = s.detach().requires_grad_(True)
            p_in = [p.detach().requires_grad_(w) for p, w in zip(params, wants, strict=True)]
            h = ctx.h_fn(s_in, *p_in)
            if not h.requires_grad:  # h constant in s and parameters: only R carries gradient
                h = h + 0.0 * s_in
            # Jacobian dh_i/ds_j per particle (h acts on each particle's s independently).
            rows = [
                torch.autograd.grad(h[:, i].sum(), s_in, retain_graph=True, allow_unused=True)[0]
                for i in range(3)
            ]
            # Diagonal part dG_ii = dh_i: back through h to s and to the parameters.
            wrt = [s_in] + [p for p, w in zip(p_in, wants, strict=True) if w]
            got = torch.autograd.grad(
                h, wrt, grad_outputs=torch.diagonal(PG, dim1=-2, dim2=-1), allow_unused=True
            )
        jac = torch.stack([torch.zeros_like(s) if r is None else r for r in rows], dim=1)
        h = h.detach()
        g_s = torch.zeros_like(s) if got[0] is None else got[0]
        # Off-diagonal part: divided differences of h (see the class docstring).
        si, sj = s[:, :, None], s[:, None, :]
        hi, hj = h[:, :, None], h[:, None, :]
        diff, total = si - sj, si + sj
        tol = torch.finfo(s.dtype).eps ** 0.5 * torch.clamp(torch.maximum(si.abs(), sj.abs()), 1.0)
        far = diff.abs() > tol
        jd = torch.diagonal(jac, dim1=-2, dim2=-1)
        limit = 0.5 * (jd[:, :, None] + jd[:, None, :]) - 0.5 * (jac + jac.transpose(-1, -2))
        d_minus = torch.where(far, (hi - hj) / torch.where(far, diff, 1.0), limit)
        tiny = torch.finfo(s.dtype).tiny ** 0.5
        safe_total = torch.where(total.abs() > tiny, total, torch.full_like(total, tiny))
        d_plus = (hi + hj) / safe_total
        PGt = PG.transpose(-1, -2)
        Q = 0.5 * (PG + PGt) * d_minus + 0.5 * (PG - PGt) * d_plus
        if gR is not None:
            PR = Ut @ gR @ V
            Q = Q + (PR - PR.transpose(-1, -2)) / safe_total
        Q = Q * off + torch.diag_embed(g_s)
        g_F = U @ Q @ V.transpose(-1, -2)
        it = iter(got[1:])
        g_params = [next(it) if w else None for w in wants]
        return (g_F, None, *g_params)


def svd_map(
    F: Tensor, h_fn: Callable[..., Tensor], *params: Tensor
) -> tuple[Tensor, Tensor, Tensor]:
    """Differentiable (G, R, s) with G = U diag(h_fn(s, *params)) V^T and R = U V^T.

    ``h_fn`` maps signed singular values [N, 3] (and [N] parameters) to new ones [N, 3] and must
    be isotropic (a permutation of s permutes its output). ``s`` is returned detached, for
    branch decisions only.
    """
    return _SVDMap.apply(F, h_fn, *params)


def _keep(s: Tensor) -> Tensor:
    return s


def polar_rotation(F: Tensor) -> Tensor:
    """Rotation part R = U V^T of the polar decomposition F = R S (det R = +1), differentiable."""
    return svd_map(F, _keep)[1]


def hencky_strain(s: Tensor) -> Tensor:
    """Principal Hencky (logarithmic) strain eps = log(max(s, 1e-4)), [N, 3] (dimensionless)."""
    return torch.log(torch.clamp(s, min=SINGULAR_MIN))


def safe_norm(x: Tensor) -> Tensor:
    """Euclidean norm over the last axis with a finite gradient at x = 0."""
    return torch.sqrt((x * x).sum(dim=-1) + _NORM_EPS)


def deviatoric(eps: Tensor) -> Tensor:
    """dev(eps) = eps - mean(eps) of principal strains [N, 3]."""
    return eps - eps.mean(dim=-1, keepdim=True)


def identity_like(F: Tensor) -> Tensor:
    """[N, 3, 3] identity matrices with F's dtype and device."""
    return torch.eye(3, dtype=F.dtype, device=F.device).expand(F.shape[0], 3, 3)


def safe_det(F: Tensor) -> Tensor:
    """J = det F, clamped to at least J_MIN (for log(J) and negative powers of J)."""
    return torch.clamp(torch.linalg.det(F), min=J_MIN)


def gather_params(
    values: Mapping[str, Tensor | float],
    names: Sequence[str],
    *,
    like: Tensor | None = None,
    law: str,
) -> list[Tensor]:
    """The named parameters as tensors; with ``like`` ([N, 3, 3] F) as [N] tensors of its
    dtype/device (0-d values broadcast), without it as given (0-d or [N]).

    Raises KeyError naming the missing parameter and what the law needs.
    """
    out = []
    for name in names:
        if name not in values:
            raise KeyError(
                f"law {law!r} needs parameter {name!r}; got {sorted(values)}, needs {list(names)}"
            )
        if like is None:
            out.append(torch.as_tensor(values[name]))
            continue
        n = like.shape[0]
        v = torch.as_tensor(values[name], dtype=like.dtype, device=like.device)
        if v.dim() > 1 or (v.dim() == 1 and v.shape[0] not in (1, n)):
            raise ValueError(
                f"law {law!r}: parameter {name!r} has shape {tuple(v.shape)}; "
                f"expected a scalar or a [{n}] tensor (one value per particle)"
            )
        out.append(v.expand(n))
    return out


def plastic_j_or_ones(plastic_J: Tensor | None, *, like: Tensor) -> Tensor:
    """The given per-particle plastic volume ratio, or ones [N] when the caller has none."""
    if plastic_J is None:
        return torch.ones(like.shape[0], dtype=like.dtype, device=like.device)
    return plastic_J
