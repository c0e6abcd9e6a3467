"""The refit's polishing steps (``RefitOptions.polish``): backtracking from the best point.

Adam's steps are about one learning rate per coordinate whatever the gradient, so a refit begun
closer to the optimum than one step cannot improve on its start; polishing takes back each step
that does not lower the loss and halves the next, so the fit converges to well below the
learning rate, and never ends worse than its best point.
"""

from __future__ import annotations

import pytest
import torch

from mosiv_framework.diagnose.model import RefitOptions, refit
from mosiv_framework.errors import SimulationDiverged
from mosiv_framework.pipeline.params import ParameterVector


class _QuadraticRun:
    """A run whose only free parameter is object 1's initial velocity (from zero) and whose fit
    loss (m^2) is its squared distance to ``target`` (m/s); ``diverge_beyond`` makes rollouts
    of velocities farther than that from zero diverge."""

    def __init__(self, target, diverge_beyond=None):
        self.target = torch.tensor(target)
        self.diverge_beyond = diverge_beyond

    def parameter_vector(self, params=None):
        return ParameterVector.create({1: "elastic"}, {1: torch.zeros(3)}, ground_friction=None)

    def simulate(self, params, *, frames):
        v = params.initial_velocity[1]
        if self.diverge_beyond is not None and float(v.detach().norm()) > self.diverge_beyond:
            raise SimulationDiverged(object_id=1, frame=1, substep=0, reason="", advice="")
        return ((v - self.target) ** 2).sum()

    def loss(self, traj, frames):
        return traj

    def rollout(self, params, *, frames=None):
        with torch.no_grad():
            return self.simulate(params, frames=frames)


def test_a_refit_begun_within_one_step_of_the_optimum_converges_only_when_polished():
    run = _QuadraticRun([0.001, 0.0, 0.0005])  # 1 mm/s off: 20x below one step
    start = float((run.target**2).sum())
    plain = refit(run, None, fit_frames=[1], options=RefitOptions(iterations=3, velocity_lr=0.02))
    assert plain.loss == pytest.approx(start)  # every step overshot: it kept its start
    polished = refit(
        run, None, fit_frames=[1], options=RefitOptions(iterations=3, velocity_lr=0.02, polish=10)
    )
    assert polished.loss < start / 50
    assert torch.allclose(polished.params.initial_velocity[1], run.target, atol=3e-4)
    # the polish passes never leave the best point for a worse one: the best so far only falls
    best = [min(polished.history[: i + 1]) for i in range(len(polished.history))]
    assert polished.loss == best[-1] and len(polished.history) == 3 + 10 + 1


def test_a_polishing_step_that_diverges_is_taken_back():
    run = _QuadraticRun([0.5, 0.0, 0.0], diverge_beyond=0.45)  # the optimum itself diverges
    fit = refit(
        run, None, fit_frames=[1], options=RefitOptions(iterations=2, velocity_lr=0.2, polish=8)
    )
    v = fit.params.initial_velocity[1]
    assert float(v.norm()) <= 0.45 and fit.loss < 0.25  # better than the start, still finite
    assert fit.loss == pytest.approx(float(((v - run.target) ** 2).sum()), rel=1e-5)


def test_polish_must_not_be_negative():
    with pytest.raises(ValueError, match="polish"):
        RefitOptions(polish=-1)
