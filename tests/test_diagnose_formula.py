"""The discovered law as a model (diagnose/formula.py): an ``expression`` candidate built from
discovery, refitted through the warp-mpm rollout, checked for consistency across objects and
written as a formula with intervals.

The recovery test: a block thrown without gravity under a known law (a_x = -1.5 v_x,
a_y = 0.8, a_z = -0.5 v_z) is the recording; the same body thrown 0.1 m/s off without the law
is the model (an identification without the law biases the velocities). The residual
accelerations of its centroid are discovered as that law, the velocity change the law implies
is estimated from the centroid residual, and the refit through the simulator (the initial
velocity free too) recovers each coefficient within 3 % and the velocity within 1 %. (Under gravity
the scheme's half-substep lag of the velocity behind the position, g dt / 2, biases a_z's
residual by a smooth 0.03 m/s^2, and along one noise-free path three smooth features fitted
that better than v_z alone.)
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import torch

from mosiv_framework.diagnose.discover import discover
from mosiv_framework.diagnose.formula import (
    TESTS,
    applicable_features,
    expression_candidate,
    expression_starts,
    failed_tests,
    formula_record,
    law_to_test,
    law_velocity_change,
)
from mosiv_framework.diagnose.kinematics import ResidualSamples, residual_samples
from mosiv_framework.diagnose.model import RefitOptions, refit
from mosiv_framework.diagnose.physical import consistency
from mosiv_framework.diagnose.report import _formula_lines, recipe_change
from mosiv_framework.expression import FEATURES, NODE_FEATURES
from mosiv_framework.losses import chamfer_m2
from mosiv_framework.pipeline.params import ParameterVector
from mosiv_framework.testing.shapes import block, default_params
from mosiv_framework.types import World

FPS = 24.0
TRUTH = {"a_x:v_x": -1.5, "a_y:1": 0.8, "a_z:v_z": -0.5}
TRUE_V0 = (2.0, 0.0, 1.0)
#: relative error of each refitted coefficient against the law that made the recording
REFIT_TOL = 0.03


class _Run:
    """The RunContext members a refit reads, on a warp-mpm rollout of one block whose
    initial velocity is the free parameter; the loss is the run's Chamfer over all points."""

    def __init__(self, sim, particles, world, params, targets):
        self.sim, self.particles, self.world = sim, particles, world
        self.params, self.targets = params, targets
        self.object_ids = [1]

    def parameter_vector(self, params=None):
        params = self.params if params is None else params
        values = {k: {n: float(v) for n, v in p.values.items()} for k, p in params.objects.items()}
        return ParameterVector.create(
            {1: "elastic"},
            {1: params.initial_velocity[1].detach().clone()},
            values=values,
            ground_friction=None,
            identify=(),
            terms={n: dict(v) for n, v in params.terms.items()},
        )

    def simulate(self, params, *, frames):
        return self.sim.rollout(self.particles, params, world=self.world, frames=frames)

    def rollout(self, params, *, frames=None):
        with torch.no_grad():
            return self.simulate(params.detached(), frames=frames or len(self.targets) - 1)

    def loss(self, traj, frames):
        return torch.stack([chamfer_m2(traj.positions[t], self.targets[t]) for t in frames]).mean()


@pytest.fixture(scope="module")
def thrown():
    from mosiv_framework.registry import get_registry

    sim = get_registry().create(
        "simulator", "warp-mpm", {"grid": 16, "substeps": 10, "device": "cpu"}
    )
    world = World((0.0, 0.0, 0.0), (1.5, 1.5, 1.5), gravity=(0.0, 0.0, 0.0), fps=FPS)
    p = block((0.2, 0.7, 0.4), (0.3, 0.8, 0.5), spacing=0.025, object_id=1)
    null = default_params(p, velocities={1: (1.9, 0.05, 1.05)})
    truth = default_params(p, velocities={1: TRUE_V0})
    truth.terms["expression"] = {n: torch.tensor(v) for n, v in TRUTH.items()}
    frames = 12
    with torch.no_grad():
        target = sim.rollout(p, truth, world=world, frames=frames)
        model = sim.rollout(p, null, world=world, frames=frames)
    samples = {
        1: residual_samples(target.centroids()[1].numpy(), model.centroids()[1].numpy(), FPS)
    }
    centroids = (target.centroids()[1].double().numpy(), model.centroids()[1].double().numpy())
    return _Run(sim, p, world, null, target.positions), samples, centroids


