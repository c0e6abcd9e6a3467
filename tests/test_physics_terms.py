"""The recipe's ``physics_terms`` section, its identified leaves, and the diagnosis's snippet.

Validation is checked for every kind of mistake at once; the parameter vector against the
ParamSpec mapping (value and derivative analytic); a rollout with an identified wind against
the ballistic law of a body's centre of mass, x(t) = x0 + v0 t + (g + a) t^2 / 2.
"""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import pytest
import torch
import yaml

from mosiv_framework.diagnose.candidates import Candidate
from mosiv_framework.diagnose.report import recipe_change
from mosiv_framework.errors import ConfigError
from mosiv_framework.laws import get_law
from mosiv_framework.pipeline import check_terms_supported
from mosiv_framework.pipeline.params import ParameterVector, term_param_specs
from mosiv_framework.recipes import load_recipe
from mosiv_framework.recipes.terms import identified_terms, term_tensors
from mosiv_framework.registry import get_registry
from mosiv_framework.terms import LinearDrag, Wind
from mosiv_framework.types import ObjectParams, ParticleSet, SimulationParams, World

WIND_SPEC = term_param_specs("wind")["acceleration"]


def _load(tmp_path: Path, text: str):
    path = tmp_path / "recipe.yaml"
    path.write_text("simulator: {name: warp-mpm, device: cpu}\n" + text)
    return load_recipe(path)


def test_physics_terms_resolve_with_defaults_and_flags(tmp_path):
    recipe = _load(
        tmp_path,
        "physics_terms:\n"
        "  wind: {acceleration: [1.0, 0, 0], identify: true}\n"
        "  linear_drag: {coefficient: 0.5, identify: false}\n"
        "  quadratic_drag: {}\n",
    )
    section = recipe.physics_terms
    assert list(section.wind.acceleration) == [1.0, 0.0, 0.0] and section.wind.identify
    assert section.linear_drag.coefficient == 0.5 and not section.linear_drag.identify
    # left-out parameters start at the ParamSpec default, identify defaults to false
    assert section.quadratic_drag.coefficient == 0.0 and not section.quadratic_drag.identify
    plain = {k: dict(v) for k, v in section.items()}
    assert identified_terms(plain) == ("wind",)
    tensors = term_tensors(plain)
    assert tensors["wind"]["acceleration"].shape == (3,)
    assert tensors["linear_drag"]["coefficient"].shape == ()


def test_physics_terms_report_every_mistake_by_key(tmp_path):
    with pytest.raises(ConfigError) as err:
        _load(
            tmp_path,
            "physics_terms:\n"
            "  breeze: {speed: 1}\n"  # not a registered term
            "  wind: {acceleration: 2.0, identify: maybe}\n"  # scalar for a vector, bad flag
            "  linear_drag: {coefficient: -1.0, c: 2}\n"  # outside [0, 50], unknown key
            "  quadratic_drag: {coefficient: [1, 2, 3]}\n",  # vector for a scalar
        )
    text = str(err.value)
    assert "physics_terms.breeze" in text and "wind" in text and "linear_drag" in text
    assert "physics_terms.wind.acceleration=2.0: must be a list of 3 numbers" in text
    assert "physics_terms.wind.identify='maybe': must be true or false" in text
    assert "physics_terms.linear_drag.coefficient" in text and "[0, 50]" in text
    assert "unknown key physics_terms.linear_drag.c; valid keys of linear_drag" in text
    assert "physics_terms.quadratic_drag.coefficient=[1, 2, 3]: must be a number" in text


def test_wind_vector_of_wrong_length_and_out_of_bounds(tmp_path):
    with pytest.raises(ConfigError, match=r"acceleration=\[1, 2\]: must be a list of 3"):
        _load(tmp_path, "physics_terms: {wind: {acceleration: [1, 2]}}\n")
    with pytest.raises(ConfigError, match=r"outside its valid range \[-50, 50\]"):
        _load(tmp_path, "physics_terms: {wind: {acceleration: [0, 99, 0]}}\n")


def test_simulator_without_the_term_is_refused():
    sim = SimpleNamespace(supported_terms=frozenset({"wind"}))
    check_terms_supported({"wind": {}}, sim, "toy")
    with pytest.raises(ConfigError, match=r"\['linear_drag'\]: simulator 'toy' does not"):
        check_terms_supported({"wind": {}, "linear_drag": {}}, sim, "toy")


