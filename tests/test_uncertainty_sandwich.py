"""The sandwich intervals (``identify.interval_method: sandwich``) against analytic answers.

A straight line fitted to data from a parabola with noise that grows towards the ends is the
textbook misspecified least-squares problem: the estimate's covariance is the heteroscedasticity-
consistent H^-1 J H^-1, not the likelihood's sigma^2 (X^T X)^-1. The tests check the sandwich
against that formula on one data set, its coverage of the best-fitting line over many data sets
against the nominal 95 % (and the Laplace interval's under-coverage of the slope), the bound
kinds, the Bartlett weights, and that a run's identified.json carries the chosen method's
intervals.
"""

from __future__ import annotations

import json
import math

import pytest
import torch
from omegaconf import OmegaConf
from scipy.stats import t as student_t

from mosiv_framework.interfaces import Simulator
from mosiv_framework.pipeline import run_pipeline
from mosiv_framework.pipeline.formats import read_history
from mosiv_framework.pipeline.sandwich import hac_meat, newey_west_lag
from mosiv_framework.pipeline.uncertainty import (
    Z95,
    covered,
    interval_estimates,
    probe,
    sandwich_intervals,
)
from mosiv_framework.recipes import validate_recipe
from mosiv_framework.registry import Component, Registry, hookimpl, manager
from mosiv_framework.types import Trajectory

#: the line's coefficients are theta = SCALE (u - centre) in the optimiser's coordinates u
SCALE = 2.0


def line_fit(seed: int, *, n: int = 200, centre=(0.5, 0.5)):
    """(loss_grad, u0, x, residuals) of the least-squares line a + b x through y = x^2 +
    1.5 x^4 e (x uniform on [-1, 1], e standard normal): each point is a block whose share is
    its squared residual over n; u0 is the exact minimiser."""
    g = torch.Generator().manual_seed(seed)
    x = 2 * torch.rand(n, generator=g, dtype=torch.float64) - 1
    y = x**2 + 1.5 * x**4 * torch.randn(n, generator=g, dtype=torch.float64)
    design = torch.stack([torch.ones(n, dtype=torch.float64), x], dim=1)
    c = torch.tensor(centre, dtype=torch.float64)

    def loss_grad(u):
        r = y - design @ (SCALE * (u - c))
        return float((r**2).mean()), -2 * SCALE * (design.T @ r) / n, r**2 / n

    theta = torch.linalg.lstsq(design, y[:, None]).solution[:, 0]
    return loss_grad, theta / SCALE + c, design, y - design @ theta


@pytest.mark.parametrize("slope_at", [None, 0.99])  # central; the slope's one-sided stencil
def test_the_sandwich_of_a_line_fit_is_the_analytic_one(slope_at):
    loss_grad, u0, design, r = line_fit(1, n=60)
    if slope_at is not None:  # the same fit with the slope's coordinate shifted near 1
        loss_grad, u0, design, r = line_fit(1, n=60, centre=(0.5, 0.5 + slope_at - float(u0[1])))
        assert float(u0[1]) + 0.02 > 1.0
    n = len(r)
    bread = torch.linalg.inv(design.T @ design)
    meat = (design * r[:, None] ** 2).T @ design * n / (n - 1)
    robust = torch.diagonal(bread @ meat @ bread).sqrt() / SCALE * student_t.ppf(0.975, n - 1)
    laplace = torch.diagonal(bread * (r**2).mean()).sqrt() / SCALE * Z95
    found = sandwich_intervals(loss_grad, u0, n=n, lag=0)
    for i, got in enumerate(found):
        half = max(float(robust[i]), float(laplace[i]))
        assert got["low"] == pytest.approx(float(u0[i]) - half, rel=1e-6, abs=1e-9)
        if got["kind"] == "two-sided":
            assert got["high"] == pytest.approx(float(u0[i]) + half, rel=1e-6)
        else:  # the slope within a step of its bound runs past it
            assert got["kind"] == "lower-bound" and got["high"] is None
    assert float(robust[1]) > 1.2 * float(laplace[1])  # the case the sandwich is for


