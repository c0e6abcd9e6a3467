"""The uncertainty of an accepted effect's coefficients (the report's 95 % interval).

Three estimates are joined (the interval is their hull), because each misses something:
- profile: the Chamfer loss probed along each coefficient with every other parameter held at
  the fit. It ignores that a coefficient trades off against the initial velocities (a steady
  acceleration and a velocity change both shift the path early on), so alone it is too narrow;
- starts: every refit start whose loss is within the same likelihood-ratio bound, so starts that
  disagree show up as width;
- linearised block bootstrap: the centroid paths are linearised in the coefficients *and* the
  initial velocities (central differences through the simulator), and the least-squares step
  is recomputed with (object, time block) units resampled; the 2.5 and 97.5 percentiles of the
  resampled coefficient, plus the Gauss-Newton interval of the same linear model, capture the
  coefficient-velocity correlation and the spread across objects and time.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from mosiv_framework.diagnose.context import RunContext
from mosiv_framework.diagnose.locate import object_residuals
from mosiv_framework.diagnose.model import Fit
from mosiv_framework.errors import SimulationDiverged
from mosiv_framework.types import SimulationParams

#: two-sided 95 % quantile of the standard normal distribution
Z95 = 1.959964


@dataclass(frozen=True)
class IntervalOptions:
    """confidence_chi2: likelihood-ratio bound of the profile (3.84: 95 %); velocity_step:
    central-difference step of the initial velocities (m/s); block: frames per time block;
    bootstrap: resamples; seed: resampling seed."""

    confidence_chi2: float = 3.84
    velocity_step: float = 0.02
    block: int = 2
    bootstrap: int = 500
    seed: int = 0


def coefficient_interval(
    ctx: RunContext,
    fit: Fit,
    *,
    fit_frames: list[int],
    options: IntervalOptions = IntervalOptions(),
) -> tuple[list[float], list[float]]:
    """(lower, upper) per coefficient of ``fit``: hull of the profile interval, the refit
    starts within the likelihood-ratio bound and the linearised block bootstrap, clipped to
    the candidate's bounds."""
    candidate = fit.candidate
    lower, upper = profile_interval(ctx, fit, fit_frames=fit_frames, options=options)
    n = len(fit_frames) * len(ctx.object_ids)
    for theta, loss in fit.starts:
        if n * math.log(max(loss, 1e-300) / max(fit.loss, 1e-300)) <= options.confidence_chi2:
            lower = [min(lo, t) for lo, t in zip(lower, theta)]
            upper = [max(hi, t) for hi, t in zip(upper, theta)]
    try:
        jac, residual, units = centroid_jacobian(ctx, fit, fit_frames=fit_frames, options=options)
        boot_lo, boot_hi = linearised_bootstrap(
            jac, residual, units, n_coefficients=candidate.dim, options=options
        )
        theta = fit.theta.double().numpy()
        lower = [min(lo, t + b) for lo, t, b in zip(lower, theta, boot_lo)]
        upper = [max(hi, t + b) for hi, t, b in zip(upper, theta, boot_hi)]
    except SimulationDiverged:
        pass  # a probe left the stable range: the profile and the starts are all there is
    lower = [max(lo, float(b)) for lo, b in zip(lower, candidate.lower)]
    upper = [min(hi, float(b)) for hi, b in zip(upper, candidate.upper)]
    return lower, upper


def profile_interval(
    ctx: RunContext, fit: Fit, *, fit_frames: list[int], options: IntervalOptions
) -> tuple[list[float], list[float]]:
    """Per coefficient, others held at the fit: the loss probed one natural step either side
    and modelled as quadratic, L = L* + h (theta - theta*)^2 / 2. Treating the loss as the mean
    of n Gaussian residuals (n = frames x objects), the likelihood ratio n log(L / L*) <= chi2
    gives the half-width sqrt(2 chi2 L* / (n h)); infinite where the loss is flat."""
    candidate = fit.candidate
    n = len(fit_frames) * len(ctx.object_ids)
    base = _without(fit)
    probes = []
    for i in range(candidate.dim):
        for sign in (-1.0, 1.0):
            theta = fit.theta.clone()
            theta[i] += sign * float(candidate.step[i])
            probes.append(candidate.apply(base, candidate.clamp(theta)))
    # the 2 x dim probes are independent rollouts, so together; a diverged one is inf
    probe_losses = ctx.rollout_losses(probes, fit_frames)
    lower, upper = [], []
    for i in range(candidate.dim):
        h_step = float(candidate.step[i])
        losses = probe_losses[2 * i : 2 * i + 2]
        curvature = (losses[0] + losses[1] - 2.0 * fit.loss) / h_step**2
        if math.isfinite(curvature) and curvature > 0:
            half = math.sqrt(2.0 * options.confidence_chi2 * fit.loss / (n * curvature))
        else:
            half = math.inf  # flat or non-convex: the data do not pin the coefficient down
        lower.append(float(fit.theta[i]) - half)
        upper.append(float(fit.theta[i]) + half)
    return lower, upper


