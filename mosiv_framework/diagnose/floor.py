"""The model's resolution floor: how far a prediction moves when the same bodies are sampled
by other particles.

The location's noise floor (``locate.estimate_noise``) measures the targets' jitter, and
the oracle's targets have none, so on a control scene every sub-millimetre mismatch between the
recording's particles and the run's is "significant". A small change of a term can take up
part of that mismatch. On a control scene of the full suite, a gravity change of 0.1 % brought
the held-out error from 3.4 to 1.4 mm^2, passing both evidence tests. No data can credit an effect
smaller than the change its own discretisation makes. This module measures that change: the
run's particles moved by a random fraction of their spacing (a different sampling of the same
shapes, as the recording's generator or a lifter with another seed would give), rolled out
with the same parameters, and compared with the original rollout frame by frame. The report
gives it in excess of frame 0, where it is the resampling offset itself.

It is recorded beside the evidence; the decision uses it only through the own-effect test
(``DecideOptions.min_effect``, off by default, see ``decide`` and docs/DIAGNOSIS.md), which a
``replay`` can apply to saved diagnoses.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import torch

from mosiv_framework.diagnose.context import RunContext
from mosiv_framework.errors import SimulationDiverged
from mosiv_framework.losses import chamfer_m2
from mosiv_framework.types import ParticleSet, SimulationParams

#: how far particles move, as a fraction of their spacing (the offset is up to half of it per
#: axis). Measured on five full-suite entries (benchmarks/resolution_floor.py): at
#: 0.5 the collision after the move went so differently that control-1's floor on the held-out
#: frames was 4,840 mm^2 while its null predicts them to 3.4 mm^2; 0.25 gave 882 mm^2
DEFAULT_FRACTION = 0.25


def resampled(
    particles: ParticleSet, *, fraction: float = DEFAULT_FRACTION, seed: int = 0
) -> ParticleSet:
    """``particles`` each moved by a uniform offset of up to ``fraction`` / 2 of its spacing
    (the cube root of its volume, m) per axis; volumes and ids unchanged."""
    if not 0.0 < fraction <= 1.0:
        raise ValueError(f"resampling fraction={fraction}: must be in (0, 1]")
    generator = torch.Generator().manual_seed(seed)
    n = particles.positions.shape[0]
    spacing = particles.volumes.detach().cpu().float().clamp_min(0.0) ** (1.0 / 3.0)
    offset = (torch.rand(n, 3, generator=generator) - 0.5) * fraction * spacing[:, None]
    positions = particles.positions + offset.to(particles.positions)
    return replace(particles, positions=positions)


def resolution_floor(
    ctx: RunContext, params: SimulationParams, *, fraction: float = DEFAULT_FRACTION, seed: int = 0
) -> np.ndarray | None:
    """[K, T] Chamfer (m^2) per object and frame between the rollout of ``params`` on the run's
    particles and on ``resampled`` ones; None if either rollout diverges (the null's own
    prediction may: ``model.Fit.diverged``)."""
    particles = resampled(ctx.particles_for(params), fraction=fraction, seed=seed)
    try:
        original = ctx.rollout(params)
        with torch.no_grad():
            moved = ctx.simulator.rollout(
                particles, params.detached(), world=ctx.world, frames=ctx.n_frames - 1
            )
    except SimulationDiverged:
        return None
    table = np.zeros((len(ctx.object_ids), ctx.n_frames))
    for i, k in enumerate(ctx.object_ids):
        a, b = original.object_positions(k), moved.object_positions(k).cpu()
        for t in range(ctx.n_frames):
            table[i, t] = float(chamfer_m2(a[t], b[t]))
    return table


def summarise_floor(table: np.ndarray | None, frames: dict, *, fraction: float = DEFAULT_FRACTION):
    """A [K, T] floor (m^2) summed over objects, in mm^2, less its frame-0 value (the static
    offset of the resampling itself; the evidence tests likewise count errors in excess of
    frame 0): means over ``frames["fit"]`` and ``frames["heldout"]``, and the raw per-frame
    sums. None for None (a diverged resampled rollout)."""
    if table is None:
        return None
    per_frame = table.sum(axis=0) * 1e6  # m^2 -> mm^2
    excess = np.clip(per_frame - per_frame[0], 0.0, None)
    return {
        "fraction": fraction,
        "fit": float(excess[frames["fit"]].mean()),
        "heldout": float(excess[frames["heldout"]].mean()),
        "per_frame": per_frame.tolist(),
    }
