"""End-to-end pipeline on the analytic example scene with a ballistic reference simulator.

The example scene's spheres fly on exact ballistic arcs, so a rigid ballistic simulator
(x(t) = x0 + v0 t + g t^2 / 2, differentiable in v0) must recover the true initial velocities
and predict the future frames almost exactly. This exercises every stage, the run folder,
resuming and metrics without depending on an MPM backend.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass

import pytest
import torch
from omegaconf import OmegaConf

from mosiv_framework.interfaces import Simulator
from mosiv_framework.pipeline import run_pipeline
from mosiv_framework.pipeline.formats import read_history
from mosiv_framework.recipes import validate_recipe
from mosiv_framework.registry import Component, Registry, hookimpl, manager
from mosiv_framework.types import Trajectory


class Ballistic(Simulator):
    calls = 0

    def __init__(self, **options):
        pass

    def rollout(self, particles, params, *, world, frames):
        Ballistic.calls += 1
        t = torch.arange(frames + 1, dtype=torch.float32) / world.fps
        g = torch.tensor(world.gravity, dtype=torch.float32)
        v0 = torch.stack([params.initial_velocity[int(k)] for k in particles.object_ids.tolist()])
        x = (
            particles.positions[None]
            + t[:, None, None] * v0[None]
            + 0.5 * t[:, None, None] ** 2 * g[None, None]
        )
        return Trajectory(x, particles.object_ids, world.fps)


class BallisticPlugin:
    @hookimpl
    def mosiv_simulators(self, register):
        register(Component("simulator", "ballistic", factory=Ballistic))


@pytest.fixture
def registry(monkeypatch):
    reg = Registry().load_entry_points(disabled=["warp-mpm", "taichi-mpm", "gauss"])
    reg.add_plugin(BallisticPlugin(), name="ballistic-test")
    monkeypatch.setattr(manager, "_REGISTRY", reg)
    return reg


def make_recipe(tmp_path, registry, **identify):
    raw = {
        "scene": {
            "path": str(tmp_path / "scene"),
            "generate": "if-missing",
            "source": {"name": "example", "n_frames": 8, "n_cameras": 2, "size": 24},
        },
        "reconstructor": {"name": "oracle", "max_points": 300},
        "lifter": {"name": "gt-points", "max_particles_per_object": 300},
        "simulator": {"name": "ballistic"},
        "losses": {"chamfer": {"weight": 1.0, "max_points": 300}},
        "identify": {
            "velocity_iterations": 60,
            "param_iterations": 0,
            "velocity_lr": 0.1,
            "horizon_start": 2,
            "checkpoint_every": 20,
            **identify,
        },
        "evaluate": {"emd_samples": 128},
        "output": {"dir": str(tmp_path / "run")},
    }
    resolved, problems = validate_recipe(raw, registry)
    assert problems == []
    return OmegaConf.create(resolved)


def test_pipeline_recovers_ballistic_motion_and_resumes(tmp_path, registry):
    recipe = make_recipe(tmp_path, registry)
    metrics = run_pipeline(recipe, run_dir=tmp_path / "run")
    run = tmp_path / "run"
    for name in (
        "recipe.yaml",
        "reconstruction.pt",
        "particles.pt",
        "identified.json",
        "metrics.json",
        "trajectories.png",
        "identify/loss.png",
        "identify/history.json",
    ):
        assert (run / name).is_file(), name
    on_disk = json.loads((run / "metrics.json").read_text())
    assert on_disk["future"]["cd_mm2"] == pytest.approx(metrics["future"]["cd_mm2"])
    # the true arcs are recovered: sub-millimetre future error, initial velocity within 2%
    assert metrics["future"]["cd_mm2"] < 1.0
    for k, err in metrics["param_error"].items():
        assert err["initial_velocity"]["rel_error"] < 0.02, (k, err)
    history = read_history(run / "identify/history.json")
    horizons = [h["horizon"] for h in history]
    assert horizons[0] == 2 and horizons[-1] == 3 and horizons == sorted(horizons)  # curriculum
    # each stage's time, within the run's whole time
    times = on_disk["stage_times_s"]
    assert set(times) == {"reconstruct", "lift", "identify", "evaluate"}
    assert all(t >= 0.0 for t in times.values()) and times["identify"] > 0.0
    assert sum(times.values()) <= on_disk["time_s"] + 1e-3

    # a rerun with the same recipe resumes every stage, the evaluation too: nothing rolls out
    Ballistic.calls = 0
    again = run_pipeline(recipe, run_dir=run)
    assert Ballistic.calls == 0
    assert again["future"]["cd_mm2"] == pytest.approx(metrics["future"]["cd_mm2"])
    # an evaluation setting changed: only the evaluation rollout runs
    recipe.evaluate.emd_samples = 512
    run_pipeline(recipe, run_dir=run)
    assert Ballistic.calls == 1

    # changing an identification setting recomputes identification, not reconstruction
    before = (run / "reconstruction.pt").stat().st_mtime_ns
    Ballistic.calls = 0
    run_pipeline(make_recipe(tmp_path, registry, velocity_iterations=10), run_dir=run)
    # the starting point's loss, 10 iterations, the evaluation rollout
    assert Ballistic.calls == 12
    assert (run / "reconstruction.pt").stat().st_mtime_ns == before
    # the resumed stages keep the times they took when they ran
    rerun_times = json.loads((run / "metrics.json").read_text())["stage_times_s"]
    assert rerun_times["reconstruct"] == times["reconstruct"]
    assert rerun_times["lift"] == times["lift"]

    # each stage records the peak memory it needed; a run whose first stages ran in another
    # process (resumed, or copied as the benchmarks' baselines do) reports theirs too
    peaks = json.loads((run / "metrics.json").read_text())["stage_peak_memory_gb"]
    assert set(peaks) == {"reconstruct", "lift", "identify"}
    assert all(p > 0.0 for p in peaks.values())
    marker = run / "stages" / "reconstruct.json"
    elsewhere = {**json.loads(marker.read_text()), "peak_memory_gb": 1000.0}
    marker.write_text(json.dumps(elsewhere))  # as if Stage I had run in a 1 TB process
    run_pipeline(make_recipe(tmp_path, registry, velocity_iterations=9), run_dir=run)
    copied = json.loads((run / "metrics.json").read_text())
    assert copied["stage_peak_memory_gb"]["reconstruct"] == 1000.0
    assert copied["peak_memory_gb"] == 1000.0


def test_run_files_carry_their_format_and_older_files_still_resume(tmp_path, registry):
    from mosiv_framework.pipeline import formats

    recipe = make_recipe(tmp_path, registry, velocity_iterations=6)
    run = tmp_path / "run"
    run_pipeline(recipe, run_dir=run)
    expected = {
        "metrics.json": formats.METRICS,
        "identified.json": formats.IDENTIFIED,
        "identify/history.json": formats.HISTORY,
        "stages/reconstruct.json": formats.STAGE,
        "stages/identify.json": formats.STAGE,
        "stages/evaluate.json": formats.STAGE,
    }
    for name, fmt in expected.items():
        assert json.loads((run / name).read_text())["format"] == fmt, name
    assert (run / "recipe.yaml").read_text().splitlines()[0] == f"# {formats.RECIPE}"

    # the layout written before the field existed: no "format", the history a bare list
    for name in expected:
        data = json.loads((run / name).read_text())
        if name == "identify/history.json":
            data = data["entries"]
        else:
            del data["format"]
        (run / name).write_text(json.dumps(data))
    assert read_history(run / "identify/history.json")
    Ballistic.calls = 0
    run_pipeline(recipe, run_dir=run)
    assert Ballistic.calls == 0  # every stage resumed from the older files

    # a layout from a newer MOSIV is refused, naming the file, field, value and what is read
    metrics = json.loads((run / "metrics.json").read_text())
    (run / "metrics.json").write_text(json.dumps({**metrics, "format": "mosiv-metrics/9"}))
    with pytest.raises(formats.FormatError) as err:
        run_pipeline(recipe, run_dir=run)
    message = str(err.value)
    for part in ("metrics.json", "'format'", "'mosiv-metrics/9'", "'mosiv-metrics/1'"):
        assert part in message, (part, message)


def test_interrupted_identification_resumes_from_checkpoint(tmp_path, registry, monkeypatch):
    recipe = make_recipe(tmp_path, registry, velocity_iterations=30, checkpoint_every=10)

    class Interrupt(Exception):
        pass

    original = Ballistic.rollout

    def flaky(self, *args, **kwargs):
        if Ballistic.calls == 25:
            raise Interrupt
        return original(self, *args, **kwargs)

    Ballistic.calls = 0
    monkeypatch.setattr(Ballistic, "rollout", flaky)
    with pytest.raises(Interrupt):
        run_pipeline(recipe, run_dir=tmp_path / "run")
    monkeypatch.setattr(Ballistic, "rollout", original)
    Ballistic.calls = 0
    run_pipeline(recipe, run_dir=tmp_path / "run")
    # checkpoint after iteration 20: 10 more iterations + the evaluation rollout
    assert Ballistic.calls == 11
    history = read_history(tmp_path / "run" / "identify/history.json")
    assert [h["iteration"] for h in history] == list(range(30))


def _diverging_on_calls(calls, *, object_id: int):
    """Ballistic rollouts that raise SimulationDiverged (of ``object_id``) on the listed call
    numbers, as a too-stiff parameter step would."""
    from mosiv_framework.errors import SimulationDiverged

    original = Ballistic.rollout

    def unstable(self, *args, **kwargs):
        if Ballistic.calls in calls:
            Ballistic.calls += 1
            raise SimulationDiverged(
                object_id=object_id, frame=2, substep=3, reason="non-finite", advice=""
            )
        return original(self, *args, **kwargs)

    return unstable


def test_a_diverged_rollout_steps_back_and_continues(tmp_path, registry, monkeypatch):
    # two consecutive blow-ups at iterations 5 and 6 (call 0 evaluates the starting point)
    Ballistic.calls = 0
    monkeypatch.setattr(Ballistic, "rollout", _diverging_on_calls((6, 7), object_id=1))
    metrics = run_pipeline(make_recipe(tmp_path, registry), run_dir=tmp_path / "run")
    history = read_history(tmp_path / "run" / "identify/history.json")
    assert [h["iteration"] for h in history if "diverged" in h] == [5, 6]
    # each consecutive failure steps one accepted iterate further back: to where iteration 4
    # started (logged after iteration 3's step), then to where iteration 3 started
    by_iteration = {h["iteration"]: h for h in history if "diverged" not in h}
    stepped = [h["values"] for h in history if "diverged" in h]
    assert stepped == [by_iteration[3]["values"], by_iteration[2]["values"]]
    assert metrics["future"]["cd_mm2"] < 1.0


def test_a_phase_whose_every_step_back_diverges_stops_at_its_best_iterate(
    tmp_path, registry, monkeypatch
):
    from mosiv_framework.pipeline.identify import MAX_BACKOFFS

    failing = range(11, 11 + MAX_BACKOFFS + 1)  # from iteration 10 on, until the phase gives up
    Ballistic.calls = 0
    monkeypatch.setattr(Ballistic, "rollout", _diverging_on_calls(failing, object_id=2))
    metrics = run_pipeline(make_recipe(tmp_path, registry), run_dir=tmp_path / "run")
    history = read_history(tmp_path / "run" / "identify/history.json")
    assert [h["iteration"] for h in history if "diverged" in h] == list(range(10, 16))
    stopped = [h for h in history if "stopped_early" in h]
    assert [h["iteration"] for h in stopped] == [16] and "object 2" in stopped[0]["stopped_early"]
    assert max(h["iteration"] for h in history) == 16  # the phase ended there, the run did not
    identified = json.loads((tmp_path / "run" / "identified.json").read_text())
    assert [(s["phase"], s["iteration"]) for s in identified["stopped_early"]] == [("velocity", 16)]
    # the run goes on from the best iterate: ten good steps from the ballistic estimate
    losses = [h["loss"] for h in history if "loss" in h]
    assert metrics["observed"]["cd_mm2"] <= 1e6 * min(losses) * 1.01


def test_resync_refits_a_wrong_initial_velocity_during_the_parameter_phase(
    tmp_path, registry, monkeypatch
):
    # the ballistic start is spoiled by 0.3 m/s and the velocity phase is off: only the
    # alternating re-synchronisation inside the parameter phase can correct it
    import mosiv_framework.pipeline.identification as identification

    estimate = identification.initial_velocity_from_points

    def spoiled(*args, **kwargs):
        return {k: v + torch.tensor([0.3, 0.0, 0.0]) for k, v in estimate(*args, **kwargs).items()}

    monkeypatch.setattr(identification, "initial_velocity_from_points", spoiled)
    errors = {}
    for every in (0, 4):
        recipe = make_recipe(
            tmp_path,
            registry,
            velocity_iterations=0,
            param_iterations=12,
            resync_every=every,
            resync_iterations=10,
        )
        run = tmp_path / f"run-{every}"
        metrics = run_pipeline(recipe, run_dir=run)
        errors[every] = max(
            e["initial_velocity"]["rel_error"] for e in metrics["param_error"].values()
        )
        history = read_history(run / "identify/history.json")
        resyncs = [h for h in history if h["phase"] == "resync"]
        assert [h["iteration"] for h in resyncs] == ([4, 8] if every else [])
        for h in resyncs:  # the best iterate is kept: never worse than where it started
            assert h["resync_loss_after"] <= h["resync_loss_before"]
    assert errors[0] > 0.1  # nothing else touches the velocities
    # 20 Adam steps at the velocity rate over a 3-frame horizon: a tenfold reduction
    assert errors[4] < 0.05 and errors[4] < errors[0] / 5, errors


def _with_extra_term(term_of):
    """Ballistic rollouts with ``term_of(params, call)`` (a scalar tensor) added to every
    position: a hook that makes chosen parameters matter, or poisons their gradients."""
    original = Ballistic.rollout

    def rollout(self, particles, params, *, world, frames):
        traj = original(self, particles, params, world=world, frames=frames)
        extra = term_of(params, Ballistic.calls)
        return Trajectory(traj.positions + extra, traj.object_ids, traj.fps)

    return rollout


def test_a_non_finite_gradient_steps_back_like_a_divergence(tmp_path, registry, monkeypatch):
    def poison(params, call):
        # forward 0, but d/dv of 0 * sqrt(v - v) is 0 * inf = NaN: at calls 6 and 7, the rollouts
        # of iterations 4 and 5 (call 1 scores the start)
        v = sum(v.sum() for v in params.initial_velocity.values())
        return 0.0 * torch.sqrt(v - v.detach()) if call in (6, 7) else 0.0

    Ballistic.calls = 0
    monkeypatch.setattr(Ballistic, "rollout", _with_extra_term(poison))
    metrics = run_pipeline(make_recipe(tmp_path, registry), run_dir=tmp_path / "run")
    history = read_history(tmp_path / "run" / "identify/history.json")
    stepped_back = [h for h in history if "diverged" in h]
    assert [h["iteration"] for h in stepped_back] == [4, 5]
    assert all("non-finite gradient of v0.obj" in h["diverged"] for h in stepped_back)
    finite = [
        math.isfinite(x)
        for h in history
        for v in h["values"]["objects"].values()
        for x in v["initial_velocity"]
    ]
    assert all(finite)
    assert metrics["future"]["cd_mm2"] < 1.0


def test_a_parameter_without_gradient_holds_still(tmp_path, registry, monkeypatch):
    # E moves the positions during the first 3 parameter steps (calls 2-4), then stops mattering (as a
    # yield stress does once above every stress reached): it must not coast on Adam's momentum
    def stiffness_matters_early(params, call):
        e = params.objects[1]["E"]
        return (1e-2 if call <= 4 else 0.0) * e / e.detach()

    Ballistic.calls = 0
    monkeypatch.setattr(Ballistic, "rollout", _with_extra_term(stiffness_matters_early))
    # no global stage: its rollouts would take the calls in which E matters
    recipe = make_recipe(
        tmp_path, registry, velocity_iterations=0, param_iterations=12, global_candidates=0
    )
    run_pipeline(recipe, run_dir=tmp_path / "run")
    history = read_history(tmp_path / "run" / "identify/history.json")
    e_values = [h["values"]["objects"]["1"]["params"]["E"] for h in history if "loss" in h]
    assert e_values[0] != e_values[2]  # it did move while it mattered
    assert len(set(e_values[2:])) == 1  # and holds still from then on


def test_the_parameter_curriculum_starts_after_the_free_flight(tmp_path, registry, monkeypatch):
    # the example's spheres never touch; declare contact from frame 3 on (free flight 0..2)
    import mosiv_framework.pipeline.identification as identification

    monkeypatch.setattr(identification, "free_flight_frames", lambda *a, **k: 3)
    recipe = make_recipe(tmp_path, registry, param_iterations=6, horizon_start=1)
    run_pipeline(recipe, run_dir=tmp_path / "run")
    history = read_history(tmp_path / "run" / "identify/history.json")
    velocity = [h["horizon"] for h in history if h["phase"] == "velocity"]
    params = [h["horizon"] for h in history if h["phase"] == "params"]
    assert (min(velocity), max(velocity)) == (1, 2)
    assert min(params) == 3


class CoarseStepBallistic(Ballistic):
    """Ballistic, but a rollout past the observed window diverges below 200 substeps, as a
    fluid hitting the table faster than the recipe's time step resolves would."""

    def __init__(self, *, substeps: int | None = None, **options):
        self.substeps = substeps or 100

    def rollout(self, particles, params, *, world, frames):
        from mosiv_framework.errors import SimulationDiverged

        if frames > 5 and self.substeps < 200:
            raise SimulationDiverged(
                object_id=2, frame=6, substep=40, reason="a particle moved too far", advice=""
            )
        return super().rollout(particles, params, world=world, frames=frames)


