"""Physics, return-map, schema and gradient tests of the pure-torch constitutive laws."""

from __future__ import annotations

import math

import pytest
import torch

from mosiv_framework.laws import FAMILIES, LAWS, ConstitutiveLaw, get_law, lame_parameters
from mosiv_framework.laws.linalg import deviatoric, proper_svd

F64 = torch.float64


# ----------------------------------------------------------------------------- helpers


def params_of(law: ConstitutiveLaw, dtype=F64, **overrides) -> dict[str, torch.Tensor]:
    """Default parameters as 0-d tensors, with overrides."""
    vals = {**law.defaults(), **overrides}
    return {k: torch.tensor(v, dtype=dtype) for k, v in vals.items()}


def stress(law, F, values, *, plastic_J=None, L=None):
    if law.uses_velocity_gradient and L is None:
        L = torch.zeros_like(F)
    return law.kirchhoff_stress(F, values, plastic_J=plastic_J, velocity_gradient=L)


def rotations(n: int, gen: torch.Generator, dtype=F64) -> torch.Tensor:
    q, r = torch.linalg.qr(torch.randn(n, 3, 3, generator=gen, dtype=dtype))
    q = q * torch.sign(torch.diagonal(r, dim1=-2, dim2=-1))[:, None, :]
    return q * torch.where(torch.linalg.det(q) < 0, -1.0, 1.0).to(dtype)[:, None, None]


def from_singular(s: torch.Tensor, gen: torch.Generator) -> torch.Tensor:
    """F = U diag(s) V^T with random rotations U, V."""
    n = s.shape[0]
    U, V = rotations(n, gen, s.dtype), rotations(n, gen, s.dtype)
    return (U * s[:, None, :]) @ V.transpose(-1, -2)


def principal_strain(F: torch.Tensor) -> torch.Tensor:
    return torch.log(proper_svd(F)[1])


def sym_random(n: int, gen: torch.Generator) -> torch.Tensor:
    A = torch.randn(n, 3, 3, generator=gen, dtype=F64)
    return 0.5 * (A + A.transpose(-1, -2))


def lame_of(law: ConstitutiveLaw, values) -> tuple[torch.Tensor, torch.Tensor]:
    if law.name == "non_newtonian":
        mu = values["shear_modulus"]
        return mu, values["bulk_modulus"] - 2.0 * mu / 3.0
    return lame_parameters(values["E"], values["nu"])


EYE = torch.eye(3, dtype=F64)


# ----------------------------------------------------------------------------- registry & schema


def test_families_in_scene_order_and_lookup_errors():
    assert FAMILIES == (
        "elastic",
        "plasticine",
        "sand",
        "newtonian",
        "non_newtonian",
        "snow",
        "elastic_corotated",
        "plasticine_corotated",
    )
    assert tuple(LAWS) == FAMILIES
    for name in FAMILIES:
        assert get_law(name).name == name
    for exc in (KeyError, ValueError):
        with pytest.raises(exc) as info:
            get_law("jelly")
        assert "jelly" in str(info.value) and "non_newtonian" in str(info.value)


