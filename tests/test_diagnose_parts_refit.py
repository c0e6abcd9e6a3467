"""Unit tests of the diagnosis's refits: starts, continuing from the best model's state,
fresh identification and diverging refits, on fake runs with known answers (no simulator)."""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import pytest
import torch

from mosiv_framework.diagnose.decide import Evidence

# shared fakes of the diagnosis tests; --import-mode=importlib leaves this folder off sys.path
HERE = Path(__file__).resolve().parent
if str(HERE) not in sys.path:
    sys.path.insert(0, str(HERE))
from diagnose_fakes import (  # noqa: E402
    _diverged,
    _elastic_pair_params,
    _FakeContext,
    _OneByOneLosses,
    windy_block_context,
)


def test_null_refit_starts_from_the_identified_state_too():
    """The null model is refitted from the run's own state as well as from the regression's
    velocity change, so it can never end worse than the run every candidate starts from."""
    from mosiv_framework.diagnose.diagnosis import null_starts

    assert [(t.numel(), dv) for t, dv in null_starts(None)] == [(0, None)]
    change = {1: torch.tensor([0.1, 0.0, 0.0])}
    starts = null_starts((torch.zeros(3), change))
    assert starts[0][1] is None and starts[1][1] is change


def test_refit_ends_a_start_at_a_non_finite_gradient():
    """A NaN gradient (as from a degenerate backward pass) must not enter Adam's state: the
    start stops there and returns its best finite iterate."""
    from mosiv_framework.diagnose.model import RefitOptions, refit
    from mosiv_framework.pipeline.params import ParameterVector

    target = torch.tensor([1.0, 0.0, 0.0])

    class FakeContext:
        calls = 0

        def parameter_vector(self, params=None):
            return ParameterVector.create({1: "elastic"}, {1: torch.zeros(3)}, ground_friction=None)

        def simulate(self, params, *, frames):
            self.calls += 1
            v = params.initial_velocity[1]
            misfit = ((v - target) ** 2).sum()
            if self.calls >= 4:  # forward unchanged, gradient 0 * inf = NaN
                misfit = misfit + 0.0 * torch.sqrt(v.sum() - v.sum().detach())
            return misfit

        def loss(self, traj, frames):
            return traj

        def rollout(self, params, *, frames=None):
            return None

    ctx = FakeContext()
    fit = refit(ctx, None, fit_frames=[1, 2], options=RefitOptions(iterations=10))
    assert len(fit.history) == 4  # three clean steps, then the poisoned pass ends the start
    v = fit.params.initial_velocity[1]
    assert bool(torch.isfinite(v).all())
    assert fit.loss == pytest.approx(min(fit.history)) and fit.loss < float((target**2).sum())


class _ScalarLoss(_OneByOneLosses):
    """For fake contexts whose ``simulate`` returns the fit loss itself (m^2)."""

    def loss(self, traj, frames):
        return traj

    def rollout(self, params, *, frames=None):
        with torch.no_grad():
            return self.simulate(params, frames=frames)


class _QuadraticContext(_ScalarLoss):
    """A run whose only free parameter is object 1's initial velocity, and whose fit loss is
    its squared distance (m^2/s^2) to ``target``."""

    def __init__(self, target):
        self.target = torch.tensor(target)

    def parameter_vector(self, params=None):
        from mosiv_framework.pipeline.params import ParameterVector

        v = torch.zeros(3) if params is None else params.initial_velocity[1]
        return ParameterVector.create({1: "elastic"}, {1: v.clone()}, ground_friction=None)

    def simulate(self, params, *, frames):
        return ((params.initial_velocity[1] - self.target) ** 2).sum()


