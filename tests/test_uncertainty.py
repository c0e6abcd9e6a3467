"""Per-parameter intervals: the Laplace interval against the analytic one of a quadratic loss,
one-sided and unconstrained cases, coverage marks, and a tiny MPM scene whose identified
stiffness interval holds the truth while a parameter the motion never tests is unconstrained."""

from __future__ import annotations

import math
from types import SimpleNamespace

import pytest
import torch

from mosiv_framework.losses import WeightedSum
from mosiv_framework.pipeline.identify import identify
from mosiv_framework.pipeline.params import ParameterVector, stiffness_ceilings
from mosiv_framework.pipeline.rundir import RunDir
from mosiv_framework.pipeline.uncertainty import (
    Z95,
    attach_intervals,
    box_reach,
    covered,
    laplace_intervals,
    mark_coverage,
)
from mosiv_framework.registry import get_registry
from mosiv_framework.testing.pytest_plugin import require_simulator
from mosiv_framework.types import World

FPS = 24.0


def quadratic(floor: float, hessian, centre):
    """u -> (L, dL/du) of L = floor + (u - centre)^T H (u - centre) / 2."""
    h = torch.tensor(hessian, dtype=torch.float64)
    c = torch.tensor(centre, dtype=torch.float64)

    def loss_grad(u):
        r = u.double() - c
        return float(floor + 0.5 * r @ h @ r), h @ r

    return loss_grad


@pytest.mark.parametrize("u0", [0.5, 0.01, 0.995])  # central and both one-sided stencils
def test_laplace_interval_of_a_quadratic_loss_is_the_analytic_one(u0):
    # L = a + h (u - u0)^2 / 2 averaging n residuals of variance a: the posterior of u has
    # standard deviation sqrt(2 a / (n h)); with a = 1e-4, h = 4, n = 50: 1e-3
    (got,) = laplace_intervals(
        quadratic(1e-4, [[4.0]], [u0]), torch.tensor([u0], dtype=torch.float64), n=50
    )
    half = Z95 * math.sqrt(2 * 1e-4 / (50 * 4.0))
    assert got["kind"] == "two-sided"
    assert got["low"] == pytest.approx(u0 - half, rel=1e-6)
    assert got["high"] == pytest.approx(u0 + half, rel=1e-6)


def test_correlated_parameters_get_their_marginal_interval():
    # two coordinates that trade off: H = [[4, 3], [3, 4]]; the marginal variance of each is
    # (2 a / n) [H^-1]_ii = (2 a / n) 4 / 7, wider than the conditional (2 a / n) / 4
    u0 = [0.4, 0.6]
    found = laplace_intervals(
        quadratic(1e-3, [[4.0, 3.0], [3.0, 4.0]], u0), torch.tensor(u0, dtype=torch.float64), n=20
    )
    for got, centre in zip(found, u0):
        half = Z95 * math.sqrt(2 * 1e-3 / 20 * 4 / 7)
        assert got["kind"] == "two-sided"
        assert got["high"] - centre == pytest.approx(half, rel=1e-6)
        assert centre - got["low"] == pytest.approx(half, rel=1e-6)
    # a perfect trade-off (H singular): neither is pinned down, a third, separate one is
    found = laplace_intervals(
        quadratic(1e-3, [[1.0, 1.0, 0.0], [1.0, 1.0, 0.0], [0.0, 0.0, 4.0]], [0.5] * 3),
        torch.tensor([0.5] * 3, dtype=torch.float64),
        n=20,
    )
    assert [got["kind"] for got in found] == ["unconstrained", "unconstrained", "two-sided"]


