"""The constitutive laws (docs/PHYSICS.md, Constitutive laws) as Taichi functions.

Every law is split the same way so that the simulator needs only one SVD per particle and
substep (whose adjoint is written by hand in ``svd_grad.py``, because Taichi cannot
differentiate its built-in SVD):

- ``*_stress`` returns the Kirchhoff stress tau = J sigma (Pa) of the elastic state, given F and
  its proper SVD factors U, s (F = U diag(s) V^T, det U = det V = +1);
- ``*_return_map`` takes the trial F with its SVD and returns (F_new, s_new, plastic_J_new), where
  s_new are the singular values of F_new in the same U, V frame.

``P`` is the object's parameter vector in the order of ``LAW_PARAMS[family]`` (zero-padded to
``MAX_LAW_PARAMS``). Every function is differentiable by Taichi's autodiff: norms and logarithms
are guarded so that their derivatives stay finite where a branch does not use them.
"""

# no `from __future__ import annotations`: Taichi reads the annotations at runtime
import math

import taichi as ti

from mosiv_framework.laws import FAMILIES, get_law

#: family name -> law id used inside kernels (the core's family order)
LAW_IDS: dict[str, int] = {family: i for i, family in enumerate(FAMILIES)}

#: family name -> parameter names, in the order they are packed into P (the core's schema order)
LAW_PARAMS: dict[str, tuple[str, ...]] = {
    family: tuple(spec.name for spec in get_law(family).params) for family in FAMILIES
}
MAX_LAW_PARAMS = 5

SINGULAR_MIN = 1e-4  # s is clamped to this before log (Hencky strain)
J_MIN = 1e-6  # J is clamped to this before log / negative powers (the torch reference: 1e-4)
NORM_EPS = 1e-30  # added under square roots so their derivative stays finite at 0
DEG = math.pi / 180.0

Mat3 = ti.types.matrix(3, 3, ti.f32)
Vec3 = ti.types.vector(3, ti.f32)


@ti.func
def lame(E, nu):
    """mu = E / (2 (1 + nu)), lam = E nu / ((1 + nu)(1 - 2 nu)) (Pa)."""
    return E / (2.0 * (1.0 + nu)), E * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))


@ti.func
def diag3(d):
    return ti.Matrix([[d[0], 0.0, 0.0], [0.0, d[1], 0.0], [0.0, 0.0, d[2]]], ti.f32)


@ti.func
def hencky(s):
    """Principal Hencky strain eps = log(max(s, 1e-4))."""
    return ti.log(ti.max(s, SINGULAR_MIN))


@ti.func
def safe_norm(e):
    """||e|| with a finite derivative at e = 0."""
    return ti.sqrt(e.dot(e) + NORM_EPS)


@ti.func
def hencky_tau(U, s, mu, lam):
    """StVK-Hencky: tau = U diag(2 mu eps + lam tr(eps)) U^T."""
    eps = hencky(s)
    principal = 2.0 * mu * eps + lam * eps.sum()
    return U @ diag3(principal) @ U.transpose()


@ti.func
def compose(U, s, V):
    """F = U diag(s) V^T."""
    return U @ diag3(s) @ V.transpose()


# ----------------------------------------------------------------------------------------------
# Kirchhoff stresses
# ----------------------------------------------------------------------------------------------


@ti.func
def elastic_stress(F, P):
    """Neo-Hookean: tau = mu (F F^T - I) + lam ln(J) I."""
    mu, lam = lame(P[0], P[1])
    J = ti.max(F.determinant(), J_MIN)
    return mu * (F @ F.transpose() - ti.Matrix.identity(ti.f32, 3)) + lam * ti.log(
        J
    ) * ti.Matrix.identity(ti.f32, 3)


@ti.func
def plasticine_stress(U, s, P):
    """StVK-Hencky with (mu, lam) from (E, nu)."""
    mu, lam = lame(P[0], P[1])
    return hencky_tau(U, s, mu, lam)


@ti.func
def sand_stress(U, s, P):
    """StVK-Hencky with (mu, lam) from (E = P[1], nu = P[2])."""
    mu, lam = lame(P[1], P[2])
    return hencky_tau(U, s, mu, lam)


@ti.func
def newtonian_stress(F, C, P):
    """tau = J eta (L + L^T) + (K / 7)(J - J^-6) I, L = C (APIC velocity gradient)."""
    J = ti.max(F.determinant(), J_MIN)
    pressure = P[1] / 7.0 * (J - ti.pow(J, -6.0))
    return J * P[0] * (C + C.transpose()) + pressure * ti.Matrix.identity(ti.f32, 3)


@ti.func
def non_newtonian_stress(U, s, P):
    """StVK-Hencky with mu = shear modulus, lam = kappa - 2 mu / 3."""
    mu = P[0]
    return hencky_tau(U, s, mu, P[1] - 2.0 * mu / 3.0)


@ti.func
def corotated_stress(U, s, mu, lam):
    """Fixed-corotated: tau = 2 mu (F - R) F^T + lam (J - 1) J I = U diag(2 mu (s-1) s) U^T + ..."""
    J = s[0] * s[1] * s[2]
    shear = U @ diag3(2.0 * mu * (s - 1.0) * s) @ U.transpose()
    return shear + lam * (J - 1.0) * J * ti.Matrix.identity(ti.f32, 3)


@ti.func
def snow_stress(U, s, Jp, P):
    """Fixed-corotated with mu, lam hardened by exp(xi (1 - plastic_J))."""
    mu0, lam0 = lame(P[0], P[1])
    h = ti.exp(P[4] * (1.0 - Jp))
    return corotated_stress(U, s, mu0 * h, lam0 * h)


