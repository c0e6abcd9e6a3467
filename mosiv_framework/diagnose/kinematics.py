"""Residual accelerations of the object centroids: what the identified (or refitted) model
misses, frame by frame, as an acceleration.

The centroid residual r(t) = target centroid - simulated centroid changes by an initial
velocity change as a straight line and by an unmodelled force as its double integral; its
second central difference, the residual acceleration, drops the first and keeps the second. It
is measured at the target's own state (centroid position and central-difference velocity),
where the effect acted. Drag exponents (``equivalence``), consistency across objects
(``physical``) and open-form discovery (``discover``) all regress on these samples.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class ResidualSamples:
    """Residual-acceleration samples of one object at interior frames.

    frames: [M] frame indices; time: [M] s; position, velocity: [M, 3] the target centroid's
    (m, m/s); residual: [M, 3] target minus simulated centroid acceleration (m/s^2); regime:
    the simulated regime of each frame ("" where unknown)."""

    frames: np.ndarray
    time: np.ndarray
    position: np.ndarray
    velocity: np.ndarray
    residual: np.ndarray
    regime: list[str]

    def subset(self, mask: np.ndarray) -> ResidualSamples:
        idx = np.flatnonzero(mask)
        return ResidualSamples(
            self.frames[idx],
            self.time[idx],
            self.position[idx],
            self.velocity[idx],
            self.residual[idx],
            [self.regime[i] for i in idx],
        )

    def __len__(self) -> int:
        return len(self.frames)


def residual_samples(
    target: np.ndarray,
    sim: np.ndarray,
    fps: float,
    *,
    frames: list[int] | None = None,
    regimes: list[str] | None = None,
) -> ResidualSamples:
    """Samples at each interior frame t whose stencil t-1, t, t+1 lies in ``frames`` (all
    frames if None; frame 0 always counts, it is the common start), so that frames held out
    of a fit never enter a regression on it.

    Args:
        target, sim: [T, 3] centroid paths (m) of the recording and of the model.
        fps: frames per second.
        frames: the frames the samples may use.
        regimes: the model's regime per frame.
    """
    target = np.asarray(target, dtype=np.float64)
    sim = np.asarray(sim, dtype=np.float64)
    n = target.shape[0]
    allowed = set(range(n)) if frames is None else {0, *frames}
    ts = np.array([t for t in range(1, n - 1) if {t - 1, t, t + 1} <= allowed], dtype=int)
    if ts.size == 0:
        empty = np.zeros((0, 3))
        return ResidualSamples(ts, np.zeros(0), empty, empty, empty, [])

    def accel(path):
        return (path[ts + 1] - 2.0 * path[ts] + path[ts - 1]) * fps**2

    velocity = (target[ts + 1] - target[ts - 1]) * fps / 2.0
    regime = [regimes[t] if regimes is not None and t < len(regimes) else "" for t in ts]
    return ResidualSamples(ts, ts / fps, target[ts], velocity, accel(target) - accel(sim), regime)


def run_samples(ctx, traj, *, frames: list[int], regimes: dict[int, list[str]] | None = None):
    """``residual_samples`` of every object of a run (``RunContext``) against ``traj``, over
    the frames up to the last of ``frames``: object id -> samples."""
    from mosiv_framework.diagnose.locate import object_residuals

    n = max(frames) + 1 if frames else 0
    residuals = object_residuals(ctx, traj, n)
    return {
        k: residual_samples(
            r.target_centroid,
            r.sim_centroid,
            ctx.fps,
            frames=frames,
            regimes=None if regimes is None else regimes.get(k),
        )
        for k, r in residuals.items()
    }