def test_a_saddle_direction_widens_each_coordinate_by_its_reach_within_the_box():
    # H = R diag(4, -0.05) R^T, R a rotation by 30 degrees: the loss falls along
    # v = (-sin 30, cos 30) = (-0.5, 0.866). From u0 = (0.4, 0.5) the box lets v be followed
    # for t in [-0.577, 0.577] (coordinate 2 reaches 0 and 1 first), which moves coordinate 1
    # by 0.5 * 0.577 = 0.289 either way; its curved part is the Laplace width of the direction
    # (cos 30, sin 30) with curvature 4: [H^+]_11 = cos^2 30 / 4. Coordinate 2 spans the box.
    c, s = math.cos(math.pi / 6), math.sin(math.pi / 6)
    rotation = torch.tensor([[c, -s], [s, c]], dtype=torch.float64)
    hessian = rotation @ torch.diag(torch.tensor([4.0, -0.05], dtype=torch.float64)) @ rotation.T
    u0 = [0.4, 0.5]
    first, second = laplace_intervals(
        quadratic(1e-3, hessian.tolist(), u0), torch.tensor(u0, dtype=torch.float64), n=20
    )
    reach = 0.5 * (0.5 / c)
    half = Z95 * math.sqrt(2 * 1e-3 / 20 * c**2 / 4)
    assert first["kind"] == "two-sided"
    assert first["low"] == pytest.approx(0.4 - reach - half, rel=1e-6)
    assert first["high"] == pytest.approx(0.4 + reach + half, rel=1e-6)
    assert second["kind"] == "unconstrained"


def test_box_reach_of_flat_directions():
    u0 = torch.tensor([0.2, 0.5, 0.9], dtype=torch.float64)
    # along the first axis alone: from 0.2 down to 0 and up to 1
    down, up = box_reach(u0, torch.tensor([[1.0], [0.0], [0.0]], dtype=torch.float64))
    assert down.tolist() == pytest.approx([0.2, 0.0, 0.0])
    assert up.tolist() == pytest.approx([0.8, 0.0, 0.0])
    # along (1, 0, 1)/sqrt 2 the third coordinate stops the way up after 0.1, the first the
    # way down after 0.2; two directions add their reaches
    v = torch.tensor([[1.0, 0.0], [0.0, 1.0], [1.0, 0.0]], dtype=torch.float64) / torch.tensor(
        [math.sqrt(2), 1.0], dtype=torch.float64
    )
    down, up = box_reach(u0, v)
    assert down.tolist() == pytest.approx([0.2, 0.5, 0.2])
    assert up.tolist() == pytest.approx([0.1, 0.5, 0.1])
    down, up = box_reach(u0, torch.zeros(3, 0, dtype=torch.float64))
    assert down.tolist() == [0.0, 0.0, 0.0] and up.tolist() == [0.0, 0.0, 0.0]


def test_an_interval_past_a_bound_keeps_only_the_side_the_data_support():
    # half-width 1.96 * sqrt(2 * 1e-2 / (10 * 0.5)) = 0.124
    half = Z95 * math.sqrt(2 * 1e-2 / (10 * 0.5))
    top = laplace_intervals(
        quadratic(1e-2, [[0.5]], [0.95]), torch.tensor([0.95], dtype=torch.float64), n=10
    )[0]
    assert top["kind"] == "lower-bound" and top["high"] is None
    assert top["low"] == pytest.approx(0.95 - half, rel=1e-6)
    bottom = laplace_intervals(
        quadratic(1e-2, [[0.5]], [0.05]), torch.tensor([0.05], dtype=torch.float64), n=10
    )[0]
    assert bottom["kind"] == "upper-bound" and bottom["low"] is None
    assert bottom["high"] == pytest.approx(0.05 + half, rel=1e-6)
    wide = laplace_intervals(
        quadratic(1.0, [[0.5]], [0.5]), torch.tensor([0.5], dtype=torch.float64), n=1
    )[0]
    assert wide["kind"] == "unconstrained"  # half-width 3.9: past both bounds


def test_a_flat_loss_is_unconstrained():
    found = laplace_intervals(
        quadratic(3e-5, [[0.0]], [0.4]), torch.tensor([0.4], dtype=torch.float64), n=10
    )
    assert found == [{"low": None, "high": None, "kind": "unconstrained"}]


