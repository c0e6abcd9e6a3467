"""Out-of-library concealed fields (vortex, attractor) in the ``genesis`` scene source.

The aiming through a position-dependent field is plain numpy and always tested, and so is the
committed recording tests/data/vortex_scene (``python -m mosiv_genesis.tiny_scene OUT
--vortex``): its bodies' measured free-flight accelerations must be the field its
gt/effects.json records, evaluated by the recorded function. The engine tests (marked
``genesis_engine`` and ``slow``, deselected without genesis-world, conftest.py) record such
scenes afresh, with a vortex and with an attractor, and check the same.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from mosiv_genesis import plan as P
from mosiv_genesis.options import GenesisOptions
from mosiv_genesis.source import true_acceleration
from mosiv_genesis.tiny_scene import VORTEX_OPTIONS

from mosiv_framework.conceal import parse_conceal
from mosiv_framework.conceal_fields import field_acceleration, linear_form
from mosiv_framework.diagnose.law_score import law_score
from mosiv_framework.registry import get_registry
from mosiv_framework.scene import read_scene

G = np.array([0.0, 0.0, -9.8])
VORTEX_SCENE = Path(__file__).parent / "data" / "vortex_scene"


def test_options_take_the_out_of_library_fields():
    opts = GenesisOptions(conceal="vortex:strength=-8,center=0.05,0,0;attractor")
    assert opts.conceal == [
        "vortex:strength=-8.0,radial=0.0,center=0.05,0.0,0.0",
        "attractor:strength=3.0,position=0.0,0.0,0.27",
    ]


def test_true_acceleration_adds_the_field_to_gravity_wind_and_drag():
    effects = parse_conceal(
        "vortex:strength=10;wind:acceleration=1,0,0;linear_drag:coefficient=2",
        kinds=("vortex", "wind", "linear_drag"),
    )
    f = true_acceleration(effects, G)
    x, v = np.array([0.1, 0.2, 0.3]), np.array([1.0, -1.0, 0.5])
    # vortex (-10 y, 10 x, 0) = (-2, 1, 0); wind (1, 0, 0); drag -2 v = (-2, 2, -1)
    assert np.allclose(f(x, v, 0.0), [-3.0, 3.0, -9.8 - 1.0])


@pytest.mark.parametrize("spec", ["vortex:strength=12", "attractor:strength=3"])
def test_shooting_reaches_the_target_through_the_field(spec):
    """RK4 flights of the shot velocity land on the target (to 1e-7 m), where the ballistic
    velocity under the start's acceleration misses it by centimetres."""
    f = true_acceleration(parse_conceal(spec, kinds=("vortex", "attractor")), G)
    start, target, t_c = np.array([0.18, -0.05, 0.25]), np.array([0.04, 0.0, 0.27]), 0.25
    v = P.shoot_velocity(start, target, t_c, f)
    assert np.linalg.norm(P.fly(start, v, t_c, f, steps=256) - target) < 1e-6
    naive = P.launch_velocity(start, target, t_c, f(start, np.zeros(3), 0.0))
    assert np.linalg.norm(P.fly(start, naive, t_c, f) - target) > 0.005


def test_fly_is_exact_for_a_constant_acceleration():
    a = np.array([0.5, 0.0, -9.8])
    x = P.fly([0.0, 0.0, 0.3], [1.0, 0.0, 1.0], 0.2, lambda x, v, t: a, steps=4)
    assert np.allclose(x, [0.2 + 0.01, 0.0, 0.3 + 0.2 - 0.196])


# -------------------------------------------- the recorded field against the recorded motion
#: tolerance on each free-flight acceleration sample (m/s^2): relative to the field's magnitude,
#: plus an absolute part. The vortex is linear in position, so the mean of the field over a
#: body's grid nodes equals its mean over the particles (quadratic B-splines reproduce linear
#: functions) and only float32 and the field's change along the path between frames remain:
#: measured 0.0005-0.0044 m/s^2 on 1-2.5 m/s^2. The attractor's unit direction is not linear,
#: so grid and particle means differ: measured 0.02-0.08 m/s^2 on 3 m/s^2.
TOLERANCES = {"vortex": (0.01, 0.01), "attractor": (0.04, 0.05)}