def _vector(identify=("wind",)):
    return ParameterVector.create(
        {1: "elastic"},
        {1: torch.tensor([0.5, 0.0, 0.0])},
        ground_friction=None,
        terms={
            "wind": {"acceleration": torch.tensor([1.0, -2.0, 0.5])},
            "linear_drag": {"coefficient": torch.tensor(0.5)},
        },
        identify_terms=identify,
    )


def test_identified_term_is_a_normalised_leaf_within_its_bounds():
    vector = _vector()
    leaf = vector.normalized["term.wind.acceleration"]
    assert leaf.shape == (3,) and leaf.requires_grad
    # u = (a - lower) / (upper - lower) for the linear ParamSpec [-50, 50]
    expected = (torch.tensor([1.0, -2.0, 0.5]) + 50.0) / 100.0
    assert torch.allclose(leaf.detach(), expected)
    assert "term.linear_drag.coefficient" not in vector.normalized
    params = vector.physical()
    assert torch.allclose(params.terms["wind"]["acceleration"], torch.tensor([1.0, -2.0, 0.5]))
    assert float(params.terms["linear_drag"]["coefficient"]) == 0.5
    # d a / d u = upper - lower, per axis
    params.terms["wind"]["acceleration"].sum().backward()
    assert torch.allclose(leaf.grad, torch.full((3,), WIND_SPEC.upper - WIND_SPEC.lower))
    with torch.no_grad():  # bounds hold whatever the optimiser does to the leaf
        leaf.add_(10.0)
    assert torch.allclose(
        vector.physical().terms["wind"]["acceleration"], torch.full((3,), WIND_SPEC.upper)
    )


def test_terms_round_trip_through_identified_json():
    data = _vector().to_json()
    assert data["terms"]["wind"]["acceleration"] == pytest.approx([1.0, -2.0, 0.5])
    assert data["terms"]["linear_drag"]["coefficient"] == pytest.approx(0.5)
    back = ParameterVector.from_json(data)
    assert torch.allclose(back.terms["wind"]["acceleration"], torch.tensor([1.0, -2.0, 0.5]))
    assert back.terms["linear_drag"]["coefficient"].shape == ()
    with pytest.raises(ValueError, match="gravity"):
        _vector(identify=("gravity",))


def test_identified_wind_moves_the_centre_of_mass_ballistically():
    """A body in free flight under gravity g and wind a: c(t) = c0 + v0 t + (g + a) t^2 / 2
    (in its time-discrete form), so d c_x / d u_x = (upper - lower) times the t^2 / 2 factor
    through the normalised leaf."""
    fps, frames, substeps = 24.0, 2, 20
    world = World((0.0, 0.0, 0.0), (1.0, 1.0, 1.0), gravity=(0.0, 0.0, -9.8), ground_height=None)
    g = torch.linspace(0.0, 0.06, 4)
    pos = torch.stack(torch.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3) + 0.45
    n = pos.shape[0]
    particles = ParticleSet(
        pos, torch.full((n,), 0.02**3), torch.ones(n, dtype=torch.long), {1: "elastic"}
    )
    sim = get_registry().create(
        "simulator", "warp-mpm", {"grid": 16, "substeps": substeps, "device": "cpu"}
    )
    v0 = torch.tensor([0.3, 0.0, 0.5])
    wind = torch.tensor([2.0, 0.0, 0.0])
    vector = ParameterVector.create(
        {1: "elastic"},
        {1: v0},
        ground_friction=None,
        terms={"wind": {"acceleration": wind}},
        identify_terms=("wind",),
    )
    traj = sim.rollout(particles, vector.physical(), world=world, frames=frames)
    # symplectic Euler over n substeps of dt (velocity first, then position) moves the centre by
    # v0 t + a dt^2 n (n + 1) / 2, the discrete form of (g + a) t^2 / 2
    n_steps, dt = frames * substeps, 1.0 / (fps * substeps)
    t, drift = n_steps * dt, 0.5 * dt**2 * n_steps * (n_steps + 1)
    c = traj.positions[-1].mean(0)
    expected = pos.mean(0) + v0 * t + (torch.tensor(world.gravity) + wind) * drift
    assert torch.allclose(c, expected, atol=2e-5), (c, expected)
    # the tolerance resolves the discrete law: gravity alone makes it differ by ~40x as much
    assert 9.8 * (drift - 0.5 * t**2) > 20 * 2e-5
    c[0].backward()
    grad = vector.normalized["term.wind.acceleration"].grad
    analytic = drift * (WIND_SPEC.upper - WIND_SPEC.lower)
    assert float(grad[0]) == pytest.approx(analytic, rel=0.01)
    assert abs(float(grad[1])) < 0.03 * analytic and abs(float(grad[2])) < 0.03 * analytic


