"""The MOSIV constitutive laws as Warp functions (equations: docs/PHYSICS.md,
Constitutive laws).

Every law reads its parameters from one ``vec5`` per object, in the order of
``LAW_PARAM_NAMES`` (unused slots are 0). Each law has a stress function and a return map of
one signature (``STRESS_OF``, ``RETURN_MAP_OF``), from which transfer_kernels.py makes one
kernel per law for the backward's taped replay; ``kirchhoff_stress`` and ``return_map`` dispatch
on the law id to the same functions, for kernels that serve every law (the fused transfers of
forward rollouts, transfer_kernels.p2g_fused and g2p_fused, and the parity tests'
``evaluate_laws``). Every SVD
goes through ``svd.proper_svd``, whose adjoint stays finite at repeated singular values.
"""

from __future__ import annotations

import warp as wp

from mosiv_framework.laws import FAMILIES, get_law
from mosiv_warp_mpm.svd import proper_svd

#: parameters per object slot (the largest law, snow, has five)
N_SLOTS = 5
vec5 = wp.types.vector(length=N_SLOTS, dtype=wp.float32)

#: family name -> law id used inside kernels (the core's family order)
LAW_IDS: dict[str, int] = {family: i for i, family in enumerate(FAMILIES)}

#: family name -> parameter names, in slot order of the object's vec5 (the core's schema order)
LAW_PARAM_NAMES: dict[str, tuple[str, ...]] = {
    family: tuple(spec.name for spec in get_law(family).params) for family in FAMILIES
}

SINGULAR_MIN = wp.constant(1.0e-4)  # singular values are clamped to this before log (spec)
J_MIN = wp.constant(1.0e-6)  # J is clamped to this before log(J) and J^-6 (torch reference: 1e-4)
NORM_EPS = wp.constant(1.0e-30)  # under square roots: finite gradient of |0|
DEG = wp.constant(0.017453292519943295)  # radians per degree


@wp.func
def lame_mu(E: float, nu: float):
    # mu = E / (2 (1 + nu))
    return E / (2.0 * (1.0 + nu))


@wp.func
def lame_lam(E: float, nu: float):
    # lambda = E nu / ((1 + nu)(1 - 2 nu))
    return E * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))


@wp.func
def safe_norm(a: wp.vec3):
    # |a| with a finite gradient at a = 0
    return wp.sqrt(wp.dot(a, a) + NORM_EPS)


@wp.func
def hencky(s: wp.vec3):
    # eps = log(max(s, 1e-4))
    return wp.vec3(
        wp.log(wp.max(s[0], SINGULAR_MIN)),
        wp.log(wp.max(s[1], SINGULAR_MIN)),
        wp.log(wp.max(s[2], SINGULAR_MIN)),
    )


@wp.func
def deviatoric(eps: wp.vec3):
    # dev(eps) = eps - mean(eps)
    m = (eps[0] + eps[1] + eps[2]) / 3.0
    return eps - wp.vec3(m, m, m)


@wp.func
def trace3(a: wp.vec3):
    return a[0] + a[1] + a[2]


@wp.func
def exp3(a: wp.vec3):
    return wp.vec3(wp.exp(a[0]), wp.exp(a[1]), wp.exp(a[2]))


@wp.func
def neo_hookean_tau(F: wp.mat33, mu: float, lam: float):
    # tau = mu (F F^T - I) + lam ln(J) I
    J = wp.max(wp.determinant(F), J_MIN)
    return mu * (F * wp.transpose(F) - wp.identity(n=3, dtype=float)) + lam * wp.log(
        J
    ) * wp.identity(n=3, dtype=float)


@wp.func
def hencky_tau(F: wp.mat33, mu: float, lam: float):
    # tau = U diag(2 mu eps + lam tr(eps)) U^T  (StVK-Hencky)
    U, s, V = proper_svd(F)
    eps = hencky(s)
    tr = trace3(eps)
    t = 2.0 * mu * eps + wp.vec3(lam * tr, lam * tr, lam * tr)
    return U * wp.diag(t) * wp.transpose(U)


@wp.func
def newtonian_tau(F: wp.mat33, L: wp.mat33, viscosity: float, bulk: float):
    # tau = J viscosity (L + L^T) + (bulk / 7)(J - J^-6) I
    J = wp.max(wp.determinant(F), J_MIN)
    pressure = bulk / 7.0 * (J - wp.pow(J, -6.0))
    return J * viscosity * (L + wp.transpose(L)) + pressure * wp.identity(n=3, dtype=float)


@wp.func
def corotated_tau(F: wp.mat33, mu: float, lam: float):
    # tau = 2 mu (F - R) F^T + lam (J - 1) J I  (fixed-corotated)
    U, s, V = proper_svd(F)
    R = U * wp.transpose(V)  # proper rotation even for an inverted F (det F < 0)
    J = wp.determinant(F)
    return 2.0 * mu * (F - R) * wp.transpose(F) + lam * (J - 1.0) * J * wp.identity(
        n=3, dtype=float
    )