def test_an_evaluation_rollout_that_diverges_is_retried_with_more_substeps(tmp_path, registry):
    registry.add_plugin(CoarseStepPlugin(), name="coarse-step-test")
    recipe = make_recipe(tmp_path, registry, velocity_iterations=10)
    recipe.simulator = {"name": "coarse-step", "substeps": 100}
    metrics = run_pipeline(recipe, run_dir=tmp_path / "run")
    note = metrics["evaluation_note"]
    assert "object 2 at frame 6" in note and "200 substeps" in note
    assert metrics["future"]["cd_mm2"] < 1.0  # the retried rollout was scored, every frame

    # without a substeps option there is nothing to refine: the divergence is reported
    recipe.simulator = {"name": "coarse-step"}
    recipe.output.dir = str(tmp_path / "run2")
    with pytest.raises(Exception, match="object 2 at frame 6"):
        run_pipeline(recipe, run_dir=tmp_path / "run2")


@dataclass
class CoarseStepOptions:
    substeps: int | None = None


class CoarseStepPlugin:
    @hookimpl
    def mosiv_simulators(self, register):
        factory = CoarseStepBallistic
        register(Component("simulator", "coarse-step", factory=factory, options=CoarseStepOptions))


def test_the_run_peak_takes_only_stage_peaks_of_the_same_kind(monkeypatch):
    from mosiv_framework.pipeline import memory

    monkeypatch.setattr(memory, "memory_kind", lambda: memory.GPU)
    stages = {
        "reconstruct": {"peak_memory_gb": 9.0, "memory": memory.GPU},
        "lift": {"peak_memory_gb": 50.0, "memory": memory.RSS},  # host memory: not comparable
        "identify": None,  # a marker from before the record
    }
    assert memory.run_peak_gb(4.0, stages) == 9.0
    assert memory.comparable_peaks(stages) == {"reconstruct": 9.0, "lift": None, "identify": None}
    assert memory.run_peak_gb(12.0, stages) == 12.0
    monkeypatch.setattr(memory, "memory_kind", lambda: memory.RSS)
    assert memory.run_peak_gb(4.0, stages) == 50.0
