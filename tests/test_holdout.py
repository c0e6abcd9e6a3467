"""Held-out frames in the parameter phase (``identify.holdout_frames``): the phase fits the
observed frames before them, and the global stage's result and the descent's best then compete
on the whole window, so the held-out frames say which one extrapolates.

The toy: one point drifting at a constant speed that E sets (log10(E / 1e4) + 1), observed
while it accelerates; the model cannot follow, as a simulator cannot follow another engine's
scene. Fitted on the first frames the speed comes out lower than the whole window's best."""

from __future__ import annotations

import math
from types import SimpleNamespace

import pytest
import torch

from mosiv_framework.errors import ConfigError
from mosiv_framework.interfaces import Simulator
from mosiv_framework.losses import WeightedSum
from mosiv_framework.pipeline.identify import _choose_on_holdout, identify
from mosiv_framework.pipeline.params import ParameterVector
from mosiv_framework.pipeline.phases import BestIterate, Fit, build_phases
from mosiv_framework.pipeline.rundir import RunDir
from mosiv_framework.registry import get_registry
from mosiv_framework.types import ParticleSet, Trajectory, World

FPS = 24.0
OBSERVED = 8


class Drift(Simulator):
    """One point moving in x at log10(E / 1e4) + 1 m/s."""

    def rollout(self, particles, params, *, world, frames):
        speed = torch.log10(params.objects[1].values["E"] / 1e4) + 1.0
        t = torch.arange(frames + 1, dtype=torch.float32) / world.fps
        step = torch.stack([speed, torch.zeros(()), torch.zeros(())])
        x = particles.positions[None] + t[:, None, None] * step
        return Trajectory(x, particles.object_ids, world.fps)


def _toy(e: float = 1e4):
    world = World((0, 0, 0), (1, 1, 1), gravity=(0, 0, 0), ground_height=None, fps=FPS)
    particles = ParticleSet(
        torch.tensor([[0.2, 0.5, 0.5]]), torch.ones(1), torch.ones(1, dtype=torch.long),
        {1: "elastic"},
    )  # fmt: skip
    t = torch.arange(OBSERVED, dtype=torch.float32) / FPS
    x = 0.2 + 1.0 * t + 6.0 * t * t  # accelerating: no constant speed follows it
    targets = {1: torch.stack([x, torch.full_like(x, 0.5), torch.full_like(x, 0.5)], -1)[:, None]}
    objective = WeightedSum({"chamfer": get_registry().create("loss", "chamfer", {})})
    vector = ParameterVector.create(
        {1: "elastic"}, {1: torch.zeros(3)}, values={1: {"E": e}}, identify=("E",),
        ground_friction=None,
    )  # fmt: skip
    return Fit(Drift(), particles, world, targets, objective), vector


def _e(vector: ParameterVector) -> float:
    return float(vector.physical().objects[1].values["E"].detach())


def _section(**overrides):
    values = dict(
        velocity_iterations=0, param_iterations=30, velocity_lr=0.01, param_lr=0.05,
        horizon_start=2, horizon_full_at=0.3, checkpoint_every=100, resync_every=0,
        resync_iterations=0, global_candidates=0, global_frames=0, global_polish=0,
        holdout_frames=0, intervals=False, seed=0,
    )  # fmt: skip
    return SimpleNamespace(**{**values, **overrides})


def _identify(tmp_path, name: str, **section):
    fit, vector = _toy()
    _, history = identify(
        simulator=fit.simulator, vector=vector, particles=fit.particles, world=fit.world,
        targets=fit.targets, observed_frames=OBSERVED, objective=fit.objective,
        section=_section(**section), run_dir=RunDir(tmp_path / name), config_hash=name,
    )  # fmt: skip
    return fit, vector, history


def test_the_phase_fits_the_frames_before_the_held_out_ones_and_keeps_the_better_one(tmp_path):
    fit, vector, history = _identify(tmp_path, "held", holdout_frames=3)
    horizons = {h["horizon"] for h in history if h.get("phase") == "params" and "horizon" in h}
    assert max(horizons) == OBSERVED - 1 - 3  # the last three observed frames never fitted
    (record,) = [h for h in history if h["phase"] == "holdout"]
    assert set(record["losses"]) == {"descent", "global"} and record["frames"] == OBSERVED - 1
    chosen = record["chosen"]
    assert record["losses"][chosen] == min(record["losses"].values())
    # what is applied is the chosen candidate: its whole-window loss, recomputed
    assert fit.window_loss(vector, OBSERVED - 1) == pytest.approx(record["losses"][chosen])
    # fitted on the early frames the speed is below the whole window's best
    _, whole, plain = _identify(tmp_path, "whole")
    assert not [h for h in plain if h["phase"] == "holdout"]
    assert _e(vector) < _e(whole)


def test_the_candidate_that_fits_the_whole_window_wins_and_a_missing_one_is_skipped():
    fit, vector = _toy(e=1e4)  # speed 1: the early frames' slope
    better = BestIterate.snapshot(vector)
    with torch.no_grad():
        vector.normalized["obj1.E"].fill_(float(vector.normalized["obj1.E"]) - 0.3)
    worse = BestIterate.snapshot(vector)
    history: list[dict] = []
    candidates = {"descent": worse, "global": better, "resumed": None}
    _choose_on_holdout(fit, vector, candidates, OBSERVED - 1, history)
    assert history[-1]["chosen"] == "global" and set(history[-1]["losses"]) == {"descent", "global"}
    assert math.isclose(_e(vector), 1e4, rel_tol=1e-5)


def test_holding_out_every_frame_after_the_start_is_refused():
    with pytest.raises(ConfigError, match=r"holdout_frames=6: .* hold out at most 5"):
        build_phases(_section(holdout_frames=6), observed_frames=OBSERVED, velocity_frames=None)
    phases = build_phases(
        _section(holdout_frames=2), observed_frames=OBSERVED, velocity_frames=None
    )
    assert phases[1].last == OBSERVED - 1 - 2 and phases[0].last == OBSERVED - 1