def test_a_law_made_residual_is_discovered_and_refitted_through_the_simulator(thrown):
    run, samples, (target, model) = thrown
    discovered = discover(samples, up=(0.0, 0.0, 1.0))
    kept = {
        f"a_{axis}:{t['feature']}": t["coefficient"]
        for axis, ax in discovered["axes"].items()
        for t in ax["terms"]
    }
    assert set(kept) == set(TRUTH), discovered["formula"]
    candidate = expression_candidate(discovered, up=(0.0, 0.0, 1.0), ground_height=None)
    assert candidate.coefficient_names == list(kept) and candidate.kind == "expression"
    frames = list(range(1, 12))
    residual = (target - model) - (target[0] - model[0])
    dv = law_velocity_change(
        candidate, {1: target}, {1: residual}, {1: ["free_flight"] * 13}, frames, FPS
    )
    bias = torch.tensor(TRUE_V0) - run.params.initial_velocity[1]
    assert torch.allclose(dv[1], bias, atol=0.01)  # (0.092, -0.048, -0.051) of (0.1, -0.05, -0.05)
    start = expression_starts(candidate, 1, dv)
    start_loss = float(
        run.loss(run.rollout(candidate.apply(run.params, start[0][0]), frames=11), frames)
    )
    fit = refit(
        run,
        candidate,
        fit_frames=frames,
        starts=start,
        options=RefitOptions(iterations=8, polish=8),
    )
    refitted = dict(zip(candidate.coefficient_names, fit.theta.tolist()))
    for name, true in TRUTH.items():
        assert refitted[name] == pytest.approx(true, rel=REFIT_TOL), (name, refitted, kept)
    v0 = fit.params.initial_velocity[1].detach()
    assert torch.allclose(v0, torch.tensor(TRUE_V0), atol=0.01 * 2.0)
    assert fit.loss < start_loss / 10
    # the model applies only the discovered coefficients, and removes them again
    assert set(fit.params.terms["expression"]) == set(TRUTH)
    assert "expression" not in candidate.without(fit.params, fit.theta).terms
    snippet = recipe_change(fit, None)
    assert "expression:" in snippet and "a_x:v_x" in snippet and "identify: true" in snippet


def _samples(law, rng, *, noise=0.0):
    """Free-flight residual samples of three objects under ``law(p, v, t)``."""
    out = {}
    for k in range(3):
        t = np.arange(2, 20) / FPS
        p = rng.uniform(0.2, 0.8, (len(t), 3))
        v = rng.normal(size=(len(t), 3))
        res = np.stack([law(p[i], v[i], t[i]) for i in range(len(t))])
        res = res + noise * rng.standard_normal(res.shape)
        out[k] = ResidualSamples(np.arange(2, 20), t, p, v, res, ["free_flight"] * len(t))
    return out


def _law(**axes):
    discovered = {
        "axes": {
            axis: {
                "terms": [
                    {"feature": f, "coefficient": c, "interval": [c - 0.1, c + 0.1]}
                    for f, c in axes.get(axis, {}).items()
                ]
            }
            for axis in "xyz"
        },
        "formula": "law",
    }
    return discovered


def test_the_law_agrees_across_objects_only_when_they_share_it():
    """The consistency test reads each object's coefficients off its own samples' features."""
    rng = np.random.default_rng(0)
    candidate = expression_candidate(
        _law(x={"v_x": -1.0}, z={"h": -4.0}), up=(0.0, 0.0, 1.0), ground_height=0.0
    )

    def shared(p, v, t):
        return np.array([-1.0 * v[0], 0.0, -4.0 * p[2]])

    result = consistency(candidate, _samples(shared, rng, noise=0.01))
    assert result["objects"] == 3 and result["consistent"] is True
    assert result["pooled"] == pytest.approx([-1.0, -4.0], rel=0.02)
    samples = _samples(shared, rng, noise=0.01)
    samples[2].residual[:, 0] -= 2.0 * samples[2].velocity[:, 0]  # object 2: -3 v_x
    assert consistency(candidate, samples)["consistent"] is False