def centroid_jacobian(
    ctx: RunContext, fit: Fit, *, fit_frames: list[int], options: IntervalOptions
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(J [m, p], r [m], unit [m]) of the fit's centroid residuals at the fit frames.

    Rows are (object, frame, axis); columns the candidate's coefficients then each object's
    initial-velocity components. J is d(residual)/d(parameter) by central differences (steps:
    the candidate's natural step, ``velocity_step``); r is target minus simulated centroid
    relative to frame 0 (m); unit numbers the (object, time block) a row belongs to.
    """
    candidate = fit.candidate
    base = _without(fit)
    horizon = max(fit_frames)
    objects = ctx.object_ids

    def centroids(params: SimulationParams) -> np.ndarray:
        traj = ctx.rollout(params, frames=horizon)
        return np.stack(
            [traj.object_positions(k)[fit_frames].double().mean(dim=1).numpy() for k in objects]
        )  # [K, F, 3]

    columns = []
    for i in range(candidate.dim):
        step = float(candidate.step[i])
        sides = []
        for sign in (1.0, -1.0):
            theta = fit.theta.clone()
            theta[i] += sign * step
            sides.append(centroids(candidate.apply(base, theta)))
        columns.append(-(sides[0] - sides[1]) / (2.0 * step))  # residual = target - sim
    for k in objects:
        for axis in range(3):
            sides = []
            for sign in (1.0, -1.0):
                velocity = dict(base.initial_velocity)
                dv = torch.zeros(3)
                dv[axis] = sign * options.velocity_step
                velocity[k] = velocity[k] + dv
                shifted = SimulationParams(
                    base.objects, velocity, base.ground_friction, dict(base.terms)
                )
                sides.append(centroids(candidate.apply(shifted, fit.theta)))
            columns.append(-(sides[0] - sides[1]) / (2.0 * options.velocity_step))
    jac = np.stack([c.reshape(-1) for c in columns], axis=1)
    res = object_residuals(ctx, fit.trajectory, horizon + 1)
    residual = np.stack([res[k].centroid[fit_frames] for k in objects]).reshape(-1)
    blocks = np.asarray([(t - fit_frames[0]) // options.block for t in fit_frames])
    n_blocks = int(blocks.max()) + 1
    unit = np.stack([kk * n_blocks + blocks for kk in range(len(objects))])  # [K, F]
    return jac, residual, np.repeat(unit.reshape(-1), 3)


def linearised_bootstrap(
    jac: np.ndarray,
    residual: np.ndarray,
    unit: np.ndarray,
    *,
    n_coefficients: int,
    options: IntervalOptions,
) -> tuple[np.ndarray, np.ndarray]:
    """(lower, upper) offsets of the first ``n_coefficients`` parameters from the fit.

    The linear model r ~ J delta is solved by weighted least squares with whole units
    resampled (weight = how often a unit is drawn); the offsets are the 2.5 / 97.5 percentiles
    of delta_w - delta_1 (delta_1: the step with every unit once), widened to the Gauss-Newton
    interval +-1.96 sqrt(s^2 (J^T J)^-1) (s^2: residual variance after the step) and to
    delta_1 itself (where a centroid fit would put the coefficient). A coefficient the linear
    model cannot separate from the velocities gets an infinite offset.
    """
    m, p = jac.shape
    normal = jac.T @ jac
    if np.linalg.matrix_rank(normal) < p or m <= p:
        inf = np.full(n_coefficients, np.inf)
        return -inf, inf
    delta_1 = np.linalg.solve(normal, jac.T @ residual)
    after = residual - jac @ delta_1
    s2 = float(after @ after) / (m - p)
    gauss_newton = Z95 * np.sqrt(s2 * np.diag(np.linalg.inv(normal))[:n_coefficients])
    units = np.unique(unit)
    rng = np.random.default_rng(options.seed)
    draws = []
    for _ in range(options.bootstrap):
        counts = np.bincount(rng.integers(0, len(units), len(units)), minlength=len(units))
        weight = counts[np.searchsorted(units, unit)].astype(np.float64)
        weighted = jac.T * weight
        try:
            delta = np.linalg.solve(weighted @ jac, weighted @ residual)
        except np.linalg.LinAlgError:
            continue  # a resample that dropped every unit pinning a parameter
        draws.append(delta[:n_coefficients] - delta_1[:n_coefficients])
    low = -gauss_newton
    high = gauss_newton.copy()
    if draws:
        draws = np.asarray(draws)
        low = np.minimum(low, np.percentile(draws, 2.5, axis=0))
        high = np.maximum(high, np.percentile(draws, 97.5, axis=0))
    centroid_fit = delta_1[:n_coefficients]
    return np.minimum(low, centroid_fit), np.maximum(high, centroid_fit)


def _without(fit: Fit) -> SimulationParams:
    """The fit's parameters with the candidate's effect taken out again (it is re-applied
    at probed coefficients)."""
    return fit.candidate.without(fit.params, fit.theta)