# (name, unit, lower, upper, default, log_scale), the table of docs/PHYSICS.md, Constitutive laws
SPEC = {
    "elastic": [("E", "Pa", 1e3, 1e7, 5e4, True), ("nu", "1", 0.0, 0.45, 0.25, False)],
    "plasticine": [
        ("E", "Pa", 1e3, 1e7, 5e4, True),
        ("nu", "1", 0.0, 0.45, 0.25, False),
        ("yield_stress", "Pa", 10, 1e6, 2e3, True),
    ],
    "sand": [
        ("friction_angle", "deg", 5, 60, 30, False),
        ("E", "Pa", 1e3, 1e7, 5e4, True),
        ("nu", "1", 0.0, 0.45, 0.3, False),
    ],
    "newtonian": [
        ("viscosity", "Pa*s", 1e-3, 1e4, 10, True),
        ("bulk_modulus", "Pa", 1e3, 1e7, 5e4, True),
    ],
    "non_newtonian": [
        ("shear_modulus", "Pa", 1e2, 1e6, 1e4, True),
        ("bulk_modulus", "Pa", 1e3, 1e7, 5e4, True),
        ("yield_stress", "Pa", 10, 1e5, 500, True),
        ("plastic_viscosity", "Pa*s", 1e-3, 1e3, 1.0, True),
    ],
    "elastic_corotated": [("E", "Pa", 1e3, 1e7, 5e4, True), ("nu", "1", 0.0, 0.45, 0.25, False)],
    "plasticine_corotated": [
        ("E", "Pa", 1e3, 1e7, 5e4, True),
        ("nu", "1", 0.0, 0.45, 0.25, False),
        ("yield_stress", "Pa", 10, 1e6, 2e3, True),
    ],
    "snow": [
        ("E", "Pa", 1e3, 1e7, 5e4, True),
        ("nu", "1", 0.0, 0.45, 0.25, False),
        ("critical_compression", "1", 1e-3, 0.2, 2.5e-2, False),
        ("critical_stretch", "1", 1e-3, 0.1, 7.5e-3, False),
        ("hardening", "1", 0, 30, 10, False),
    ],
}


@pytest.mark.parametrize("name", FAMILIES)
def test_param_schema_matches_spec(name):
    got = [(p.name, p.unit, p.lower, p.upper, p.default, p.log_scale) for p in LAWS[name].params]
    assert got == [tuple(float(x) if isinstance(x, int) else x for x in row) for row in SPEC[name]]
    assert LAWS[name].param_names()[-2:] == ["rho", "friction"]


@pytest.mark.parametrize("name", FAMILIES)
def test_param_normalisation_round_trip(name):
    for spec in LAWS[name].all_params:
        v = torch.tensor([spec.lower, spec.default, spec.upper], dtype=F64)
        u = spec.to_normalized(v)
        assert torch.allclose(u[[0, 2]], torch.tensor([0.0, 1.0], dtype=F64), atol=1e-12)
        assert torch.allclose(spec.from_normalized(u), v, rtol=1e-12, atol=1e-15)
        # Out-of-range normalised values are clamped back onto the bounds.
        out = spec.from_normalized(torch.tensor([-0.5, 1.5], dtype=F64))
        assert torch.allclose(out, torch.tensor([spec.lower, spec.upper], dtype=F64))


@pytest.mark.parametrize("name", FAMILIES)
def test_validate_names_parameter_and_range(name):
    law = LAWS[name]
    law.validate(law.defaults())
    spec = law.params[-1]
    with pytest.raises(ValueError) as info:
        law.validate({spec.name: spec.upper * 2 + 1})
    msg = str(info.value)
    assert spec.name in msg and f"{spec.lower:g}" in msg and f"{spec.upper:g}" in msg
    with pytest.raises(ValueError, match="no parameter"):
        law.validate({"stiffness": 1.0})


def test_derived_constants():
    values = {"E": torch.tensor(2.6e4, dtype=F64), "nu": torch.tensor(0.3, dtype=F64)}
    d = LAWS["elastic"].derived(values)
    assert torch.isclose(d["mu"], torch.tensor(1e4, dtype=F64))  # E / (2 (1 + nu))
    assert torch.isclose(d["lam"], torch.tensor(1.5e4, dtype=F64))  # E nu / ((1+nu)(1-2nu))
    sand = LAWS["sand"].derived({**values, "friction_angle": torch.tensor(30.0, dtype=F64)})
    assert torch.isclose(sand["alpha"], torch.tensor(math.sqrt(2 / 3) * 2 * 0.5 / 2.5, dtype=F64))
    nn = LAWS["non_newtonian"].derived(params_of(LAWS["non_newtonian"], bulk_modulus=3e4))
    assert torch.isclose(nn["lam"], torch.tensor(3e4 - 2e4 / 3, dtype=F64))
    # With like=F every constant becomes one value per particle.
    F = EYE.expand(5, 3, 3)
    assert LAWS["snow"].derived(params_of(LAWS["snow"]), like=F)["mu0"].shape == (5,)
    with pytest.raises(ValueError, match="shape"):
        LAWS["elastic"].derived({**values, "E": torch.ones(3, dtype=F64)}, like=F)


