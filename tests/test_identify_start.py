"""Where identification starts and how it gets away from a start far off the truth: the
data-independent centre start, the global Sobol stage, and the parameter phase moving a
stiffness 5x off toward the truth on a tiny MPM scene."""

from __future__ import annotations

import math
from types import SimpleNamespace

import pytest
import torch

from mosiv_framework.errors import SimulationDiverged
from mosiv_framework.interfaces import Simulator
from mosiv_framework.laws.base import ParamSpec
from mosiv_framework.losses import WeightedSum
from mosiv_framework.pipeline.global_search import global_search, sobol_design
from mosiv_framework.pipeline.identify import identify
from mosiv_framework.pipeline.params import ParameterVector, centre_value, stiffness_ceilings
from mosiv_framework.pipeline.phases import Fit
from mosiv_framework.pipeline.rundir import RunDir
from mosiv_framework.registry import get_registry
from mosiv_framework.testing.pytest_plugin import require_simulator
from mosiv_framework.types import ParticleSet, Trajectory, World

FPS = 24.0


def test_centre_start_is_the_middle_of_each_laws_bounds_below_the_ceiling():
    vector = ParameterVector.create(
        {1: "elastic", 2: "plasticine"},
        {1: torch.zeros(3), 2: torch.zeros(3)},
        ceilings={1: {"E": 1e6}, 2: {"E": 2e4}},
    )
    vector.move_to_centre()
    objects = vector.to_json()["objects"]
    assert objects["1"]["params"]["E"] == pytest.approx(1e5, rel=1e-5)  # sqrt(1e3 * 1e7)
    assert objects["2"]["params"]["E"] == pytest.approx(2e4, rel=1e-5)  # the ceiling
    assert objects["2"]["params"]["yield_stress"] == pytest.approx(math.sqrt(10 * 1e6), rel=1e-5)
    assert objects["1"]["params"]["nu"] == pytest.approx(0.225, rel=1e-6)  # linear: midpoint
    assert objects["2"]["params"]["rho"] == pytest.approx(500.0, rel=1e-5)  # sqrt(50 * 5000)
    assert objects["1"]["params"]["rho"] == 1000.0  # the gauge density is not identified
    assert centre_value(ParamSpec("x", "1", 2.0, 8.0, 3.0, log_scale=True)) == pytest.approx(4.0)


def test_sobol_design_puts_one_candidate_in_each_sixteenth_of_every_axis():
    design = sobol_design(16, 3, seed=7)
    assert design.shape == (16, 3)
    for axis in range(3):
        strata = torch.floor(design[:, axis] * 16).long()
        assert sorted(strata.tolist()) == list(range(16))
    assert torch.equal(design, sobol_design(16, 3, seed=7))  # reproducible
    assert not torch.equal(design, sobol_design(16, 3, seed=8))  # scrambled by the seed


class LogStiffnessDrift(Simulator):
    """One point drifting along x at a speed set by log10(E) - 4 (the truth is E = 1e4 Pa);
    stiffnesses above 1e6 Pa 'diverge', as an explicit step past its CFL limit would."""

    def __init__(self):
        self.calls = 0

    def rollout(self, particles, params, *, world, frames):
        self.calls += 1
        e = params.objects[1].values["E"]
        if float(e.detach()) > 1e6:
            raise SimulationDiverged(object_id=1, frame=1, substep=0, reason="too stiff", advice="")
        t = torch.arange(frames + 1, dtype=torch.float32) / world.fps
        speed = (torch.log10(e) - 4.0) * torch.tensor([1.0, 0.0, 0.0])
        x = particles.positions[None] + t[:, None, None] * speed
        return Trajectory(x, particles.object_ids, world.fps)


def _toy(start_e: float):
    world = World((0, 0, 0), (1, 1, 1), gravity=(0, 0, 0), ground_height=None, fps=FPS)
    particles = ParticleSet(
        torch.tensor([[0.5, 0.5, 0.5]]),
        torch.ones(1),
        torch.ones(1, dtype=torch.long),
        {1: "elastic"},
    )
    targets = {1: particles.positions[None].repeat(6, 1, 1)}  # at rest: log10(E) = 4
    objective = WeightedSum({"chamfer": get_registry().create("loss", "chamfer", {})})
    sim = LogStiffnessDrift()
    vector = ParameterVector.create(
        {1: "elastic"},
        {1: torch.zeros(3)},
        values={1: {"E": start_e}},
        identify=("E",),
        ground_friction=None,
    )
    return Fit(sim, particles, world, targets, objective), vector


