"""Out-of-library concealed fields (mosiv_framework/conceal_fields.py): specs, the recorded
truth and its analytic values, and that no library term carries their names."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mosiv_framework.conceal import CONCEAL_DEFAULTS, parse_conceal
from mosiv_framework.conceal_fields import (
    OUT_OF_LIBRARY_KINDS,
    attractor_acceleration,
    field_acceleration,
    library_conflicts,
    linear_form,
    vortex_acceleration,
)
from mosiv_framework.diagnose.law_score import form_matches
from mosiv_framework.registry import get_registry

FIELDS = ("vortex", "attractor")


def test_specs_parse_only_for_a_source_that_lists_them():
    effects = parse_conceal(
        "vortex:strength=-8,radial=4,center=0.1,0,0;attractor:position=0,0.1,0.3", kinds=FIELDS
    )
    assert effects[0].params == {"strength": -8.0, "radial": 4.0, "center": (0.1, 0.0, 0.0)}
    assert effects[1].params == {"strength": 3.0, "position": (0.0, 0.1, 0.3)}
    assert parse_conceal([e.spec() for e in effects], kinds=FIELDS) == effects
    assert not any(e.in_library for e in effects)
    # a source that does not list them (the default: library kinds only) refuses them by name
    with pytest.raises(ValueError, match="'vortex': an out-of-library field"):
        parse_conceal("vortex")
    with pytest.raises(ValueError, match="must be >= 0"):
        parse_conceal("attractor:strength=-1", kinds=FIELDS)
    with pytest.raises(ValueError, match="3 numbers"):
        parse_conceal("vortex:center=0,0", kinds=FIELDS)


def test_no_library_term_or_candidate_is_named_after_a_field():
    """The library the diagnosis screens: the registered physics terms (every installed
    plugin's) and the built-in candidates; none may be an out-of-library kind."""
    terms = get_registry().names("physics_term")
    assert terms and library_conflicts(terms) == []
    built_in = {"ground_friction", "object_friction", "plasticity", *CONCEAL_DEFAULTS}
    assert library_conflicts(built_in) == []
    assert library_conflicts(["wind", "vortex"]) == ["vortex"]
    assert set(OUT_OF_LIBRARY_KINDS) == set(FIELDS)


def test_vortex_is_tangential_with_magnitude_strength_times_radius():
    # at (0.3, 0.4) from the axis through (0.1, -0.2): r = 0.5 m, tangent (-0.8, 0.6)
    pos = np.array([0.4, 0.2, 0.25])
    a = vortex_acceleration(pos, strength=12.0, center=(0.1, -0.2, 5.0))
    assert np.allclose(a, 12.0 * 0.5 * np.array([-0.8, 0.6, 0.0]))
    assert abs(a @ np.array([0.3, 0.4, 0.0])) < 1e-12  # perpendicular to the radius
    # a radial strength pulls towards the axis: -radial * (dx, dy, 0)
    b = vortex_acceleration(pos, strength=0.0, radial=4.0, center=(0.1, -0.2, 0.0))
    assert np.allclose(b, [-1.2, -1.6, 0.0])
    # batched positions; the field ignores velocity and time
    many = vortex_acceleration(np.stack([pos, pos]), np.ones((2, 3)), 3.0, strength=12.0,
                               center=(0.1, -0.2, 5.0))  # fmt: skip
    assert np.allclose(many, a)


def test_attractor_pulls_with_constant_magnitude_towards_its_point():
    p = np.array([0.0, 0.0, 0.27])
    for pos in ([0.3, 0.0, 0.27], [0.05, -0.1, 0.1], [-0.2, 0.2, 0.5]):
        a = attractor_acceleration(np.array(pos), strength=3.0, position=p)
        d = np.array(pos) - p
        assert np.linalg.norm(a) == pytest.approx(3.0, rel=1e-5)
        assert np.allclose(a / 3.0, -d / np.linalg.norm(d), atol=1e-5)
    # at the point itself the pull vanishes (Genesis' regularised unit vector)
    assert np.allclose(attractor_acceleration(p, strength=3.0, position=p), 0.0)


def test_recorded_truth_evaluates_like_the_functions():
    """gt/effects.json's entry (lists for vectors) gives the same acceleration, and the
    vortex's linear form reproduces it: a_x = -s y + ..., a_y = s x + ..."""
    (vortex,) = parse_conceal("vortex:strength=12,radial=2,center=0.1,-0.2,0", kinds=FIELDS)
    record = vortex.to_json()
    assert record["library"] is False and "strength" in record["formula"]
    rng = np.random.default_rng(0)
    pos = rng.uniform(-0.3, 0.3, size=(5, 3))
    a = field_acceleration(record, pos)
    assert np.allclose(a, vortex_acceleration(pos, **vortex.params))
    form = record["linear_form"]
    for axis, col in (("x", 0), ("y", 1)):
        c = form[axis]
        assert np.allclose(c["1"] + c["x"] * pos[:, 0] + c["y"] * pos[:, 1], a[:, col])
    (attractor,) = parse_conceal("attractor", kinds=FIELDS)
    assert attractor.to_json()["linear_form"] is None and linear_form("attractor", {}) is None
    assert np.allclose(
        field_acceleration(attractor.to_json(), pos),
        attractor_acceleration(pos, **attractor.params),
    )
    with pytest.raises(ValueError, match="no acceleration field for effect kind 'wind'"):
        field_acceleration({"kind": "wind", "params": {}}, pos)


def test_form_matching_compares_the_non_constant_features_per_axis():
    form = linear_form("vortex", {"strength": 12.0, "radial": 0.0, "center": (0.1, 0, 0)})

    def law(x_terms, y_terms, z_terms=()):
        return {
            "axes": {
                axis: {"terms": [{"feature": f, "coefficient": 1.0} for f in terms]}
                for axis, terms in zip("xyz", (x_terms, y_terms, z_terms))
            }
        }

    assert form_matches(law(["y"], ["x", "1"]), form)  # the constant is not part of the form
    assert form_matches(law(["y", "contact"], ["x"]), form)
    assert not form_matches(law(["y", "v_x"], ["x"]), form)
    assert not form_matches(law(["y"], ["x"], ["h"]), form)
    assert not form_matches(law(["1"], ["1"]), form)
    assert math.isclose(form["y"]["1"], -1.2)