def test_sandwich_covers_the_best_line_at_the_nominal_rate_where_laplace_does_not():
    """1,000 data sets (the binomial standard error of a 95 % coverage is 0.7 %): the best
    line in the population is a = 1/3, b = 0 (x symmetric about 0). The noise is largest where
    x is, so the slope varies more than sigma^2 (X^T X)^-1 says: the Laplace interval holds it
    about 83 % of the time, the sandwich (default Bartlett lag) within 2.5 points of 95 %."""
    truth = torch.tensor([1.0 / 3.0, 0.0], dtype=torch.float64) / SCALE + 0.5
    hits = {"laplace": [0, 0], "sandwich": [0, 0]}
    runs = 1000
    for seed in range(runs):
        loss_grad, u0, _, r = line_fit(seed)
        found = interval_estimates(probe(loss_grad, u0, blocks=True), u0, n=len(r))
        for method, counts in hits.items():
            for i in range(2):
                counts[i] += covered(found[method][i], float(truth[i]))
    laplace = [c / runs for c in hits["laplace"]]
    sandwich = [c / runs for c in hits["sandwich"]]
    assert abs(sandwich[0] - 0.95) < 0.025 and abs(sandwich[1] - 0.95) < 0.025, sandwich
    assert laplace[1] < 0.88, laplace  # the slope's Laplace interval is too narrow
    assert abs(laplace[0] - 0.95) < 0.025, laplace  # the intercept's is not


def blocks_of_quadratics(weights, centres, floor: float = 0.0):
    """L(u) = sum_b w_b (u - c_b)^2 / 2 + floor in one coordinate, one block per b (the floor
    shared out evenly): the minimiser is u0 = sum w c / sum w, H = sum w, and block b's score
    at u0 is w_b (u0 - c_b). Returns (loss_grad, u0, the sandwich half-width at lag 0)."""
    w = torch.tensor(weights, dtype=torch.float64)
    c = torch.tensor(centres, dtype=torch.float64)

    def loss_grad(u):
        shares = 0.5 * w * (u[0] - c) ** 2 + floor / len(w)
        return float(shares.sum()), (w * (u[0] - c)).sum().reshape(1), shares

    u0 = (w * c).sum() / w.sum()
    scores = w * (u0 - c)
    half = math.sqrt(scores.var().item() * len(w)) / w.sum().item()  # lag 0: sum (s - mean)^2
    return loss_grad, u0.reshape(1), half * student_t.ppf(0.975, len(w) - 1)


def test_the_bound_kinds_follow_the_sandwich_width():
    # blocks that disagree about where the optimum lies, near the top of the range: the
    # Laplace width from n = 1000 residuals is small, the sandwich runs past 1
    loss_grad, u0, half = blocks_of_quadratics([1.0, 2.0, 1.0, 3.0], [0.85, 1.0, 0.95, 1.05])
    laplace = Z95 * math.sqrt(2 * loss_grad(u0)[0] / (1000 * 7.0))
    assert float(u0) + half > 1.0 and float(u0) - half > 0.0 and half > 3 * laplace
    (got,) = sandwich_intervals(loss_grad, u0, n=1000, lag=0)
    assert got["kind"] == "lower-bound" and got["high"] is None
    assert got["low"] == pytest.approx(float(u0) - half, rel=1e-6)
    # blocks that agree (a misfit they all share): the sandwich alone would have no width,
    # the Laplace width is the floor
    loss_grad, u0, half = blocks_of_quadratics([1.0, 2.0, 1.0], [0.4, 0.4, 0.4], floor=1e-3)
    assert half == 0.0
    (got,) = sandwich_intervals(loss_grad, u0, n=10, lag=0)
    laplace = Z95 * math.sqrt(2 * 1e-3 / (10 * 4.0))
    assert got["kind"] == "two-sided"
    assert got["high"] - 0.4 == pytest.approx(laplace, rel=1e-6)
    assert 0.4 - got["low"] == pytest.approx(laplace, rel=1e-6)


def test_a_flat_or_diverged_parameter_stays_unconstrained():
    flat = lambda u: (1e-3, torch.zeros(1, dtype=torch.float64), torch.full((5,), 2e-4))  # noqa: E731
    assert sandwich_intervals(flat, torch.tensor([0.5]), n=10)[0]["kind"] == "unconstrained"

    def diverged(u):
        if abs(float(u[0]) - 0.5) < 1e-12:
            return 1e-3, torch.zeros(1, dtype=torch.float64), torch.full((5,), 2e-4)
        return math.inf, torch.full((1,), math.nan), torch.full((5,), math.nan)

    assert sandwich_intervals(diverged, torch.tensor([0.5]), n=10)[0]["kind"] == "unconstrained"
    with pytest.raises(ValueError, match="block shares"):
        sandwich_intervals(lambda u: (1.0, u.clone()), torch.tensor([0.5]), n=10)