def test_global_search_lands_within_one_stratum_of_the_truth_and_records_every_candidate():
    fit, vector = _toy(start_e=5e6)
    history: list[dict] = []
    result = global_search(fit, vector, candidates=16, frames=5, seed=0, history=history)
    e = float(vector.physical().objects[1].values["E"].detach())
    # one candidate in each sixteenth of 1e3-1e7 Pa in log space: within 0.25 decades of 1e4
    assert abs(math.log10(e) - 4.0) <= 0.25 and result["best"] >= 0
    assert [h["candidate"] for h in history] == list(range(-1, 16))
    assert fit.simulator.calls == 17
    # the start (5e6) and the candidates above 1e6 Pa diverge: recorded without a loss
    diverged = [h for h in history if h["global_loss"] is None]
    assert history[0]["global_loss"] is None and len(diverged) >= 2
    assert all(h["values"]["objects"]["1"]["params"]["E"] > 1e6 for h in diverged)


def test_global_search_keeps_a_start_no_candidate_beats():
    fit, vector = _toy(start_e=1e4)
    result = global_search(fit, vector, candidates=8, frames=5, seed=0, history=[])
    assert result["best"] == -1
    assert float(vector.physical().objects[1].values["E"].detach()) == pytest.approx(1e4, rel=1e-5)


def _section(**overrides):
    values = dict(
        velocity_iterations=0,
        param_iterations=4,
        velocity_lr=0.01,
        param_lr=0.05,
        horizon_start=2,
        horizon_full_at=0.5,
        checkpoint_every=100,
        resync_every=0,
        resync_iterations=0,
        global_candidates=16,
        global_frames=0,
        intervals=False,
        seed=0,
    )
    return SimpleNamespace(**{**values, **overrides})


def test_global_stage_runs_before_the_parameter_phase_and_is_not_redone_on_resume(tmp_path):
    fit, vector = _toy(start_e=5e6)
    kwargs = dict(
        particles=fit.particles,
        world=fit.world,
        targets=fit.targets,
        observed_frames=6,
        objective=fit.objective,
        section=_section(),
        run_dir=RunDir(tmp_path),
        config_hash="toy",
    )
    _, history = identify(simulator=fit.simulator, vector=vector, **kwargs)
    phases = [h["phase"] for h in history]
    assert phases[:17] == ["global"] * 17 and set(phases[17:]) == {"params"}
    e = float(vector.physical().objects[1].values["E"].detach())
    assert abs(math.log10(e) - 4.0) <= 0.25  # the descent started from the global stage's best
    # a rerun of the same configuration resumes from the checkpoint: no rollout at all
    again = LogStiffnessDrift()
    _, resumed = identify(simulator=again, vector=_toy(5e6)[1], **kwargs)
    assert again.calls == 0 and resumed == history


def _drop_scene(e_true: float):
    """A 4x4x4-particle elastic block thrown down onto the table (warp-mpm, 16 cells, CPU)."""
    from mosiv_framework.testing.shapes import block, default_params

    options = {"grid": 16, "substeps": 20, "device": "cpu"}
    sim = require_simulator("warp-mpm").create("simulator", "warp-mpm", options)
    world = World((0, 0, 0), (1, 1, 1), gravity=(0, 0, -9.8), ground_height=0.0, fps=FPS)
    particles = block((0.4, 0.4, 0.08), (0.56, 0.56, 0.24), spacing=0.04, object_id=1)
    params = default_params(particles, velocities={1: (0.0, 0.0, -2.0)})
    params.objects[1].values["E"] = torch.tensor(e_true)
    traj = sim.rollout(particles, params, world=world, frames=7)
    ceilings = stiffness_ceilings({1: "elastic"}, {}, dx=1 / 16, dt=1 / (FPS * 20), cfl=0.5)
    return sim, world, particles, {1: traj.object_positions(1).detach()}, ceilings


