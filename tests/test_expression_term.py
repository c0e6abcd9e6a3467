"""The ``expression`` physics term's schema (mosiv_framework.expression): registered, sparse
(only the (axis, feature) coefficients given exist, in a recipe and in the identified
parameter vector), names checked with messages that list the valid features, and a torch
reference that equals the library terms it contains (a_x:v_x = -c is linear drag along x)."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from mosiv_framework.errors import ConfigError
from mosiv_framework.expression import (
    FEATURES,
    ExpressionTerm,
    acceleration,
    node_features,
    parse_coefficient,
    uses_relative,
)
from mosiv_framework.pipeline.params import ParameterVector
from mosiv_framework.recipes import load_recipe
from mosiv_framework.recipes.terms import term_tensors
from mosiv_framework.registry import get_registry
from mosiv_framework.terms import LinearDrag, QuadraticDrag


def _load(tmp_path: Path, text: str):
    path = tmp_path / "recipe.yaml"
    path.write_text("simulator: {name: warp-mpm, device: cpu}\n" + text)
    return load_recipe(path)


def test_registered_with_a_coefficient_per_axis_and_feature():
    term = get_registry().create("physics_term", "expression", {})
    assert term.sparse and len(term.params) == 3 * len(FEATURES)
    spec = {s.name: s for s in term.params}["a_z:|v|v_z"]
    assert spec.unit == "1/m" and spec.default == 0.0 and spec.lower < 0 < spec.upper
    assert {s.name: s.unit for s in term.params}["a_x:t"] == "m/s^3"


def test_a_recipe_expression_holds_and_identifies_only_the_coefficients_given(tmp_path):
    recipe = _load(
        tmp_path,
        'physics_terms:\n  expression: {"a_x:v_x": -0.4, "a_z:h": -2.0, identify: true}\n',
    )
    section = {k: dict(v) for k, v in recipe.physics_terms.items()}
    assert set(section["expression"]) == {"a_x:v_x", "a_z:h", "identify"}
    terms = term_tensors(section)
    vector = ParameterVector.create(
        {1: "elastic"}, {1: torch.zeros(3)}, terms=terms, identify_terms=("expression",)
    )
    free = [k for k in vector.normalized if k.startswith("term.")]
    assert sorted(free) == ["term.expression.a_x:v_x", "term.expression.a_z:h"]
    physical = vector.physical().terms["expression"]
    assert float(physical["a_x:v_x"].detach()) == pytest.approx(-0.4, rel=1e-5)


def test_an_unknown_feature_is_refused_listing_the_valid_ones(tmp_path):
    with pytest.raises(ConfigError) as err:
        _load(tmp_path, 'physics_terms:\n  expression: {"a_x:speed": 1.0}\n')
    text = str(err.value)
    assert "unknown key physics_terms.expression.a_x:speed" in text
    assert "FEATURE one of 1, x, y, z, h, v_x" in text
    with pytest.raises(ValueError, match="unknown feature 'speed'; valid features: 1, x"):
        parse_coefficient("a_x:speed")
    with pytest.raises(ValueError, match="a_AXIS:FEATURE with AXIS one of x, y, z"):
        parse_coefficient("v_x")
    assert parse_coefficient("a_y:|v|v_z") == (1, "|v|v_z")
    assert uses_relative({"a_x:dv_y": 1.0}) and not uses_relative({"a_x:t": 1.0})


def test_the_reference_equals_the_drag_terms_it_contains():
    v = torch.randn(20, 3, generator=torch.Generator().manual_seed(0))
    term = ExpressionTerm()
    c = torch.tensor(0.7)
    lin = {f"a_{a}:v_{a}": -c for a in "xyz"}
    quad = {f"a_{a}:|v|v_{a}": -c for a in "xyz"}
    expected = LinearDrag().reference_acceleration(v, {"coefficient": c})
    assert torch.allclose(term.reference_acceleration(v, lin), expected)
    expected = QuadraticDrag().reference_acceleration(v, {"coefficient": c})
    assert torch.allclose(term.reference_acceleration(v, quad), expected, atol=1e-6)
    with pytest.raises(ValueError, match="needs positions, time or the other objects"):
        term.reference_acceleration(v, {"a_x:h": c})


def test_node_features_of_height_and_the_other_objects():
    x = torch.tensor([[1.0, 2.0, 3.0]])
    v = torch.tensor([[0.5, 0.0, -1.0]])
    others_p = torch.tensor([[[2.0, 2.0, 3.0], [1.0, 4.0, 3.0]]])
    others_v = torch.zeros(1, 2, 3)
    f = node_features(
        x, v, torch.tensor([0.25]), up=(0.0, 0.0, 1.0), ground_height=0.5,
        others_position=others_p, others_velocity=others_v,
    )  # fmt: skip
    assert float(f["h"][0]) == 2.5 and float(f["t"][0]) == 0.25
    assert f["dp_x"].item() == 1.0 and f["dp_y"].item() == 2.0 and f["dv_z"].item() == 2.0
    a = acceleration({"a_y:dp_y": torch.tensor(3.0), "a_x:1": torch.tensor(-1.0)}, f)
    assert a.tolist() == [[-1.0, 6.0, 0.0]]