def test_missing_parameter_is_named():
    F = EYE.expand(2, 3, 3)
    with pytest.raises(KeyError, match="yield_stress"):
        LAWS["plasticine"].kirchhoff_stress(F, {"E": torch.tensor(1e4), "nu": torch.tensor(0.3)})


def test_fluid_needs_velocity_gradient_and_viscoplastic_needs_dt():
    F = EYE.expand(2, 3, 3)
    with pytest.raises(ValueError, match="velocity_gradient"):
        LAWS["newtonian"].kirchhoff_stress(F, params_of(LAWS["newtonian"]))
    with pytest.raises(ValueError, match="dt"):
        LAWS["non_newtonian"].return_map(F, params_of(LAWS["non_newtonian"]), dt=0.0)


# ----------------------------------------------------------------------------- stress


@pytest.mark.parametrize("name", FAMILIES)
def test_zero_stress_at_rest(name):
    law = LAWS[name]
    F = EYE.expand(4, 3, 3).clone()
    tau = stress(law, F, params_of(law), plastic_J=torch.ones(4, dtype=F64))
    assert torch.allclose(tau, torch.zeros_like(tau), atol=1e-9)


@pytest.mark.parametrize("name", ["elastic", "plasticine", "sand", "snow", "non_newtonian"])
def test_small_strain_limit_is_linear_elasticity(name):
    law, gen, h = LAWS[name], torch.Generator().manual_seed(1), 1e-5
    G = sym_random(8, gen)
    if name == "sand":  # sand only carries compressive states
        G = G - (G.diagonal(dim1=-2, dim2=-1).sum(-1).abs() + 1.0)[:, None, None] * EYE
    # Per-particle parameters exercise the [N] broadcast path.
    values = params_of(law)
    first = law.params[0].name
    values[first] = values[first] * torch.linspace(0.5, 2.0, 8, dtype=F64)
    mu, lam = lame_of(law, values)
    mu, lam = mu.expand(8), lam.expand(8)
    tau = stress(law, EYE + h * G, values)
    tr = G.diagonal(dim1=-2, dim2=-1).sum(-1)
    linear = 2.0 * mu[:, None, None] * G + (lam * tr)[:, None, None] * EYE
    assert torch.allclose(tau / h, linear, rtol=1e-3, atol=1e-3 * linear.abs().max().item())


def test_newtonian_pressure_and_viscous_parts():
    law, gen, h = LAWS["newtonian"], torch.Generator().manual_seed(2), 1e-6
    values = params_of(law, viscosity=3.0, bulk_modulus=2e5)
    # Small strain, no flow: tau = bulk_modulus * tr(eps) I.
    G = sym_random(5, gen)
    tau = stress(law, EYE + h * G, values)
    expected = 2e5 * G.diagonal(dim1=-2, dim2=-1).sum(-1)[:, None, None] * EYE
    assert torch.allclose(tau / h, expected, rtol=1e-4, atol=1e-6 * 2e5)
    # Isochoric F (J = 1): only the viscous part remains, viscosity * (L + L^T).
    s = torch.tensor([[1.3, 0.9, 1 / (1.3 * 0.9)]] * 5, dtype=F64)
    F = from_singular(s, gen)
    L = torch.randn(5, 3, 3, generator=gen, dtype=F64)
    tau = stress(law, F, values, L=L)
    assert torch.allclose(tau, 3.0 * (L + L.transpose(-1, -2)), rtol=1e-10, atol=1e-8)
    # Finite compression: the Tait term (bulk_modulus / 7)(J - J^-6).
    J = 0.8
    tau = stress(law, J ** (1 / 3) * EYE.expand(1, 3, 3), values)
    assert torch.allclose(tau, 2e5 / 7 * (J - J**-6) * EYE, rtol=1e-12)