def test_the_null_continues_from_a_candidate_refit_that_found_better_shared_values():
    """A candidate's refit that moved the shared parameters closer than the null's own refit
    did: the null, refitted again from there, must fit at least as well as those values, so a
    candidate cannot win merely by having been optimised further."""
    from mosiv_framework.diagnose.model import Fit, RefitOptions, converge_null, refit

    ctx = _QuadraticContext([2.0, 0.0, 0.0])
    options = RefitOptions(iterations=3, velocity_lr=0.1)
    null = refit(ctx, None, fit_frames=[1], options=options)  # 3 steps of 0.1 from 0: still far
    assert null.loss > 2.0
    closer = ctx.parameter_vector().physical()
    closer.initial_velocity[1] = torch.tensor([1.8, 0.0, 0.0])
    far = ctx.parameter_vector().physical()
    far.initial_velocity[1] = torch.tensor([-3.0, 0.0, 0.0])
    fits = [
        Fit(name, None, p, torch.zeros(1), 0.0, 1, shared=p)
        for name, p in (("far", far), ("closer", closer))
    ]
    warm = converge_null(ctx, null, fits, fit_frames=[1], options=options)
    assert warm.started_from == "closer" and warm.name == "null"
    assert warm.loss <= 0.2**2 + 1e-6  # no worse than where it started
    assert warm.n_params == null.n_params

    # no candidate found better shared values: the null stays as it was
    assert converge_null(ctx, null, fits[:1], fit_frames=[1], options=options) is null


def test_a_regression_start_holds_its_coefficient_while_the_shared_parameters_settle():
    """The first start that brings a velocity change keeps the wind it was given for
    ``settle`` steps while the velocities move; a start without one, and the later regression
    multiples, move the wind from their first step."""
    from mosiv_framework.diagnose.candidates import build_candidates
    from mosiv_framework.diagnose.model import RefitOptions, refit
    from mosiv_framework.pipeline.params import ParameterVector

    class Context(_ScalarLoss, _FakeContext):
        seen: list = []

        def parameter_vector(self, params=None):
            return ParameterVector.create({1: "elastic"}, {1: torch.zeros(3)}, ground_friction=None)

        def simulate(self, params, *, frames):
            wind = params.terms["wind"]["acceleration"]
            self.seen.append(wind.detach().clone())
            v = params.initial_velocity[1]
            return ((v - 1.0) ** 2).sum() + ((wind - torch.tensor([0.0, 2.0, 0.0])) ** 2).sum()

    ctx = Context(frozenset({"wind"}))
    wind = next(c for c in build_candidates(ctx)[0] if c.name == "wind")
    start = torch.tensor([0.0, 2.5, 0.0])
    dv = {1: torch.full((3,), 0.1)}
    options = RefitOptions(iterations=3, settle=4)

    ctx.seen = []
    fit = refit(ctx, wind, fit_frames=[1], starts=[(start, dv), (0.5 * start, dv)], options=options)
    # the starts descend together, one rollout each per step while both go: the first has
    # 4 settle + 3 joint + 1 scoring steps, the second 3 + 1
    first, second = ctx.seen[0:8:2] + ctx.seen[8:12], ctx.seen[1:8:2]
    assert all(torch.equal(w, start) for w in first[:5])  # the settle steps and the first joint
    assert not torch.equal(first[5], start)
    # ... and one rollout of the best fit
    assert len(ctx.seen) == 8 + 4 + 1 and not torch.equal(second[1], second[0])
    assert torch.equal(second[0], 0.5 * start)
    assert len(fit.starts) == 2

    ctx.seen = []
    refit(ctx, wind, fit_frames=[1], starts=[(start, None)], options=options)
    assert len(ctx.seen) == 4 + 1 and not torch.equal(ctx.seen[1], start)


