"""The parameter intervals of a finished run computed again, without identifying again.

``mosiv intervals RUN``: after the interval code changed, or to switch between the Laplace and
the sandwich interval (``--method``), a run's intervals are made anew around the parameters it
identified. The identified values are put into the vector identification itself used (its
free parameters, bounds and stiffness ceilings, so the same normalised coordinates), the
probes of ``uncertainty.interval_record`` run around them with the run's simulator, contact
and objective, and the new record is appended to
``identify/history.json`` (earlier records stay; the last one counts), copied into
``identified.json`` and into ``metrics.json``'s ``params``, whose ``covered`` marks are made
again. The run's other files are left as they are.
"""

from __future__ import annotations

from pathlib import Path

from omegaconf import OmegaConf

from mosiv_framework.pipeline import formats
from mosiv_framework.pipeline.identification import recipe_ceilings, stage_objective
from mosiv_framework.pipeline.phases import Fit, build_phases
from mosiv_framework.pipeline.uncertainty import attach_intervals, interval_record, mark_coverage


def recompute_intervals(
    run_dir: str | Path,
    *,
    method: str | None = None,
    device: str | None = None,
    scene_path: str | Path | None = None,
) -> dict:
    """New intervals for the finished run in ``run_dir``, written into its files.

    Args:
        run_dir: a folder written by ``mosiv run`` with an identify stage.
        method: ``laplace`` or ``sandwich`` (default: the run's ``identify.interval_method``).
        device: the simulator's device (default: the run's).
        scene_path: where the run's scene is now (default: the recipe's ``scene.path``).

    Returns:
        The new history record (``uncertainty.interval_record``), marked ``recomputed``.
    """
    # a finished run loads as the diagnosis loads it (recipe, scene, particles, targets,
    # identified parameters and the simulator with the contact identification chose)
    from mosiv_framework.diagnose.context import load_run

    overrides = {"device": device} if device else None
    ctx = load_run(run_dir, simulator_overrides=overrides, scene_path=scene_path)
    section = ctx.recipe.identify
    method = method or str(section.get("interval_method", "laplace"))
    vector = identified_vector(ctx)
    on = ctx.device
    fit = Fit(
        ctx.simulator,
        ctx.particles.to(on),
        ctx.world,
        {k: t.to(on) for k, t in ctx.targets.items()},
        stage_objective(ctx.recipe, ctx.scene, ctx.particles),
    )
    phases = build_phases(section, observed_frames=ctx.observed_frames, velocity_frames=None)
    record = interval_record(fit, vector, last=phases[-1].last, method=method)
    record["recomputed"] = True
    _write(ctx.run_dir, record)
    return record


def identified_vector(ctx):
    """The run's identified parameters as the leaves of the vector identification fitted
    (its free parameters, bounds and stiffness ceilings), velocities included."""
    sim_options = OmegaConf.to_container(ctx.recipe.simulator, resolve=True)
    families = {k: p.family for k, p in ctx.identified.objects.items()}
    return ctx.parameter_vector(
        ceilings=recipe_ceilings(ctx.recipe, ctx.scene, families, sim_options)
    )


def _write(rd, record: dict) -> None:
    """The record appended to the history, and the intervals in identified.json and
    metrics.json (coverage marks made again) where those files exist."""
    path = rd.path("identify/history.json")
    history = formats.read_history(path) if path.is_file() else []  # e.g. a library run
    history.append(record)
    rd.save_json("identify/history.json", formats.stamped_entries(formats.HISTORY, history))
    identified = rd.load_json("identified.json")
    attach_intervals(history, identified)
    rd.save_json("identified.json", identified)
    if rd.path("metrics.json").is_file():
        metrics = rd.load_json("metrics.json")
        metrics["params"] = identified
        for errors in (metrics.get("param_error") or {}).values():
            for err in errors.values():
                if isinstance(err, dict):
                    err.pop("covered", None)
        mark_coverage(metrics.get("param_error"), identified)
        rd.save_json("metrics.json", metrics)


__all__ = ["identified_vector", "recompute_intervals"]