def test_elastic_is_neo_hookean_at_finite_strain():
    law, gen = LAWS["elastic"], torch.Generator().manual_seed(3)
    values = params_of(law, E=1e5, nu=0.3)
    mu, lam = lame_parameters(values["E"], values["nu"])
    F = from_singular(torch.tensor([[1.4, 0.8, 0.7]], dtype=F64), gen)
    J = torch.linalg.det(F)
    expected = mu * (F @ F.transpose(-1, -2) - EYE) + lam * torch.log(J)[:, None, None] * EYE
    assert torch.allclose(stress(law, F, values), expected, rtol=1e-12)


def test_hencky_and_snow_principal_stresses_at_finite_strain():
    gen = torch.Generator().manual_seed(4)
    s = torch.tensor([[1.3, 0.9, 0.75]], dtype=F64)
    U, V = rotations(1, gen), rotations(1, gen)
    F = (U * s[:, None, :]) @ V.transpose(-1, -2)
    law = LAWS["plasticine"]
    values = params_of(law)
    mu, lam = lame_parameters(values["E"], values["nu"])
    eps = torch.log(s)
    principal = 2 * mu * eps + lam * eps.sum()
    assert torch.allclose(stress(law, F, values), (U * principal) @ U.transpose(-1, -2))
    snow = LAWS["snow"]
    values = params_of(snow)
    pj = torch.tensor([0.9], dtype=F64)
    mu0, lam0 = lame_parameters(values["E"], values["nu"])
    k = torch.exp(values["hardening"] * 0.1)
    J = s.prod()
    principal = 2 * mu0 * k * (s - 1) * s + lam0 * k * (J - 1) * J
    tau = stress(snow, F, values, plastic_J=pj)
    assert torch.allclose(tau, (U * principal) @ U.transpose(-1, -2), rtol=1e-10)


@pytest.mark.parametrize("name", ["elastic_corotated", "plasticine_corotated"])
def test_corotated_principal_stresses_at_finite_strain(name):
    """tau = 2 mu (F - R) F^T + lam (J - 1) J I has principal values 2 mu (s - 1) s + lam (J - 1) J
    in U's frame: Genesis's Elastic; at 30 % stretch it parts from neo-Hookean and Hencky."""
    gen = torch.Generator().manual_seed(12)
    s = torch.tensor([[1.3, 0.9, 0.75]], dtype=F64)
    U, V = rotations(1, gen), rotations(1, gen)
    F = (U * s[:, None, :]) @ V.transpose(-1, -2)
    law = LAWS[name]
    values = params_of(law, E=1e5, nu=0.3)
    mu, lam = lame_parameters(values["E"], values["nu"])
    J = s.prod()
    principal = 2 * mu * (s - 1) * s + lam * (J - 1) * J
    tau = stress(law, F, values)
    assert torch.allclose(tau, (U * principal) @ U.transpose(-1, -2), rtol=1e-10)
    base = LAWS["elastic" if name == "elastic_corotated" else "plasticine"]
    other = stress(base, F, params_of(base, E=1e5, nu=0.3))
    assert (tau - other).norm() > 0.05 * tau.norm()


def test_plasticine_corotated_returns_like_plasticine():
    """Only the stress differs: the von Mises return map on the Hencky strain is plasticine's."""
    gen = torch.Generator().manual_seed(13)
    F, _ = yield_state(6, gen, dev_size=0.2, trace=-0.01)
    values = params_of(LAWS["plasticine"], yield_stress=5e3)
    ours = LAWS["plasticine_corotated"].return_map(F, values)[0]
    assert torch.equal(ours, LAWS["plasticine"].return_map(F, values)[0])


@pytest.mark.parametrize("name", FAMILIES)
def test_stress_is_symmetric_and_frame_indifferent(name):
    law, gen = LAWS[name], torch.Generator().manual_seed(5)
    F = from_singular(torch.rand(6, 3, generator=gen, dtype=F64) * 0.8 + 0.6, gen)
    L = torch.randn(6, 3, 3, generator=gen, dtype=F64)
    pj = torch.rand(6, generator=gen, dtype=F64) * 0.4 + 0.8
    values = params_of(law)
    tau = stress(law, F, values, plastic_J=pj, L=L)
    assert torch.allclose(tau, tau.transpose(-1, -2), atol=1e-9 * tau.abs().max().item())
    R = rotations(6, gen)
    Rt = R.transpose(-1, -2)
    tau_rot = stress(law, R @ F, values, plastic_J=pj, L=R @ L @ Rt)
    assert torch.allclose(tau_rot, R @ tau @ Rt, atol=1e-9 * tau.abs().max().item())