def test_a_candidate_that_fits_worse_continues_from_the_best_models_state():
    """A candidate contains the null, so a candidate refit fitting worse than the null's is
    under-converged: it restarts at the best model's shared values (here the null's, then
    another candidate's) with its own coefficients (held while those settle) and must end
    below it; a candidate already the best is kept."""
    from mosiv_framework.diagnose.candidates import build_candidates
    from mosiv_framework.diagnose.model import Fit, RefitOptions, converge_candidates, refit
    from mosiv_framework.pipeline.params import ParameterVector

    wind_true, v_true = torch.tensor([0.0, 2.0, 0.0]), torch.ones(3)

    class Context(_ScalarLoss, _FakeContext):
        seen: list = []

        def parameter_vector(self, params=None):
            v = torch.zeros(3) if params is None else params.initial_velocity[1]
            return ParameterVector.create({1: "elastic"}, {1: v.clone()}, ground_friction=None)

        def simulate(self, params, *, frames):
            wind = params.terms.get("wind", {}).get("acceleration", torch.zeros(3))
            self.seen.append((params.initial_velocity[1].detach().clone(), wind.detach().clone()))
            v = params.initial_velocity[1]
            return ((v - v_true) ** 2).sum() + ((wind - wind_true) ** 2).sum()

    ctx = Context(frozenset({"wind"}))
    wind = next(c for c in build_candidates(ctx)[0] if c.name == "wind")
    options = RefitOptions(iterations=3, settle=2, velocity_lr=0.3)
    null = refit(ctx, None, fit_frames=[1], options=RefitOptions(iterations=30, velocity_lr=0.3))
    assert null.loss == pytest.approx(4.0, abs=0.05)  # the velocity is right; no wind
    # a wind refit that read the wind well but left the velocity far off: worse than the null
    stuck = ParameterVector.create(
        {1: "elastic"}, {1: torch.full((3,), -2.0)}, ground_friction=None
    )
    stuck = stuck.physical()
    theta = torch.tensor([0.0, 1.8, 0.0])
    bad = Fit(
        "wind", wind, wind.apply(stuck, theta), theta, 27.04, 4, starts=[([0, 1.8, 0], 27.04)]
    )
    ctx.seen = []
    (continued,) = converge_candidates(ctx, null, [bad], fit_frames=[1], options=options)
    assert continued.started_from == "null" and continued.name == "wind"
    v0, w0 = ctx.seen[0]
    assert torch.allclose(v0, null.params.initial_velocity[1])  # the null's state ...
    assert torch.equal(w0, theta) and torch.equal(ctx.seen[2][1], theta)  # ... wind held, settling
    assert continued.loss < 0.05 < null.loss  # now far below the null, as a nested model must be
    assert len(continued.starts) == 2  # the first refit's start is kept for the interval

    good = Fit("wind", wind, wind.apply(null.params, wind_true), wind_true, 0.01, 4)
    assert converge_candidates(ctx, null, [good], fit_frames=[1], options=options)[0] is good

    # the best model found is another candidate: the laggard continues from its shared values
    leader_shared = ParameterVector.create(
        {1: "elastic"}, {1: torch.full((3,), 0.9)}, ground_friction=None
    ).physical()
    leader = Fit("leader", wind, wind.apply(leader_shared, theta), theta, 0.05, 4)
    leader.shared = leader_shared
    ctx.seen = []
    kept, continued = converge_candidates(ctx, null, [leader, bad], fit_frames=[1], options=options)
    assert kept is leader and continued.started_from == "leader"
    assert torch.allclose(ctx.seen[0][0], leader_shared.initial_velocity[1])
    assert continued.loss < 0.05


