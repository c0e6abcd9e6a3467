"""A candidate's own effect on the prediction: its refitted model rolled out with and without
the effect, everything else equal.

The evidence tests ask whether a candidate's refit predicts the held-out frames better than the
null's; they do not ask how much the effect itself moves the bodies. On two control scenes of
the full suite a term with a tiny coefficient passed every test: a gravity change of 0.1 % and
a wind of 0.044 m/s^2 (the terms took up an offset of the initial velocities that
identification started from, see ``pipeline.params``). The resolution floor (``floor``) says
how far the same model's prediction moves when its particles are resampled at a fraction of
their spacing; the idea tested here was that an
effect moving the bodies less than that is not one the particle model can resolve.

This module measures the effect in the floor's units (per-frame Chamfer between the two
rollouts, summed over objects, in mm^2) and as the largest RMS particle displacement over the
observed frames (mm), which the report states in words. Measured on the saved suite entries
(benchmarks/term_effect.py), it does not separate the two false discoveries from true effects:
a true restitution moved the bodies less (up to 4 mm) than a false wind (11 mm), so the decision
records it and tests it only when asked (``DecideOptions.min_effect``).
"""

from __future__ import annotations

import numpy as np
import torch

from mosiv_framework.diagnose.context import RunContext
from mosiv_framework.errors import SimulationDiverged
from mosiv_framework.losses import chamfer_m2
from mosiv_framework.types import SimulationParams, Trajectory


def measure_effect(ctx: RunContext, fit, frames: dict) -> dict | None:
    """``summarise_effect`` of a candidate's refit (``model.Fit``): its model against its own
    shared parameters with the effect switched off; None if either rollout diverges."""
    try:
        return summarise_effect(effect_tables(ctx, fit.params, fit.shared), frames)
    except SimulationDiverged:
        return None


def effect_tables(
    ctx: RunContext, with_effect: SimulationParams, without_effect: SimulationParams
) -> dict[str, np.ndarray]:
    """Per object and frame ([K, T]) between the rollouts of ``with_effect`` and
    ``without_effect`` on the run's particles: ``chamfer`` (m^2) and ``displacement``, the RMS
    distance (m) each particle moved between the two."""
    a, b = ctx.rollout(with_effect), ctx.rollout(without_effect)
    return compare_rollouts(a, b, ctx.object_ids)


def compare_rollouts(a: Trajectory, b: Trajectory, object_ids: list[int]) -> dict[str, np.ndarray]:
    """``effect_tables`` of two rollouts of the same particles (same order)."""
    frames = min(a.positions.shape[0], b.positions.shape[0])
    chamfer = np.zeros((len(object_ids), frames))
    displacement = np.zeros((len(object_ids), frames))
    for i, k in enumerate(object_ids):
        pa, pb = a.object_positions(k), b.object_positions(k)
        for t in range(frames):
            chamfer[i, t] = float(chamfer_m2(pa[t], pb[t]))
            gap = (pa[t] - pb[t]).double()
            displacement[i, t] = float(torch.sqrt((gap * gap).sum(dim=1).mean()))
    return {"chamfer": chamfer, "displacement": displacement}


def summarise_effect(tables: dict[str, np.ndarray], frames: dict) -> dict:
    """The effect in the floor's units: per-frame Chamfer summed over objects (mm^2), mean over
    ``frames["fit"]`` and over ``frames["heldout"]``; and the largest RMS displacement of any
    object over the observed frames (mm), with the object and frame where it is reached."""
    per_frame = tables["chamfer"].sum(axis=0) * 1e6  # m^2 -> mm^2
    observed = frames["observed"]
    shown = tables["displacement"][:, :observed]
    i, t = np.unravel_index(int(np.argmax(shown)), shown.shape)
    return {
        "fit": float(per_frame[frames["fit"]].mean()),
        "heldout": float(per_frame[[f for f in frames["heldout"] if f < per_frame.size]].mean()),
        "max_displacement_mm": float(shown[i, t] * 1e3),
        "max_displacement_at": {"object_index": int(i), "frame": int(t)},
        "per_frame": per_frame.tolist(),
    }


def resolved(effect: dict | None, floor: dict | None, *, factor: float) -> bool:
    """Whether an effect moves the fitted frames by at least ``factor`` resolution floors
    (both summaries in mm^2). True where either was not measured (nothing to test against)."""
    if effect is None or floor is None:
        return True
    return effect["fit"] >= factor * floor["fit"]
