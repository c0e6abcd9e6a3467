"""The parameter intervals of a finished run computed again, without identifying again.

``mosiv intervals RUN``: after the interval code changed, or to switch between the Laplace and
the sandwich interval (``--method``), a run's intervals are made anew around the parameters it
identified. The identified values are put into the vector identification itself used (its
start, ``pipeline.start_vector``: the same bounds and stiffness ceilings, so the same
normalised coordinates), the probes of ``uncertainty.interval_record`` run around them with the
run's simulator, contact and objective, and the new record is appended to
``identify/history.json`` (earlier records stay; the last one counts), copied into
``identified.json`` and into ``metrics.json``'s ``params``, whose ``covered`` marks are made
again. The run's other files are left as they are.
"""

from __future__ import annotations

from pathlib import Path

import torch
from omegaconf import OmegaConf

from mosiv_framework.pipeline import formats
from mosiv_framework.pipeline.identification import stage_objective, start_vector
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
    """The run's identified parameters as the leaves of the vector identification started from
    (its bounds and ceilings), velocities included."""
    sim_options = OmegaConf.to_container(ctx.recipe.simulator, resolve=True)
    families = {k: p.family for k, p in ctx.identified.objects.items()}
    vector, _ = start_vector(ctx.recipe, ctx.scene, families, ctx.targets, sim_options)
    params = ctx.identified
    with torch.no_grad():
        for k, v in vector.velocity.items():
            v.copy_(params.initial_velocity[k].to(v))
        for key, u in vector.normalized.items():
            value = _identified_value(params, key)
            if value is not None:
                spec = vector.specs[key]
                u.copy_(spec.to_normalized(value.double()).clamp(0.0, 1.0).to(u))
    return vector


def _identified_value(params, key: str) -> torch.Tensor | None:
    """The identified value of a leaf key (``objK.NAME``, ``ground_friction`` or
    ``term.TERM.NAME``), None where the run has none."""
    if key == "ground_friction":
        return torch.as_tensor(float(params.ground_friction))
    if key.startswith("term."):
        _, term, name = key.split(".", 2)
        value = params.terms.get(term, {}).get(name)
        return None if value is None else torch.as_tensor(value)
    owner, name = key.split(".", 1)
    value = params.objects[int(owner[3:])].values.get(name)
    return None if value is None else torch.as_tensor(float(value))


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