def test_reidentification_replays_the_runs_schedule_on_the_fit_frames_only(monkeypatch):
    """Identifying afresh under a hypothesis: first the initial velocity with the wind (it acts
    in free flight) over the fit frames before contact, materials held; then the material with
    the wind over every fit frame, velocity held. Held-out frames are never scored, and the
    result reaches the optimum that a refit from a biased state would have to climb to."""
    from mosiv_framework.diagnose import reidentify as module
    from mosiv_framework.diagnose.candidates import build_candidates
    from mosiv_framework.pipeline.params import ParameterVector

    v_true, wind_true, e_true = torch.tensor([0.5, 0.0, 1.0]), torch.tensor([0.0, 2.0, 0.0]), 4e4

    class Context(_FakeContext):
        calls: list = []

        def simulate(self, params, *, frames):
            return params, frames  # the "trajectory": what the loss needs

        def loss(self, traj, frames):
            params, horizon = traj
            assert max(frames) <= horizon
            v = params.initial_velocity[1]
            wind = params.terms.get("wind", {}).get("acceleration", torch.zeros(3))
            e = params.objects[1].values["E"]
            self.calls.append(
                (list(frames), v.detach().clone(), wind.detach().clone(), float(e.detach()))
            )
            flight = ((v - v_true) ** 2).sum() + 0.1 * ((wind - wind_true) ** 2).sum()
            # the material shows only once the bodies touch (frame 4 on)
            contact = (torch.log(e / e_true) ** 2) * float(max(frames) >= 4)
            return flight + contact

        def rollout(self, params, *, frames=None):
            return None

    def fresh(ctx):
        vector = ParameterVector.create(
            {1: "elastic"}, {1: torch.zeros(3)}, ground_friction=None, identify=("E",)
        )
        return vector, 4  # frames 0-3 are free flight

    monkeypatch.setattr(module, "fresh_vector", fresh)
    ctx = Context(frozenset({"wind"}))
    wind = next(c for c in build_candidates(ctx)[0] if c.name == "wind")
    fit_frames = [1, 2, 5, 6, 8]  # 3, 4 and 7 held out
    options = module.ReidentifyOptions(
        velocity_iterations=80,
        param_iterations=60,
        velocity_lr=0.1,
        param_lr=0.05,
        coefficient_lr=0.2,
    )
    fit = module.reidentify(ctx, wind, fit_frames=fit_frames, options=options)

    assert all(set(frames) <= set(fit_frames) for frames, *_ in ctx.calls)
    flight = [c for c in ctx.calls[: options.velocity_iterations + 1]]
    params = ctx.calls[options.velocity_iterations + 1 :]
    assert all(max(frames) <= 2 for frames, *_ in flight)  # before contact only
    assert len({e for *_, e in flight}) == 1  # the material held while velocities move
    assert not torch.equal(flight[0][2], flight[-1][2])  # the wind moved with them
    assert all(torch.equal(v, params[0][1]) for _, v, *_ in params)  # velocity held after
    assert max(max(frames) for frames, *_ in params) == 8
    assert fit.reidentified and fit.name == "wind"
    assert torch.allclose(fit.theta, wind_true, atol=0.1)
    assert fit.params.objects[1].values["E"] == pytest.approx(e_true, rel=0.1)
    assert fit.loss < 0.01


def test_a_model_keeps_the_better_of_its_refit_and_its_fresh_identification():
    """``_better``: the fresh identification replaces the refit only where it fits the fit
    frames better (keeping both fits' starts for the interval), and a fresh identification
    whose every rollout diverged leaves the refit as it was."""
    from mosiv_framework.diagnose import diagnosis
    from mosiv_framework.diagnose.model import Fit
    from mosiv_framework.errors import SimulationDiverged

    params = _elastic_pair_params()
    refitted = Fit("wind", None, params, torch.zeros(3), 2.0, 4, starts=[([0, 0, 0], 2.0)])

    def fresh(loss):
        starts = [([1, 1, 1], loss)]
        return Fit("wind", None, params, torch.ones(3), loss, 4, starts=starts, reidentified=True)

    kept = diagnosis._better(refitted, fresh(1.0))
    assert kept.reidentified and kept.loss == 1.0
    assert kept.starts == [([0, 0, 0], 2.0), ([1, 1, 1], 1.0)]
    assert diagnosis._better(refitted, fresh(3.0)) is refitted
    diverged = SimulationDiverged(object_id=1, frame=2, substep=3, reason="test", advice="")
    assert diagnosis._better(refitted, diverged) is refitted