@wp.func
def snow_tau(F: wp.mat33, p: vec5, plastic_J: float):
    # fixed-corotated, mu/lam hardened by exp(xi (1 - J_p))
    h = wp.exp(p[4] * (1.0 - plastic_J))
    return corotated_tau(F, lame_mu(p[0], p[1]) * h, lame_lam(p[0], p[1]) * h)


@wp.func
def stress_elastic(p: vec5, F: wp.mat33, L: wp.mat33, plastic_J: float):
    return neo_hookean_tau(F, lame_mu(p[0], p[1]), lame_lam(p[0], p[1]))


@wp.func
def stress_plasticine(p: vec5, F: wp.mat33, L: wp.mat33, plastic_J: float):
    return hencky_tau(F, lame_mu(p[0], p[1]), lame_lam(p[0], p[1]))


@wp.func
def stress_sand(p: vec5, F: wp.mat33, L: wp.mat33, plastic_J: float):
    # (friction angle, E, nu)
    return hencky_tau(F, lame_mu(p[1], p[2]), lame_lam(p[1], p[2]))


@wp.func
def stress_newtonian(p: vec5, F: wp.mat33, L: wp.mat33, plastic_J: float):
    return newtonian_tau(F, L, p[0], p[1])


@wp.func
def stress_non_newtonian(p: vec5, F: wp.mat33, L: wp.mat33, plastic_J: float):
    # (mu, kappa, yield stress, viscosity): Lame's lambda = kappa - 2 mu / 3
    return hencky_tau(F, p[0], p[1] - 2.0 * p[0] / 3.0)


@wp.func
def stress_snow(p: vec5, F: wp.mat33, L: wp.mat33, plastic_J: float):
    return snow_tau(F, p, plastic_J)


@wp.func
def stress_corotated(p: vec5, F: wp.mat33, L: wp.mat33, plastic_J: float):
    # elastic_corotated and plasticine_corotated: (E, nu[, yield_stress])
    return corotated_tau(F, lame_mu(p[0], p[1]), lame_lam(p[0], p[1]))


@wp.func
def kirchhoff_stress(law: int, p: vec5, F: wp.mat33, L: wp.mat33, plastic_J: float):
    # Kirchhoff stress tau = J sigma (Pa) of the object's law (STRESS_OF, by law id)
    tau = wp.mat33()
    if law == 0:
        tau = stress_elastic(p, F, L, plastic_J)
    elif law == 1:
        tau = stress_plasticine(p, F, L, plastic_J)
    elif law == 2:
        tau = stress_sand(p, F, L, plastic_J)
    elif law == 3:
        tau = stress_newtonian(p, F, L, plastic_J)
    elif law == 4:
        tau = stress_non_newtonian(p, F, L, plastic_J)
    elif law == 5:
        tau = stress_snow(p, F, L, plastic_J)
    else:  # 6 elastic_corotated, 7 plasticine_corotated
        tau = stress_corotated(p, F, L, plastic_J)
    return tau


@wp.func
def shrink_deviatoric(F: wp.mat33, U: wp.mat33, eps: wp.vec3, V: wp.mat33, dg: float):
    # eps <- eps - dg e/||e|| where dg > 0, F = U diag(exp(eps)) V^T; F unchanged otherwise
    out = F
    if dg > 0.0:
        e = deviatoric(eps)
        eps_new = eps - dg * e / safe_norm(e)
        out = U * wp.diag(exp3(eps_new)) * wp.transpose(V)
    return out


@wp.func
def von_mises_map(F: wp.mat33, mu: float, yield_stress: float, relax: float):
    # dg = (||dev eps|| - yield / (2 mu)) / relax  (relax = 1 for plasticine)
    U, s, V = proper_svd(F)
    eps = hencky(s)
    dg = (safe_norm(deviatoric(eps)) - yield_stress / (2.0 * mu)) / relax
    return shrink_deviatoric(F, U, eps, V, dg)


@wp.func
def drucker_prager_map(F: wp.mat33, p: vec5):
    # tr eps > 0: F = U V^T; else dg = ||e|| + alpha (3 lam + 2 mu) tr(eps) / (2 mu)
    mu = lame_mu(p[1], p[2])
    lam = lame_lam(p[1], p[2])
    sin_phi = wp.sin(p[0] * DEG)
    alpha = wp.sqrt(2.0 / 3.0) * 2.0 * sin_phi / (3.0 - sin_phi)
    U, s, V = proper_svd(F)
    eps = hencky(s)
    tr = trace3(eps)
    out = F
    if tr > 0.0:
        out = U * wp.transpose(V)
    else:
        dg = safe_norm(deviatoric(eps)) + alpha * (3.0 * lam + 2.0 * mu) * tr / (2.0 * mu)
        out = shrink_deviatoric(F, U, eps, V, dg)
    return out