def test_bartlett_meat_is_the_weighted_sum_of_lagged_outer_products():
    scores = torch.randn(9, 3, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
    c = scores - scores.mean(dim=0)
    expected = torch.zeros(3, 3, dtype=torch.float64)
    for t in range(9):
        for s in range(9):
            weight = max(0.0, 1.0 - abs(t - s) / 3.0)  # lag 2: weights 1, 2/3, 1/3
            expected += weight * torch.outer(c[t], c[s])
    got = hac_meat(scores, 2)
    assert torch.allclose(got, expected * 9 / 8)
    assert float(torch.linalg.eigvalsh(got).min()) >= -1e-12  # positive semi-definite
    assert torch.allclose(hac_meat(scores, 0), c.T @ c * 9 / 8)
    assert [newey_west_lag(t) for t in (3, 15, 36, 100)] == [1, 2, 3, 4]
    with pytest.raises(ValueError, match="at least 2 blocks"):
        hac_meat(scores[:1], 0)


class SinkingBallistic(Simulator):
    """Ballistic flight (exact for the example scene) plus a vertical offset of object 1 that the
    recording does not have: SINK t^3 (an unmodelled force) and STIFF t^2 log(E / E0) (a
    stiffness that matters). E can take up part of the t^3 drift but not all of it, and each
    frame would take it up with a different E: a model that is not the data's."""

    SINK, STIFF, E0 = 0.4, 0.05, 5.0e4

    def __init__(self, **options):
        pass

    def rollout(self, particles, params, *, world, frames):
        t = torch.arange(frames + 1, dtype=torch.float32) / world.fps
        g = torch.tensor(world.gravity, dtype=torch.float32)
        v0 = torch.stack([params.initial_velocity[int(k)] for k in particles.object_ids.tolist()])
        x = particles.positions[None] + t[:, None, None] * v0[None]
        x = x + 0.5 * t[:, None, None] ** 2 * g[None, None]
        one = (particles.object_ids == 1).float()
        stiff = torch.log(params.objects[1]["E"] / self.E0) * one
        dz = self.SINK * t[:, None] ** 3 * one[None] + self.STIFF * t[:, None] ** 2 * stiff[None]
        x = x + torch.nn.functional.pad(dz[..., None], (2, 0))
        return Trajectory(x, particles.object_ids, world.fps)


class SinkingPlugin:
    @hookimpl
    def mosiv_simulators(self, register):
        register(Component("simulator", "sinking", factory=SinkingBallistic))


@pytest.fixture
def registry(monkeypatch):
    reg = Registry().load_entry_points(disabled=["warp-mpm", "taichi-mpm", "gauss"])
    reg.add_plugin(SinkingPlugin(), name="sinking-test")
    monkeypatch.setattr(manager, "_REGISTRY", reg)
    return reg


def sinking_recipe(tmp_path, registry, **identify):
    raw = {
        "scene": {
            "path": str(tmp_path / "scene"),
            "generate": "if-missing",
            "source": {"name": "example", "n_frames": 16, "n_cameras": 2, "size": 24},
        },
        "reconstructor": {"name": "oracle", "max_points": 300},
        "lifter": {"name": "gt-points", "max_particles_per_object": 300},
        "simulator": {"name": "sinking"},
        "losses": {"chamfer": {"weight": 1.0, "max_points": 300}},
        "identify": {
            "velocity_iterations": 0,
            "param_iterations": 15,
            "param_lr": 0.05,
            "horizon_start": 8,
            "identify_ground_friction": False,
            "checkpoint_every": 100,
            **identify,
        },
        "evaluate": {"emd_samples": 64},
        "output": {"dir": str(tmp_path / "run")},
    }
    resolved, problems = validate_recipe(raw, registry)
    assert problems == []
    return OmegaConf.create(resolved)


def test_identified_json_carries_the_intervals_of_the_chosen_method(tmp_path, registry):
    recipe = sinking_recipe(tmp_path, registry, interval_method="sandwich")
    run_pipeline(recipe, run_dir=tmp_path / "run")
    identified = json.loads((tmp_path / "run" / "identified.json").read_text())
    e = identified["intervals"]["obj1"]["E"]
    assert e["method"] == "sandwich" and e["kind"] == "two-sided", e
    (record,) = [
        h
        for h in read_history(tmp_path / "run" / "identify/history.json")
        if h["phase"] == "intervals"
    ]
    assert record["method"] == "sandwich" and record["blocks"] == 7 and record["lag"] == 2
    lap = record["laplace"]["obj1"]["E"]
    assert lap["method"] == "laplace" and lap["kind"] == "two-sided"
    # the frames disagree about E, so the sandwich is wider (in log E) than the Laplace one
    assert math.log(e["high"] / e["low"]) > 1.5 * math.log(lap["high"] / lap["low"])
    # parameters the motion does not depend on are unconstrained under it too
    assert identified["intervals"]["obj2"]["E"]["kind"] == "unconstrained"
    # the default stays the Laplace interval
    recipe = sinking_recipe(tmp_path, registry)
    run_pipeline(recipe, run_dir=tmp_path / "run")  # Stages I and II are resumed
    identified = json.loads((tmp_path / "run" / "identified.json").read_text())
    assert identified["intervals"]["obj1"]["E"]["method"] == "laplace"