def test_the_far_start_is_added_only_when_asked_and_only_without_a_regression():
    from mosiv_framework.diagnose.candidates import Candidate
    from mosiv_framework.diagnose.diagnosis import refit_starts
    from mosiv_framework.diagnose.hypothesise import Screen

    bounce = Candidate(
        name="ground_restitution",
        kind="term",
        coefficient_names=["restitution"],
        units=["1"],
        lower=torch.tensor([0.0]),
        upper=torch.tensor([1.0]),
        step=torch.tensor([0.01]),
        regimes=frozenset({"ground_contact"}),
        description="a bounce",
    )
    contact = Screen(bounce, True, [-1.0], torch.tensor([0.1]), 0.3, 5.0, far=torch.tensor([1.0]))
    thetas = [float(t) for t, _ in refit_starts(contact, 3)]
    assert thetas == pytest.approx([0.1, 0.05, 0.15])
    with_far = refit_starts(contact, 3, far_start=True)
    assert [float(t) for t, _ in with_far] == pytest.approx([0.1, 0.05, 0.15, 1.0])
    assert with_far[-1][1] is None  # the run's initial velocities
    # a body force's regression start already carries its own estimate: no far start
    wind = Screen(
        bounce,
        True,
        [-1.0],
        torch.tensor([0.1]),
        0.3,
        5.0,
        far=torch.tensor([1.0]),
        regression=(torch.tensor([0.4]), {}),
    )
    assert len(refit_starts(wind, 3, far_start=True)) == 3


# --------------------------------------------------------------------------------------------
# diverging predictions


class _PredictingContext(_QuadraticContext):
    """A _QuadraticContext whose rollout over all frames (``frames=None``) diverges where
    ``blows_up(params)``, as a refit that fits the fit frames can still blow up after them."""

    def __init__(self, target, blows_up):
        super().__init__(target)
        self.blows_up, self.asked = blows_up, []

    def rollout(self, params, *, frames=None):
        self.asked.append(frames)
        if frames is None and self.blows_up(params):
            raise _diverged()
        return super().rollout(params, frames=frames)


def test_refit_predicts_with_the_next_best_start_when_the_best_ones_prediction_diverges():
    """The start that fits best (here the one begun at the target) blows up after the fit
    frames: the refit keeps the next-best start, whose prediction succeeds, with every start
    still listed for the interval."""
    from mosiv_framework.diagnose.model import RefitOptions, refit

    ctx = _PredictingContext([1.0, 0.0, 0.0], lambda p: float(p.initial_velocity[1][0]) > 0.5)
    starts = [(torch.zeros(0), None), (torch.zeros(0), {1: torch.tensor([1.0, 0.0, 0.0])})]
    fit = refit(ctx, None, fit_frames=[1, 2], starts=starts, options=RefitOptions(iterations=2))
    assert fit.diverged is None and fit.trajectory is not None
    assert float(fit.params.initial_velocity[1][0]) < 0.5  # the start begun at zero
    losses = sorted(loss for _, loss in fit.starts)
    assert len(losses) == 2 and fit.loss == pytest.approx(losses[1]) and losses[0] < 1e-3
    assert ctx.asked == [None, None]  # the best start's prediction, then the next one's