def test_candidate_bounds_starts_and_formula_record():
    candidate = expression_candidate(
        _law(x={"1": 2.5}, y={"|v|v_y": -0.2}), up=(0.0, 0.0, 1.0), ground_height=None
    )
    assert candidate.coefficient_names == ["a_x:1", "a_y:|v|v_y"]
    assert candidate.units == ["m/s^2", "1/m"]
    assert float(candidate.step[0]) == pytest.approx(0.25)  # a tenth of the coefficient
    starts = expression_starts(candidate, 3)
    assert [s[0].tolist() for s in starts][1] == pytest.approx([1.25, -0.1])
    record = formula_record(candidate, torch.tensor([2.4, -0.21]), [[2.2, 2.6], [-0.3, -0.1]])
    assert record["formula"] == "a_x = 2.4; a_y = -0.21 |v|v_y; a_z = 0"
    assert record["axes"]["y"]["terms"][0]["interval"] == [-0.3, -0.1]
    lines = "\n".join(_formula_lines({"tested": "law", "refitted": record, "accepted": True}))
    assert "accepted" in lines and "`a_y = -0.21 |v|v_y` (|v|v_y: -0.21 [-0.3, -0.1])" in lines
    untested = formula_record(candidate, torch.tensor([2.4, -0.21]), None)
    lines = "\n".join(
        _formula_lines(
            {"tested": "law", "refitted": untested, "accepted": False, "failed": ["held-out"]}
        )
    )
    assert "not accepted (failed: held-out)" in lines and "(1: 2.4 [-])" in lines
    assert "[-]: no interval" in lines
    assert failed_tests(SimpleNamespace(**{f: f != "passes_bic" for f, _ in TESTS})) == [
        "information criterion"
    ]
    assert expression_candidate(_law(x={"contact": 1.0}), up=(0, 0, 1), ground_height=None) is None
    assert expression_candidate(_law(), up=(0, 0, 1), ground_height=None) is None


def _context(terms, contact="multi_field", diagnose=None):
    from omegaconf import OmegaConf

    recipe = OmegaConf.create({"diagnose": diagnose or {"terms": [], "exclude": []}})
    return SimpleNamespace(
        recipe=recipe,
        simulator=SimpleNamespace(
            supported_terms=frozenset(terms), options=SimpleNamespace(contact=contact)
        ),
        simulator_name="sim",
        identified=SimpleNamespace(terms={}),
        world=SimpleNamespace(gravity=(0.0, 0.0, -9.8), ground_height=0.0),
    )


def test_the_law_tested_uses_only_features_the_simulator_applies():
    """A law with the contact indicator, or the other objects' features in single-field
    mode, is discovered again within what the simulator can apply; a simulator without the
    term, or a recipe that excludes it, gets none, with the reason."""
    assert applicable_features(SimpleNamespace(supported_terms={"expression"}), None) == FEATURES
    single = applicable_features(SimpleNamespace(supported_terms={"expression"}), "single_field")
    assert single == NODE_FEATURES
    local_only = SimpleNamespace(supported_terms={"expression"}, expression_features=NODE_FEATURES)
    assert applicable_features(local_only, "multi_field") == NODE_FEATURES  # taichi-mpm's case
    rng = np.random.default_rng(1)
    samples = _samples(lambda p, v, t: np.array([-2.0 * v[0], 0.0, 0.0]), rng)
    with_contact = _law(x={"contact": 1.0})
    law, reason = law_to_test(_context({"expression"}), samples, with_contact)
    assert reason is None and law["axes"]["x"]["terms"][0]["feature"] == "v_x"
    with_dp = _law(x={"dp_x": 1.0})
    single = _context({"expression"}, contact="single_field")
    law, _ = law_to_test(single, samples, with_dp)  # discovered again without dp, dv
    assert {t["feature"] for t in law["axes"]["x"]["terms"]} <= set(NODE_FEATURES)
    assert law_to_test(_context({"expression"}), samples, with_dp)[0] is with_dp
    assert law_to_test(_context({"wind"}), samples, with_contact)[1].endswith("implement it")
    excluded = _context({"expression"}, diagnose={"terms": [], "exclude": ["expression"]})
    assert "diagnose.exclude" in law_to_test(excluded, samples, with_contact)[1]