def free_flight_errors(path: Path, last: int) -> list[tuple[float, float]]:
    """(|measured - recorded truth|, |truth|) per body and frame 1..``last`` (m/s^2): the
    centroid's second difference minus the declared gravity against the recorded field's mean
    over the body's particles (at their central-difference velocities)."""
    (truth,) = json.loads((path / "gt" / "effects.json").read_text())["effects"]
    scene = read_scene(path)
    fps, gravity = scene.fps, np.asarray(scene.gravity)
    out = []
    for pts in scene.gt_points().values():
        x = pts.numpy().astype(np.float64)  # [T, N, 3]
        for t in range(1, last + 1):
            measured = (x[t + 1] - 2 * x[t] + x[t - 1]).mean(axis=0) * fps**2 - gravity
            vel = (x[t + 1] - x[t - 1]) * fps / 2
            expected = field_acceleration(truth, x[t], vel, t / fps).mean(axis=0)
            out.append(
                (float(np.linalg.norm(measured - expected)), float(np.linalg.norm(expected)))
            )
    return out


def check_errors(errors, kind: str) -> None:
    rel, tol = TOLERANCES[kind]
    for err, size in errors:
        assert size > 1.0  # the field is there to be measured
        assert err < rel * size + tol, f"{kind}: error {err:.4f} m/s^2 on {size:.3f} m/s^2"


def test_committed_vortex_recording_moves_as_its_recorded_field():
    """Frames 1..4 (contact planned at 6): each body's acceleration is the recorded vortex."""
    (truth,) = json.loads((VORTEX_SCENE / "gt" / "effects.json").read_text())["effects"]
    assert truth["kind"] == "vortex" and truth["library"] is False
    assert truth["function"] == "mosiv_framework.conceal_fields:vortex_acceleration"
    assert truth["linear_form"] == linear_form("vortex", truth["params"])
    errors = free_flight_errors(VORTEX_SCENE, last=4)
    assert len(errors) == 8
    check_errors(errors, "vortex")


def _law(terms_per_axis: dict[str, dict[str, float]]) -> dict:
    """A ``discover`` record with the given {axis: {feature: coefficient}}."""
    return {
        "axes": {
            axis: {"terms": [{"feature": f, "coefficient": c} for f, c in terms.items() if c]}
            for axis, terms in terms_per_axis.items()
        }
    }


def test_law_score_on_the_committed_recording():
    """The vortex's own linear law scores a near-zero error and the right form; a uniform
    wind of the same mean (what a library term could say) the wrong form and a large error."""
    effects = json.loads((VORTEX_SCENE / "gt" / "effects.json").read_text())["effects"]
    form = effects[0]["linear_form"]
    right = law_score(_law(form), effects, VORTEX_SCENE)
    assert right["form_correct"] is True and right["law_error"] < 1e-6
    assert right["law_samples"] == 2 * (VORTEX_OPTIONS["observed_frames"] - 2)
    wrong = law_score(_law({"x": {"1": 0.2}, "y": {"1": 0.3}, "z": {}}), effects, VORTEX_SCENE)
    assert wrong["form_correct"] is False and wrong["law_error"] > 0.5
    assert law_score(None, effects, VORTEX_SCENE) == {"law_error": None, "form_correct": False}
    assert law_score(None, [], VORTEX_SCENE) is None


# ------------------------------------------------------------ generation (needs Genesis)
@pytest.mark.genesis_engine
@pytest.mark.slow
@pytest.mark.parametrize("spec", ["vortex:strength=12", "attractor:strength=3"])
def test_genesis_field_acceleration_is_the_recorded_truth(spec, tmp_path):
    """A fresh recording of the committed scene's settings with each field: accelerations as
    recorded, and the launch aimed through the field still brings the bodies together."""
    from scipy.spatial import cKDTree

    options = {**VORTEX_OPTIONS, "conceal": spec}
    path = get_registry().create("scene_source", "genesis", options).generate(tmp_path / "s")
    kind = spec.split(":")[0]
    (truth,) = json.loads((path / "gt" / "effects.json").read_text())["effects"]
    assert truth == parse_conceal(spec, kinds=(kind,))[0].to_json()
    check_errors(free_flight_errors(path, last=4), kind)
    x = {k: p.numpy() for k, p in read_scene(path).gt_points().items()}
    gaps = [cKDTree(x[1][t]).query(x[2][t])[0].min() for t in (0, options["collision_frame"])]
    assert gaps[0] > 0.2 and gaps[1] < 0.05, f"closest particles {gaps} m at frames 0 and 6"