def test_refit_keeps_a_model_whose_every_prediction_diverges_as_evidence():
    """Every start's prediction diverges: no crash, but the best fit without a trajectory,
    with the simulator's message and its rollout up to the frame before the divergence; a
    fit that predicts replaces it in any later comparison, even at a higher fit loss."""
    from mosiv_framework.diagnose.model import Fit, RefitOptions, refit, replaces

    ctx = _PredictingContext([1.0, 0.0, 0.0], lambda p: True)
    starts = [(torch.zeros(0), None), (torch.zeros(0), {1: torch.tensor([1.0, 0.0, 0.0])})]
    fit = refit(ctx, None, fit_frames=[1, 2], starts=starts, options=RefitOptions(iterations=2))
    assert fit.trajectory is None
    assert "object 2 at frame 18, substep 1" in fit.diverged
    assert fit.loss == pytest.approx(min(loss for _, loss in fit.starts))  # the best start
    assert ctx.asked == [None, None, 17] and fit.reached is not None
    predicts = Fit("null", None, fit.params, torch.zeros(0), 10 * fit.loss + 1.0, fit.n_params)
    assert replaces(predicts, fit) and not replaces(fit, predicts)


def test_a_refit_whose_every_start_diverges_is_rejected_as_evidence_not_raised():
    """Every start of a candidate's refit diverges in its first rollout (a discovered law's did
    on two control scenes and ended the diagnosis): the model is kept at its first start with
    an infinite fit loss, the simulator's place in ``diverged`` and its rollout up to the frame
    before; a refit continued from the best model's state that diverges again leaves it as it
    was; its evidence stays strict JSON and the report gives the reason it was not accepted."""
    from mosiv_framework.diagnose.candidates import build_candidates
    from mosiv_framework.diagnose.model import RefitOptions, converge_candidates, refit
    from mosiv_framework.diagnose.report import _evidence_lines, _evidence_row
    from mosiv_framework.pipeline.params import ParameterVector

    class Context(_ScalarLoss, _FakeContext):
        asked: list = []

        def parameter_vector(self, params=None):
            v = torch.zeros(3) if params is None else params.initial_velocity[1]
            return ParameterVector.create({1: "elastic"}, {1: v.clone()}, ground_friction=None)

        def simulate(self, params, *, frames):
            self.asked.append(("wind" in params.terms, frames))
            if "wind" in params.terms and (frames is None or frames >= 3):
                raise _diverged(frame=3)  # the wind blows the bodies apart in frame 3
            return ((params.initial_velocity[1] - 1.0) ** 2).sum()

    ctx = Context(frozenset({"wind"}))
    wind = next(c for c in build_candidates(ctx)[0] if c.name == "wind")
    options = RefitOptions(iterations=2)
    null = refit(ctx, None, fit_frames=[1, 2, 3], options=options)
    starts = [(torch.tensor([0.0, 2.5, 0.0]), {1: torch.full((3,), 0.1)}), (torch.ones(3), None)]
    ctx.asked = []
    fit = refit(ctx, wind, fit_frames=[1, 2, 3], starts=starts, options=options)
    assert fit.refit_diverged and fit.trajectory is None and fit.shared is None
    assert fit.diverged == (
        "refit diverged at object 2, frame 3, substep 1 (a particle moved too far)"
    )
    assert fit.loss == math.inf and fit.starts == []
    assert fit.theta.tolist() == [0.0, 2.5, 0.0]  # the first start, velocity change and all
    assert torch.allclose(fit.params.initial_velocity[1], torch.full((3,), 0.1))
    assert fit.n_params == null.n_params + 3
    # one rollout per start, then the frames before the divergence
    assert ctx.asked == [(True, 3), (True, 3), (True, 2)] and fit.reached is not None
    assert null.diverged is None and not null.refit_diverged

    assert converge_candidates(ctx, null, [fit], fit_frames=[1, 2, 3], options=options) == [fit]

    e = Evidence("wind", -math.inf, math.inf, math.nan, False, False, fit.loss, 3)
    e.diverged = fit.diverged
    saved = json.loads(json.dumps(e.to_json(), allow_nan=False))
    assert saved["fit_loss_m2"] is None and not saved["accepted"]
    assert "| fail (refit diverged) |" in _evidence_row(saved)
    text = "\n".join(_evidence_lines({"evidence": [saved], "frames": {"fit": [1], "heldout": []}}))
    assert "`wind` was not accepted: refit diverged at object 2, frame 3, substep 1" in text