@wp.func
def snow_map(F: wp.mat33, p: vec5, plastic_J: float):
    # s <- clamp(s, 1 - theta_c, 1 + theta_s); J_p <- J_p prod(s) / prod(s_new)
    U, s, V = proper_svd(F)
    lo = 1.0 - p[2]
    hi = 1.0 + p[3]
    sn = wp.vec3(wp.clamp(s[0], lo, hi), wp.clamp(s[1], lo, hi), wp.clamp(s[2], lo, hi))
    out = F
    pj = plastic_J
    if sn[0] != s[0] or sn[1] != s[1] or sn[2] != s[2]:
        # recompose only when clamped: unyielded particles keep F bit-exactly
        # (docs/PHYSICS.md, Snow)
        pj = plastic_J * (s[0] * s[1] * s[2]) / (sn[0] * sn[1] * sn[2])
        out = U * wp.diag(sn) * wp.transpose(V)
    return out, pj


@wp.func
def map_none(p: vec5, F: wp.mat33, plastic_J: float, dt: float):
    # elastic laws: the trial F is the new F
    return F, plastic_J


@wp.func
def map_von_mises(p: vec5, F: wp.mat33, plastic_J: float, dt: float):
    # plasticine and plasticine_corotated: (E, nu, yield stress)
    return von_mises_map(F, lame_mu(p[0], p[1]), p[2], 1.0), plastic_J


@wp.func
def map_sand(p: vec5, F: wp.mat33, plastic_J: float, dt: float):
    return drucker_prager_map(F, p), plastic_J


@wp.func
def map_newtonian(p: vec5, F: wp.mat33, plastic_J: float, dt: float):
    # a fluid keeps only its volume change: F = J^(1/3) I
    J = wp.max(wp.determinant(F), J_MIN)
    return wp.pow(J, 1.0 / 3.0) * wp.identity(n=3, dtype=float), plastic_J


@wp.func
def map_non_newtonian(p: vec5, F: wp.mat33, plastic_J: float, dt: float):
    # viscoplastic von Mises: the flow relaxed by 1 + viscosity / (2 mu dt)
    return von_mises_map(F, p[0], p[2], 1.0 + p[3] / (2.0 * p[0] * dt)), plastic_J


@wp.func
def map_snow(p: vec5, F: wp.mat33, plastic_J: float, dt: float):
    return snow_map(F, p, plastic_J)


@wp.func
def return_map(law: int, p: vec5, F: wp.mat33, plastic_J: float, dt: float):
    # plastic projection of the trial F (RETURN_MAP_OF, by law id); returns (F_new, plastic_J_new)
    out = F
    pj = plastic_J
    if law == 1 or law == 7:
        out, pj = map_von_mises(p, F, plastic_J, dt)
    elif law == 2:
        out, pj = map_sand(p, F, plastic_J, dt)
    elif law == 3:
        out, pj = map_newtonian(p, F, plastic_J, dt)
    elif law == 4:
        out, pj = map_non_newtonian(p, F, plastic_J, dt)
    elif law == 5:
        out, pj = map_snow(p, F, plastic_J, dt)
    return out, pj


#: law id -> the law's stress function (p, F, L, plastic_J) -> tau, for kernels made per law
#: (transfer_kernels.py): one law's code, none of the others' branches
STRESS_OF = {
    LAW_IDS["elastic"]: stress_elastic,
    LAW_IDS["plasticine"]: stress_plasticine,
    LAW_IDS["sand"]: stress_sand,
    LAW_IDS["newtonian"]: stress_newtonian,
    LAW_IDS["non_newtonian"]: stress_non_newtonian,
    LAW_IDS["snow"]: stress_snow,
    LAW_IDS["elastic_corotated"]: stress_corotated,
    LAW_IDS["plasticine_corotated"]: stress_corotated,
}

#: law id -> the law's return map (p, F_trial, plastic_J, dt) -> (F, plastic_J)
RETURN_MAP_OF = {
    LAW_IDS["elastic"]: map_none,
    LAW_IDS["plasticine"]: map_von_mises,
    LAW_IDS["sand"]: map_sand,
    LAW_IDS["newtonian"]: map_newtonian,
    LAW_IDS["non_newtonian"]: map_non_newtonian,
    LAW_IDS["snow"]: map_snow,
    LAW_IDS["elastic_corotated"]: map_none,
    LAW_IDS["plasticine_corotated"]: map_von_mises,
}


@wp.kernel
def evaluate_laws(
    law: int,
    params: wp.array(dtype=vec5),
    F: wp.array(dtype=wp.mat33),
    L: wp.array(dtype=wp.mat33),
    plastic_J: wp.array(dtype=float),
    dt: float,
    tau: wp.array(dtype=wp.mat33),
    F_new: wp.array(dtype=wp.mat33),
    plastic_J_new: wp.array(dtype=float),
):
    # per-particle stress and return map of one law (used by the parity tests)
    i = wp.tid()
    tau[i] = kirchhoff_stress(law, params[i], F[i], L[i], plastic_J[i])
    f, pj = return_map(law, params[i], F[i], plastic_J[i], dt)
    F_new[i] = f
    plastic_J_new[i] = pj