@ti.func
def elastic_corotated_stress(U, s, P):
    """Fixed-corotated with P = (E, nu[, yield_stress]): elastic_corotated and
    plasticine_corotated."""
    mu, lam = lame(P[0], P[1])
    return corotated_stress(U, s, mu, lam)


# ----------------------------------------------------------------------------------------------
# Return maps: (F_trial, U, s, V, plastic_J) -> (F_new, s_new, plastic_J_new)
# ----------------------------------------------------------------------------------------------


@ti.func
def shrink_deviatoric(F, U, s, V, dg):
    """eps <- eps - dg e/||e|| where dg > 0 (tr eps kept), else F unchanged."""
    F_new = F
    s_new = s
    if dg > 0.0:
        eps = hencky(s)
        e = eps - eps.sum() / 3.0
        eps = eps - dg * e / safe_norm(e)
        s_new = ti.exp(eps)
        F_new = compose(U, s_new, V)
    return F_new, s_new


@ti.func
def plasticine_return_map(F, U, s, V, P):
    """von Mises: dg = ||dev eps|| - yield_stress / (2 mu)."""
    mu, _lam = lame(P[0], P[1])
    eps = hencky(s)
    dg = safe_norm(eps - eps.sum() / 3.0) - P[2] / (2.0 * mu)
    return shrink_deviatoric(F, U, s, V, dg)


@ti.func
def sand_return_map(F, U, s, V, P):
    """Drucker-Prager (Klar 2016): tension -> s = 1; else dg = ||e|| + alpha (3lam+2mu) tr(eps)/(2mu)."""
    mu, lam = lame(P[1], P[2])
    sin_phi = ti.sin(P[0] * DEG)
    alpha = ti.sqrt(2.0 / 3.0) * 2.0 * sin_phi / (3.0 - sin_phi)
    eps = hencky(s)
    tr = eps.sum()
    dg = safe_norm(eps - tr / 3.0) + alpha * (3.0 * lam + 2.0 * mu) * tr / (2.0 * mu)
    F_new, s_new = shrink_deviatoric(F, U, s, V, dg)
    if tr > 0.0:
        s_new = ti.Vector([1.0, 1.0, 1.0], ti.f32)
        F_new = U @ V.transpose()
    return F_new, s_new


@ti.func
def newtonian_return_map(F):
    """A fluid keeps only its volume: F_new = J^(1/3) I."""
    c = ti.pow(ti.max(F.determinant(), J_MIN), 1.0 / 3.0)
    return c * ti.Matrix.identity(ti.f32, 3), ti.Vector([c, c, c], ti.f32)


@ti.func
def non_newtonian_return_map(F, U, s, V, P, dt):
    """Viscoplastic: dg = (||e|| - yield/(2 mu)) / (1 + eta / (2 mu dt)) where positive."""
    mu = P[0]
    eps = hencky(s)
    dg = safe_norm(eps - eps.sum() / 3.0) - P[2] / (2.0 * mu)
    dg = dg / (1.0 + P[3] / (2.0 * mu * dt))
    return shrink_deviatoric(F, U, s, V, dg)


@ti.func
def snow_return_map(U, s, V, Jp, P):
    """s_new = clamp(s, 1 - theta_c, 1 + theta_s); Jp <- Jp prod(s) / prod(s_new)."""
    s_new = ti.min(ti.max(s, 1.0 - P[2]), 1.0 + P[3])
    Jp_new = Jp * (s[0] * s[1] * s[2]) / (s_new[0] * s_new[1] * s_new[2])
    return compose(U, s_new, V), s_new, Jp_new


# ----------------------------------------------------------------------------------------------
# Dispatch over the families present in a scene (``present`` is a compile-time tuple of ids)
# ----------------------------------------------------------------------------------------------


@ti.func
def kirchhoff_stress(present: ti.template(), law, F, U, s, C, Jp, P):
    """Kirchhoff stress tau (Pa) of the particle's law."""
    tau = ti.Matrix.zero(ti.f32, 3, 3)
    for i in ti.static(range(len(present))):
        if law == ti.static(present[i]):
            if ti.static(present[i] == 0):
                tau = elastic_stress(F, P)
            elif ti.static(present[i] == 1):
                tau = plasticine_stress(U, s, P)
            elif ti.static(present[i] == 2):
                tau = sand_stress(U, s, P)
            elif ti.static(present[i] == 3):
                tau = newtonian_stress(F, C, P)
            elif ti.static(present[i] == 4):
                tau = non_newtonian_stress(U, s, P)
            elif ti.static(present[i] == 5):
                tau = snow_stress(U, s, Jp, P)
            else:  # 6 elastic_corotated, 7 plasticine_corotated
                tau = elastic_corotated_stress(U, s, P)
    return tau


@ti.func
def return_map(present: ti.template(), law, F, U, s, V, Jp, P, dt):
    """(F_new, s_new, plastic_J_new) of the particle's law after the plastic projection."""
    F_new = F
    s_new = s
    Jp_new = Jp
    for i in ti.static(range(len(present))):
        if law == ti.static(present[i]):
            if ti.static(present[i] == 1 or present[i] == 7):  # von Mises, either stress
                F_new, s_new = plasticine_return_map(F, U, s, V, P)
            elif ti.static(present[i] == 2):
                F_new, s_new = sand_return_map(F, U, s, V, P)
            elif ti.static(present[i] == 3):
                F_new, s_new = newtonian_return_map(F)
            elif ti.static(present[i] == 4):
                F_new, s_new = non_newtonian_return_map(F, U, s, V, P, dt)
            elif ti.static(present[i] == 5):
                F_new, s_new, Jp_new = snow_return_map(U, s, V, Jp, P)
    return F_new, s_new, Jp_new