@pytest.mark.parametrize("name", FAMILIES)
@pytest.mark.parametrize("dtype", [torch.float32, F64])
def test_crushed_and_near_singular_states_stay_finite(name, dtype):
    law, gen = LAWS[name], torch.Generator().manual_seed(6)
    s = torch.tensor(
        [[0.1, 0.1, 0.1], [2.0, 1.0, 5e-4], [1.0, 1.0, 1e-7], [1.0, 1.0, -0.2]], dtype=dtype
    )
    F = from_singular(s, gen).requires_grad_(True)
    values = params_of(law, dtype=dtype)
    pj = torch.ones(4, dtype=dtype)
    tau = stress(law, F, values, plastic_J=pj)
    F_new, pj_new = law.return_map(F, values, plastic_J=pj, dt=1e-3)
    assert torch.isfinite(tau).all() and torch.isfinite(F_new).all()
    assert torch.isfinite(pj_new).all()
    (tau.sum() / law.params[0].default + F_new.sum() + pj_new.sum()).backward()
    assert torch.isfinite(F.grad).all()


# ----------------------------------------------------------------------------- return maps


def yield_state(n, gen, *, dev_size, trace=0.0):
    """Random F whose Hencky strain has deviatoric norm dev_size and the given trace."""
    e = deviatoric(torch.randn(n, 3, generator=gen, dtype=F64))
    e = e / e.norm(dim=-1, keepdim=True) * dev_size + trace / 3.0
    return from_singular(torch.exp(e), gen), e


@pytest.mark.parametrize("name", ["plasticine", "plasticine_corotated", "non_newtonian"])
def test_von_mises_return_map_lands_on_surface(name):
    law, gen = LAWS[name], torch.Generator().manual_seed(7)
    values = params_of(law, plastic_viscosity=0.0) if name == "non_newtonian" else params_of(law)
    mu = lame_of(law, values)[0]
    radius = (values["yield_stress"] / (2 * mu)).item()
    F, eps = yield_state(5, gen, dev_size=3.0 * radius, trace=-0.02)
    F_new, pj = law.return_map(F, values, plastic_J=torch.full((5,), 0.7, dtype=F64), dt=1e-3)
    eps_new = principal_strain(F_new)
    on_surface = 2 * mu * deviatoric(eps_new).norm(dim=-1)
    assert torch.allclose(on_surface, values["yield_stress"].expand(5), rtol=1e-4)
    assert torch.allclose(eps_new.sum(-1), eps.sum(-1), atol=1e-10)  # volume is elastic
    assert torch.equal(pj, torch.full((5,), 0.7, dtype=F64))
    # Inside the surface nothing changes.
    F_in, _ = yield_state(5, gen, dev_size=0.5 * radius)
    assert torch.equal(law.return_map(F_in, values, dt=1e-3)[0], F_in)


def test_non_newtonian_relaxes_a_rate_dependent_fraction():
    law, gen, dt = LAWS["non_newtonian"], torch.Generator().manual_seed(8), 1e-3
    values = params_of(law, plastic_viscosity=30.0)
    mu = values["shear_modulus"]
    radius = (values["yield_stress"] / (2 * mu)).item()
    F, eps = yield_state(4, gen, dev_size=2.5 * radius)
    eps_new = principal_strain(law.return_map(F, values, dt=dt)[0])
    dg = (2.5 - 1.0) * radius / (1.0 + 30.0 / (2 * mu.item() * dt))
    got = deviatoric(eps).norm(dim=-1) - deviatoric(eps_new).norm(dim=-1)
    assert torch.allclose(got, torch.full((4,), dg, dtype=F64), rtol=1e-8)


