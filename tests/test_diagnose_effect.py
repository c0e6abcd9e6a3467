"""A candidate's own effect (``diagnose/effect.py``) and the effect test of the decision step.

- On a free body, a steady extra acceleration a moves every particle by a t^2 / 2 after t
  seconds, whatever the material: the measured displacement matches the time-discrete form of
  that (n substeps of symplectic Euler) to 0.1 %, and the Chamfer of the shifted body is twice
  its square (each point's nearest neighbour in the other cloud is its own image while the
  shift is below half the particle spacing).
- The decision fails a candidate whose effect is below ``min_effect`` resolution floors and
  lets the next one through; a replay applies the same test to the recorded effects, and files
  that ran without it replay without it.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from mosiv_framework.diagnose.decide import DecideOptions, Evidence, apply_effect_test
from mosiv_framework.diagnose.effect import measure_effect, resolved, summarise_effect
from mosiv_framework.diagnose.replay import replay_diagnosis
from mosiv_framework.diagnose.report import MM2
from mosiv_framework.testing.pytest_plugin import require_simulator
from mosiv_framework.testing.shapes import block, default_params
from mosiv_framework.types import World

FPS = 24.0
SUBSTEPS = 20
FRAMES = 4


def test_a_steady_acceleration_moves_a_free_body_by_half_a_t_squared():
    sim = require_simulator("warp-mpm").create(
        "simulator", "warp-mpm", {"grid": 16, "substeps": SUBSTEPS, "device": "cpu"}
    )
    world = World((0.0, 0.0, 0.0), (1.0, 1.0, 1.0), gravity=(0.0, 0.0, 0.0), ground_height=None)
    spacing = 0.025
    particles = block((0.45, 0.45, 0.45), (0.55, 0.55, 0.55), spacing=spacing, object_id=1)
    a = 0.6  # m/s^2 along x: 9.4 mm after 4 frames, under half the spacing
    windy = default_params(particles, terms={"wind": {"acceleration": [a, 0.0, 0.0]}})
    calm = default_params(particles)
    ctx = SimpleNamespace(
        object_ids=[1],
        rollout=lambda p: sim.rollout(particles, p.detached(), world=world, frames=FRAMES),
    )
    fit = SimpleNamespace(params=windy, shared=calm)
    frames = {"fit": [1, 2], "heldout": [3, 4], "observed": FRAMES + 1}
    effect = measure_effect(ctx, fit, frames)

    # symplectic Euler (v += a dt, then x += v dt) over n substeps moves a dt^2 n (n + 1) / 2:
    # a t^2 / 2 with t = n dt, to first order in 1 / n
    dt = 1.0 / (FPS * SUBSTEPS)
    n = SUBSTEPS * np.arange(FRAMES + 1)
    expected = a * dt**2 * n * (n + 1) / 2  # m, per particle
    assert np.allclose(expected[1:], 0.5 * a * (n[1:] * dt) ** 2, rtol=1.0 / SUBSTEPS + 1e-9)
    moved = np.asarray(effect["per_frame"])  # Chamfer, mm^2: 2 d^2 for a shift d
    assert np.allclose(moved, 2 * (expected * 1e3) ** 2, rtol=1e-3, atol=1e-9)
    assert effect["max_displacement_mm"] == pytest.approx(expected[-1] * 1e3, rel=1e-3)
    assert effect["max_displacement_at"]["frame"] == FRAMES
    assert effect["fit"] == pytest.approx(moved[[1, 2]].mean())
    assert effect["heldout"] == pytest.approx(moved[[3, 4]].mean())


def test_summarise_effect_sums_objects_and_reports_the_largest_displacement():
    chamfer = np.array([[0.0, 1e-6, 4e-6, 9e-6], [0.0, 0.0, 1e-6, 1e-6]])
    displacement = np.array([[0.0, 1e-3, 2e-3, 3e-3], [0.0, 0.0, 5e-3, 1e-3]])
    out = summarise_effect(
        {"chamfer": chamfer, "displacement": displacement},
        {"fit": [1, 2], "heldout": [3], "observed": 3},
    )
    assert out["per_frame"] == pytest.approx([0.0, 1.0, 5.0, 10.0])
    assert out["fit"] == pytest.approx(3.0) and out["heldout"] == pytest.approx(10.0)
    # frame 3 is not observed: the largest observed displacement is object 2's at frame 2
    assert out["max_displacement_mm"] == pytest.approx(5.0)
    assert out["max_displacement_at"] == {"object_index": 1, "frame": 2}


def _evidence(name, dbic):
    return Evidence(name, 0.6, 0.05, dbic, True, True, 1e-6, 1)


def test_an_effect_below_the_floor_is_not_named_and_the_next_candidate_is():
    floor = {"fit": 50.0, "heldout": 600.0}
    effects = {"gravity": {"fit": 0.3}, "wind": {"fit": 80.0}}
    ranked = apply_effect_test(
        [_evidence("gravity", -15.0), _evidence("wind", -9.0)],
        effects,
        floor,
        DecideOptions(min_effect=1.0),
    )
    assert [e.name for e in ranked] == ["wind", "gravity"]
    assert ranked[0].accepted and not ranked[1].accepted and not ranked[1].passes_effect
    assert ranked[1].to_json()["effect"] == {"fit": 0.3}
    # a stricter rule rejects both; the test off (0, the default) rejects neither
    strict = apply_effect_test(
        [_evidence("gravity", -15.0), _evidence("wind", -9.0)],
        effects,
        floor,
        DecideOptions(min_effect=2.0),
    )
    assert not any(e.accepted for e in strict)
    off = apply_effect_test(
        [_evidence("gravity", -15.0), _evidence("wind", -9.0)], effects, floor, DecideOptions()
    )
    assert [e.name for e in off if e.accepted] == ["gravity", "wind"]
    # nothing to test against: an unmeasured effect or a missing (diverged) floor passes
    assert resolved(None, floor, factor=1.0) and resolved({"fit": 0.0}, None, factor=1.0)


def _saved_diagnosis(with_rule_key: bool) -> dict:
    """A diagnosis.json as the decision step reads it: two candidates that both win the
    held-out and BIC tests, the first (gravity) with an effect far below the floor."""
    rng = np.random.default_rng(0)
    frames = 12
    base = np.linspace(0.0, 1.0, frames) * 1e-5  # m^2, growing error of the null
    null = np.stack([base, base]) + rng.uniform(0, 1e-8, (2, frames))
    gravity, wind = 0.2 * null, 0.3 * null
    rule = {"bootstrap": 200, "block": 2, "z": 2.0, "min_drop": 0.2, "bic_margin": 0.0}
    rule.update({"seed": 0, "require_nonzero": True})
    if with_rule_key:
        rule["min_effect"] = 1.0
    interval = [[0.1, 0.2]]
    return {
        "where": {"significant": True},
        "frames": {"fit": [1, 2, 3, 5, 6, 7], "heldout": [4, 8, 9, 10, 11], "observed": 8},
        "null_parameters": 10,
        "rule": rule,
        "frame_errors_mm2": {
            name: (table * MM2).tolist()
            for name, table in (("null", null), ("gravity", gravity), ("wind", wind))
        },
        "resolution_floor_mm2": {"fit": 50.0, "heldout": 600.0},
        "evidence": [
            {
                "name": "gravity",
                "new_coefficients": 1,
                "fit_loss_m2": 1e-7,
                "interval": interval,
                "effect": {"fit": 0.3, "max_displacement_mm": 0.5},
            },
            {
                "name": "wind",
                "new_coefficients": 1,
                "fit_loss_m2": 2e-7,
                "interval": interval,
                "effect": {"fit": 90.0, "max_displacement_mm": 12.0},
            },
        ],
        "accepted": {"name": "gravity"},
    }


def test_a_replay_applies_the_effect_test_to_the_recorded_effects():
    ran_with_it = replay_diagnosis(_saved_diagnosis(with_rule_key=True))
    assert ran_with_it["accepted"]["name"] == "wind"
    rows = {e["name"]: e for e in ran_with_it["evidence"]}
    assert not rows["gravity"]["passes_effect"] and rows["wind"]["passes_effect"]
    # a file from before the test replays under the rule it ran with: gravity stays first ...
    old = replay_diagnosis(_saved_diagnosis(with_rule_key=False))
    assert old["accepted"]["name"] == "gravity"
    # ... unless the replay is asked for the test
    asked = replay_diagnosis(_saved_diagnosis(with_rule_key=False), DecideOptions(min_effect=1.0))
    assert asked["accepted"]["name"] == "wind"