def _fit(candidate, theta, terms):
    params = SimulationParams(
        {
            1: ObjectParams(
                "elastic", {k: torch.tensor(v) for k, v in get_law("elastic").defaults().items()}
            )
        },
        {1: torch.zeros(3)},
        torch.tensor(0.3),
        terms,
    )
    return SimpleNamespace(candidate=candidate, theta=theta, params=params)


def _term_candidate(term, dim):
    spec = term.params[0]
    return Candidate(
        term.name,
        "term",
        [f"c{i}" for i in range(dim)],
        [spec.unit] * dim,
        torch.full((dim,), spec.lower),
        torch.full((dim,), spec.upper),
        torch.full((dim,), 0.01 * (spec.upper - spec.lower)),
        term.regimes,
        term.description,
        term,
    )


def test_recipe_change_loads_and_reproduces_the_term(tmp_path):
    """The diagnosis's snippet pasted into a recipe loads and carries the fitted wind, with
    the run's own (refitted) drag kept."""
    wind = _term_candidate(Wind(), 3)
    theta = torch.tensor([2.4371234, -0.0123456, 0.25])
    run_terms = {"linear_drag": {"coefficient": 0.5, "identify": True}}
    fit = _fit(
        wind,
        theta,
        {"linear_drag": {"coefficient": torch.tensor(0.61)}, "wind": {"acceleration": theta}},
    )
    snippet = recipe_change(fit, run_terms)
    assert yaml.safe_load(snippet)["physics_terms"]["wind"]["identify"] is True
    recipe = _load(tmp_path, snippet)
    terms = term_tensors({k: dict(v) for k, v in recipe.physics_terms.items()})
    assert torch.allclose(terms["wind"]["acceleration"], theta, rtol=1e-5)
    assert float(terms["linear_drag"]["coefficient"]) == pytest.approx(0.61, rel=1e-5)
    assert recipe.physics_terms.linear_drag.identify and recipe.physics_terms.wind.identify
    drag = _term_candidate(LinearDrag(), 1)
    snippet = recipe_change(_fit(drag, torch.tensor([1.75]), {}), None)
    recipe = _load(tmp_path, snippet)
    assert recipe.physics_terms.linear_drag.coefficient == pytest.approx(1.75)


def test_damping_and_restitution_are_registered_terms_with_bounds(tmp_path):
    """The two non-body-force terms: registered, no reference acceleration, recipe bounds
    enforced (viscosity [0, 200] Pa s, restitution [0, 1]), and concealable by the generator."""
    from mosiv_framework.conceal import TERM_KINDS, parse_conceal

    names = set(get_registry().names("physics_term"))
    assert {"material_damping", "ground_restitution"} <= names
    for name, param in (("material_damping", "viscosity"), ("ground_restitution", "coefficient")):
        term = get_registry().create("physics_term", name, {})
        assert [s.name for s in term.params] == [param] and term.params[0].default == 0.0
        assert term.reference_acceleration(torch.zeros(2, 3), {param: torch.tensor(1.0)}) is None
        assert name in TERM_KINDS
    recipe = _load(
        tmp_path,
        "physics_terms:\n  material_damping: {viscosity: 25.0}\n  ground_restitution: {}\n",
    )
    assert recipe.physics_terms.material_damping.viscosity == 25.0
    assert recipe.physics_terms.ground_restitution.coefficient == 0.0
    with pytest.raises(ConfigError, match=r"outside its valid range \[0, 1\]"):
        _load(tmp_path, "physics_terms: {ground_restitution: {coefficient: 1.5}}\n")
    with pytest.raises(ValueError, match="must be <= 1"):
        parse_conceal("ground_restitution:coefficient=1.2")
    assert parse_conceal("material_damping")[0].params == {"viscosity": 30.0}