def test_sand_return_map():
    law, gen = LAWS["sand"], torch.Generator().manual_seed(9)
    values = params_of(law, friction_angle=25.0)
    mu, lam = lame_parameters(values["E"], values["nu"])
    sin_phi = math.sin(math.radians(25.0))
    alpha = math.sqrt(2 / 3) * 2 * sin_phi / (3 - sin_phi)
    slope = alpha * (3 * lam + 2 * mu) / (2 * mu)
    # Expansion: all elastic strain is lost, F becomes its polar rotation.
    F, _ = yield_state(4, gen, dev_size=0.05, trace=0.03)
    U, _, V = proper_svd(F)
    F_new = law.return_map(F, values)[0]
    assert torch.allclose(F_new, U @ V.transpose(-1, -2), atol=1e-12)
    # Compression outside the cone lands on the cone with the same volume strain.
    F, eps = yield_state(4, gen, dev_size=0.05, trace=-0.01)
    eps_new = principal_strain(law.return_map(F, values)[0])
    cone = deviatoric(eps_new).norm(dim=-1) + slope * eps_new.sum(-1)
    assert torch.allclose(cone, torch.zeros(4, dtype=F64), atol=1e-10)
    assert torch.allclose(eps_new.sum(-1), eps.sum(-1), atol=1e-12)
    # Compression inside the cone is elastic.
    F, _ = yield_state(4, gen, dev_size=0.001, trace=-0.01)
    assert torch.equal(law.return_map(F, values)[0], F)


def test_snow_clamps_and_preserves_total_volume():
    law, gen = LAWS["snow"], torch.Generator().manual_seed(10)
    values = params_of(law)
    tc, ts = values["critical_compression"].item(), values["critical_stretch"].item()
    s = torch.tensor([[1.05, 1.0, 0.9], [1.002, 0.99, 0.98], [1.2, 1.1, 1.0]], dtype=F64)
    F = from_singular(s, gen)
    pj = torch.tensor([1.0, 0.95, 1.1], dtype=F64)
    F_new, pj_new = law.return_map(F, values, plastic_J=pj)
    s_new = proper_svd(F_new)[1]
    assert torch.allclose(s_new, s.clamp(1 - tc, 1 + ts), atol=1e-12)
    total_before = torch.linalg.det(F) * pj
    assert torch.allclose(torch.linalg.det(F_new) * pj_new, total_before, rtol=1e-12)
    assert torch.equal(F_new[1], F[1]) and pj_new[1] == pj[1]  # inside the band: elastic
    assert pj_new[0] < pj[0] and pj_new[2] > pj[2]  # compaction lowers J_p, stretch raises it


def test_newtonian_return_map_keeps_volume_and_drops_shear():
    law, gen = LAWS["newtonian"], torch.Generator().manual_seed(11)
    F = from_singular(torch.rand(5, 3, generator=gen, dtype=F64) + 0.5, gen)
    F_new, _ = law.return_map(F, params_of(law))
    J = torch.linalg.det(F)
    assert torch.allclose(torch.linalg.det(F_new), J, rtol=1e-12)
    assert torch.allclose(F_new, J[:, None, None] ** (1 / 3) * EYE, rtol=1e-12)


@pytest.mark.parametrize("name", ["elastic", "plasticine", "sand", "newtonian", "non_newtonian"])
def test_plastic_j_passes_through(name):
    law, gen = LAWS[name], torch.Generator().manual_seed(12)
    F = from_singular(torch.rand(3, 3, generator=gen, dtype=F64) + 0.5, gen)
    pj = torch.tensor([0.8, 1.0, 1.3], dtype=F64)
    assert torch.equal(law.return_map(F, params_of(law), plastic_J=pj, dt=1e-3)[1], pj)
    if name in ("elastic", "elastic_corotated"):
        assert torch.equal(law.return_map(F, params_of(law))[0], F)


# ----------------------------------------------------------------------------- gradients