def test_a_diverged_null_is_continued_from_a_candidate_state_that_predicts():
    """The null fits the fit frames best but its prediction diverged: it is refitted again
    from a candidate's shared state, and that refit, which predicts, replaces it although it
    fits a little worse; a diverged state is never the one others continue from."""
    from mosiv_framework.diagnose.model import Fit, RefitOptions, converge_null, refit

    # a velocity above 0.5 m/s fits best and blows up after the fit frames
    ctx = _PredictingContext([1.0, 0.0, 0.0], lambda p: float(p.initial_velocity[1][0]) > 0.5)
    options = RefitOptions(iterations=2, velocity_lr=0.01)
    start = [(torch.zeros(0), {1: torch.tensor([1.0, 0.0, 0.0])})]
    null = refit(ctx, None, fit_frames=[1], starts=start, options=options)
    assert null.diverged is not None and null.loss < 1e-3
    calm = ctx.parameter_vector().physical()
    calm.initial_velocity[1] = torch.tensor([0.4, 0.0, 0.0])
    candidate = Fit("calm", None, calm, torch.zeros(1), 0.5, 7, shared=calm)
    warm = converge_null(ctx, null, [candidate], fit_frames=[1], options=options)
    assert warm.diverged is None and warm.trajectory is not None
    assert warm.started_from == "calm" and warm.loss > null.loss


@pytest.mark.parametrize(
    ("reidentify", "identified"),
    [("every", [None, "wind", "linear_drag"]), ("null-model", [None])],
)
def test_the_budget_chooses_which_models_are_identified_afresh(monkeypatch, reidentify, identified):
    """``diagnose.reidentify``: "every" identifies the null and every kept candidate afresh,
    "null-model" the null alone; a candidate left out keeps its refit, in its place."""
    from dataclasses import replace
    from types import SimpleNamespace

    from omegaconf import OmegaConf

    from mosiv_framework.diagnose import diagnosis
    from mosiv_framework.diagnose.candidates import build_candidates
    from mosiv_framework.diagnose.hypothesise import Screen
    from mosiv_framework.diagnose.model import Fit
    from mosiv_framework.recipes.schema import IdentifySection

    params = _elastic_pair_params()
    ctx = SimpleNamespace(recipe=OmegaConf.create({"identify": IdentifySection()}))
    names = {c.name: c for c in build_candidates(windy_block_context(3))[0]}
    kept = [
        Screen(names[n], True, [-1.0], torch.tensor([0.1]), 0.3, 5.0)
        for n in ("wind", "linear_drag")
    ]  # fmt: skip
    fits = [
        Fit(n, None, params, torch.zeros(3), 2.0, 4, starts=[]) for n in ("wind", "linear_drag")
    ]
    null = Fit("null", None, params, torch.zeros(3), 2.0, 4, starts=[])
    asked = []

    def fresh_fits(ctx, models, **_):
        asked.extend(None if c is None else c.name for c, _ in models)
        name = lambda c: "null" if c is None else c.name  # noqa: E731
        return [Fit(name(c), None, params, torch.ones(3), 1.0, 4, starts=[], reidentified=True)
                for c, _ in models]  # fmt: skip

    monkeypatch.setattr(diagnosis, "reidentify_together", fresh_fits)
    plan = SimpleNamespace(
        ctx=ctx,
        fit_frames=[1, 2],
        budget=replace(diagnosis.BUDGETS["full"], reidentify=reidentify),
        steps=SimpleNamespace(get_many=lambda names, make: make(names)),
        say=lambda *a, **k: None,
    )
    new_null, new_fits = diagnosis._identify_afresh(plan, null, fits, kept)
    assert asked == identified
    assert new_null.reidentified
    assert [f.name for f in new_fits] == ["wind", "linear_drag"]
    assert [f.reidentified for f in new_fits] == [reidentify == "every"] * 2