def test_coverage_marks_in_the_metrics():
    identified = {
        "intervals": {
            "obj1": {
                "E": {"low": 1e4, "high": 2e4, "kind": "two-sided"},
                "nu": {"low": 0.3, "high": None, "kind": "lower-bound"},
                "friction": {"low": None, "high": None, "kind": "unconstrained"},
            }
        }
    }
    errors = {
        "1": {
            "E": {"value": 1.5e4, "true": 2.5e4, "rel_error": 0.4},
            "nu": {"value": 0.35, "true": 0.32, "rel_error": 0.1},
            "friction": {"value": 0.3, "true": 1.9, "rel_error": 5.0},
            "rho": {"value": 900.0, "true": 1000.0, "rel_error": 0.1},
        }
    }
    mark_coverage(errors, identified)
    assert errors["1"]["E"]["covered"] is False
    assert errors["1"]["nu"]["covered"] is True and errors["1"]["friction"]["covered"] is True
    assert "covered" not in errors["1"]["rho"]  # no interval, no mark
    # a stiffness of a second object, identified in the gauge where object 1's density is 900
    # (truth 1000): its interval [1e4, 2e4] is [1.11e4, 2.22e4] in the truth's gauge
    errors["2"] = {
        "E": {"value": 1.5e4, "true": 2.1e4, "rel_error": 0.3, "rel_error_gauge_free": 0.2}
    }
    identified["intervals"]["obj2"] = {"E": {"low": 1e4, "high": 2e4, "kind": "two-sided"}}
    mark_coverage(errors, identified)
    assert errors["2"]["E"]["covered"] is True
    assert covered({"low": 1.0, "high": 2.0}, 2.0) and not covered({"low": 1.0, "high": None}, 0.5)
    out: dict = {}
    attach_intervals([{"phase": "params"}, {"phase": "intervals", "intervals": {"x": 1}}], out)
    assert out == {"intervals": {"x": 1}}


def test_intervals_on_a_tiny_scene_cover_the_truth_and_leave_an_unseen_yield_stress_open(tmp_path):
    """A plasticine block thrown down onto the table, its recorded points jittered by 3 mm:
    identified from E 2x off, the E interval holds the truth; its yield stress, far above
    every stress the impact reaches (the block only bounces elastically), is unconstrained."""
    from mosiv_framework.testing.shapes import block, default_params

    options = {"grid": 16, "substeps": 20, "device": "cpu"}
    sim = require_simulator("warp-mpm").create("simulator", "warp-mpm", options)
    world = World((0, 0, 0), (1, 1, 1), gravity=(0, 0, -9.8), ground_height=0.0, fps=FPS)
    particles = block((0.4, 0.4, 0.08), (0.56, 0.56, 0.24), spacing=0.04, object_id=1)
    particles.materials[1] = "plasticine"
    e_true = 4e4
    params = default_params(particles, velocities={1: (0.0, 0.0, -2.0)})
    params.objects[1].values.update(E=torch.tensor(e_true), yield_stress=torch.tensor(1e6))
    points = sim.rollout(particles, params, world=world, frames=7).object_positions(1).detach()
    noisy = points + 3e-3 * torch.randn(points.shape, generator=torch.Generator().manual_seed(0))
    vector = ParameterVector.create(
        {1: "plasticine"},
        {1: torch.tensor([0.0, 0.0, -2.0])},
        values={1: {"E": 2 * e_true, "yield_stress": 1e5}},
        identify=("E", "yield_stress"),
        ground_friction=None,
        ceilings=stiffness_ceilings({1: "elastic"}, {}, dx=1 / 16, dt=1 / (FPS * 20), cfl=0.5),
    )
    section = SimpleNamespace(
        velocity_iterations=0,
        param_iterations=16,
        velocity_lr=0.01,
        param_lr=0.05,
        horizon_start=2,
        horizon_full_at=0.5,
        checkpoint_every=100,
        resync_every=0,
        resync_iterations=0,
        global_candidates=0,
        intervals=True,
        seed=0,
    )
    _, history = identify(
        simulator=sim,
        particles=particles,
        world=world,
        targets={1: noisy},
        observed_frames=8,
        objective=WeightedSum({"chamfer": get_registry().create("loss", "chamfer", {})}),
        vector=vector,
        section=section,
        run_dir=RunDir(tmp_path),
    )
    intervals = [h for h in history if h["phase"] == "intervals"][-1]["intervals"]
    e = intervals["obj1"]["E"]
    assert e["kind"] == "two-sided" and e["low"] <= e_true <= e["high"], e
    assert e["high"] / e["low"] < 4.0  # and says something: narrower than a factor 4
    assert intervals["obj1"]["yield_stress"]["kind"] == "unconstrained"