# Generic (distinct singular values) states per law, chosen away from yield-surface kinks:
# plastic where the law has plasticity, so the gradient goes through the return map.
GRAD_SINGULAR = {
    "elastic": [[1.2, 0.95, 0.8]],
    "plasticine": [[1.2, 0.95, 0.8], [1.01, 1.0, 0.995]],
    "sand": [[1.05, 0.97, 0.9], [1.2, 1.05, 0.95]],  # on-cone compression, expansion
    "newtonian": [[1.2, 0.95, 0.8]],
    "non_newtonian": [[1.2, 0.95, 0.8], [1.01, 1.0, 0.995]],
    "snow": [[1.05, 0.995, 0.9], [1.004, 1.0, 0.99]],
    "elastic_corotated": [[1.2, 0.95, 0.8]],
    "plasticine_corotated": [[1.2, 0.95, 0.8], [1.01, 1.0, 0.995]],
}


@pytest.mark.parametrize("name", FAMILIES)
def test_gradcheck_stress_and_return_map(name):
    law, gen = LAWS[name], torch.Generator().manual_seed(13)
    F = from_singular(torch.tensor(GRAD_SINGULAR[name], dtype=F64), gen)
    n = F.shape[0]
    names = [p.name for p in law.params]
    # Parameters in O(1) units so finite differences see comparable scales.
    scale = {p.name: (p.default if p.default != 0 else 1.0) for p in law.params}
    unit = [torch.tensor(1.0, dtype=F64, requires_grad=True) for _ in names]
    L = torch.randn(n, 3, 3, generator=gen, dtype=F64, requires_grad=True)
    pj = torch.tensor([0.9, 1.05][:n], dtype=F64, requires_grad=True)
    stress_scale = float(law.params[0].default)

    def values(xs):
        return {k: x * scale[k] for k, x in zip(names, xs, strict=True)}

    def tau_fn(F_, L_, pj_, *xs):
        return stress(law, F_, values(xs), plastic_J=pj_, L=L_) / stress_scale

    def map_fn(F_, pj_, *xs):
        return law.return_map(F_, values(xs), plastic_J=pj_, dt=2e-3)

    F = F.requires_grad_(True)
    assert torch.autograd.gradcheck(tau_fn, (F, L, pj, *unit), atol=1e-6, rtol=1e-4)
    assert torch.autograd.gradcheck(map_fn, (F, pj, *unit), atol=1e-6, rtol=1e-4)


@pytest.mark.parametrize(
    "name",
    ["plasticine", "sand", "non_newtonian", "snow", "elastic_corotated", "plasticine_corotated"],
)
def test_stress_gradient_exact_at_identity(name):
    """At F = I (all singular values equal) d tau / dF is the linear-elastic tangent.

    That tangent T(dF) = 2 mu sym(dF) + lam tr(dF) I is self-adjoint, so the reverse-mode
    gradient of <W, tau> must be T(W) for any W.
    """
    law = LAWS[name]
    values = params_of(law)
    mu, lam = lame_of(law, values)
    gen = torch.Generator().manual_seed(14)
    W = torch.randn(1, 3, 3, generator=gen, dtype=F64)
    F = EYE.expand(1, 3, 3).clone().requires_grad_(True)
    (grad,) = torch.autograd.grad((stress(law, F, values) * W).sum(), F)
    sym = 0.5 * (W + W.transpose(-1, -2))
    expected = 2 * mu * sym + lam * W.diagonal(dim1=-2, dim2=-1).sum(-1)[:, None, None] * EYE
    assert torch.allclose(grad, expected, rtol=1e-9, atol=1e-9 * float(mu))


def test_return_map_gradcheck_at_repeated_singular_values():
    """Uniaxial plastic state s = (a, b, b): the return map is smooth there, and so is ours."""
    law, gen = LAWS["plasticine"], torch.Generator().manual_seed(15)
    F = from_singular(torch.tensor([[1.1, 0.95, 0.95]], dtype=F64), gen).requires_grad_(True)
    values = params_of(law)
    assert torch.autograd.gradcheck(lambda X: law.return_map(X, values)[0], (F,), atol=1e-6)