def test_a_stiffness_5x_off_moves_to_the_truth_rather_than_staying_at_its_start(tmp_path):
    # truth 1.5e5 Pa, near the 1.875e5 Pa ceiling; start 3e4 Pa. On the way up Adam's momentum
    # carries E into the ceiling, where it stayed pinned, and the curriculum's best iterates
    # (next to the truth at horizons 4-5) were never compared on the whole window: the phase
    # returned 1.87e5 Pa (25 % off) before; now it returns the best of them
    e_true, e_start = 1.5e5, 3e4
    sim, world, particles, targets, ceilings = _drop_scene(e_true)
    vector = ParameterVector.create(
        {1: "elastic"},
        {1: torch.tensor([0.0, 0.0, -2.0])},
        values={1: {"E": e_start}},
        identify=("E",),
        ground_friction=None,
        ceilings=ceilings,
    )
    objective = WeightedSum({"chamfer": get_registry().create("loss", "chamfer", {})})
    identify(
        simulator=sim,
        particles=particles,
        world=world,
        targets=targets,
        observed_frames=8,
        objective=objective,
        vector=vector,
        section=_section(param_iterations=20, global_candidates=0),
        run_dir=RunDir(tmp_path),
    )
    e = float(vector.physical().objects[1].values["E"].detach())
    start_error, error = abs(e_start - e_true) / e_true, abs(e - e_true) / e_true
    assert e != pytest.approx(e_start) and error <= 0.5 * start_error
    assert error < 0.1, e


def test_no_iterate_passes_the_stability_limit_when_the_poisson_ratio_is_high(tmp_path):
    """The ceilings are set at the default Poisson ratio (0.25). A body identified at its E
    ceiling with nu 0.44 has a P-wave 1.8x faster than the simulator's limit, so the phase
    lowers E to the limit at the start and after every step (ParameterVector.keep_stable):
    every recorded iterate stays inside it."""
    sim, world, particles, targets, ceilings = _drop_scene(1.5e5)
    limit = 0.5 * (1 / 16) * FPS * 20  # stiffness_cfl cells of 1/16 m per substep, m/s
    vector = ParameterVector.create(
        {1: "elastic"},
        {1: torch.tensor([0.0, 0.0, -2.0])},
        values={1: {"E": 1e7, "nu": 0.44}},  # E starts at its ceiling
        identify=("E", "nu"),
        ground_friction=None,
        ceilings=ceilings,
    )
    vector.wave_speed_limit = limit  # given to create, the start would already be held to it
    objective = WeightedSum({"chamfer": get_registry().create("loss", "chamfer", {})})
    _, history = identify(
        simulator=sim,
        particles=particles,
        world=world,
        targets=targets,
        observed_frames=8,
        objective=objective,
        vector=vector,
        section=_section(param_iterations=3, global_candidates=0),
        run_dir=RunDir(tmp_path),
    )
    iterates = [entry["values"]["objects"]["1"]["params"] for entry in history]
    assert len(iterates) == 3
    for p in [*iterates, vector.to_json()["objects"]["1"]["params"]]:
        e, nu, rho = p["E"], p["nu"], p["rho"]
        speed = math.sqrt(e * (1 - nu) / ((1 + nu) * (1 - 2 * nu)) / rho)
        assert speed <= limit * (1 + 1e-4), p


def test_every_point_the_global_stage_scores_is_inside_the_stability_limit():
    """Sobol candidates draw densities down to the law's bound while E's ceiling was set at the
    default density: each candidate is held to the limit before it is scored, and the point
    kept is the one scored (the polish sweep likewise)."""
    from mosiv_framework.pipeline.global_search import coordinate_polish

    limit = 15.0
    vector = ParameterVector.create(
        {1: "elastic", 2: "elastic"},
        {1: torch.zeros(3), 2: torch.zeros(3)},
        values={2: {"E": 1e7}},
        ceilings=stiffness_ceilings(
            {1: "elastic", 2: "elastic"}, {}, dx=1 / 16, dt=1 / (FPS * 20), cfl=0.5
        ),
        ground_friction=None,
    )
    vector.wave_speed_limit = limit
    scored = []

    def speed(params, k):
        p = {n: float(v) for n, v in params.objects[k].values.items()}
        m = p["E"] * (1 - p["nu"]) / ((1 + p["nu"]) * (1 - 2 * p["nu"]))
        return math.sqrt(m / p["rho"])

    def losses(params_list, frames):
        scored.extend(params_list)
        return [-float(p.objects[2].values["E"]) for p in params_list]  # the stiffest wins

    fit = SimpleNamespace(
        window_loss=lambda vec, frames: losses([vec.physical().detached()], frames)[0],
        window_losses=losses,
    )
    global_search(fit, vector, candidates=16, frames=3, seed=0, history=[])
    coordinate_polish(fit, vector, points=6, frames=3, history=[])
    assert len(scored) > 16
    for params in [*scored, vector.physical().detached()]:
        for k in (1, 2):
            assert speed(params, k) <= limit * (1 + 1e-4)
    kept = vector.physical().detached()
    assert -float(kept.objects[2].values["E"]) == min(
        -float(p.objects[2].values["E"]) for p in scored
    )
