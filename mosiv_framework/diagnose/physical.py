"""Evidence that an effect is physics, not model discrepancy.

A model that is not exactly the recording's generator (another simulator, other particles)
leaves a smooth systematic residual that any extra coefficient absorbs part of. Before an
effect is named it must show what such a discrepancy cannot:

- consistency across objects (``consistency``): a body force acts on every object alike, so
  its coefficient fitted to each object's residual accelerations (free flight, fit frames) must
  agree across objects within their uncertainty (chi-square test at
  ``DecideOptions.consistency_level``); a discrepancy differs from body to body;
- a clear win over a nuisance model (``nuisance_errors``): the null's rollout corrected by a
  per-object smooth displacement, a time polynomial of degree ``DecideOptions.nuisance_degree``
  per axis fitted to that object's centroid residual on the fit frames (degree 2: a velocity
  offset and a constant acceleration bias per object). The candidate must predict the held-out
  frames better than it by more than ``z`` bootstrap spreads and at least
  ``nuisance_min_drop``; a global effect consistent across two or more objects may instead tie
  with it (the agreement across objects is then the evidence).
"""

from __future__ import annotations

import math

import numpy as np
import torch
from scipy.stats import chi2

from mosiv_framework.diagnose.formula import object_designs
from mosiv_framework.diagnose.kinematics import ResidualSamples


def candidate_basis(candidate, velocity: np.ndarray) -> np.ndarray | None:
    """[M, 3, d] the candidate's extra acceleration per unit coefficient at ``velocity``
    [M, 3] (a body force is linear in its coefficients), or None for a non-body force."""
    if candidate is None:
        return None
    v = torch.as_tensor(velocity, dtype=torch.float32)
    cols = []
    for i in range(candidate.dim):
        unit = torch.zeros(candidate.dim)
        unit[i] = 1.0
        acc = candidate.acceleration(v, unit)
        if acc is None:
            return None
        cols.append(acc.detach().double().numpy())
    return np.stack(cols, axis=-1)


def _object_designs(candidate, samples: dict[int, ResidualSamples]) -> dict | None:
    """Per object: (basis [M, 3, d], residual [M, 3]) of its free-flight samples; None for a
    candidate that is not a body force."""
    if getattr(candidate, "kind", None) == "expression":
        return object_designs(candidate, samples)
    if candidate_basis(candidate, np.zeros((1, 3))) is None:
        return None
    out = {}
    for k, s in samples.items():
        flight = s.subset(np.array([r in ("free_flight", "") for r in s.regime]))
        out[k] = (candidate_basis(candidate, flight.velocity), flight.residual)
    return out


def object_coefficient(basis: np.ndarray, residual: np.ndarray) -> tuple | None:
    """(theta [d], covariance [d, d]) of residual [M, 3] ~ basis [M, 3, d] theta by least
    squares, or None without more equations than coefficients."""
    x = basis.reshape(-1, basis.shape[-1])
    y = residual.reshape(-1)
    if len(y) <= x.shape[1]:
        return None
    xtx = x.T @ x
    if np.linalg.matrix_rank(xtx) < x.shape[1]:
        return None
    theta = np.linalg.solve(xtx, x.T @ y)
    sigma2 = float(((y - x @ theta) ** 2).sum()) / (len(y) - x.shape[1])
    return theta, sigma2 * np.linalg.inv(xtx)


def consistency(
    candidate,
    samples: dict[int, ResidualSamples],
    *,
    level: float = 0.95,
    tolerance: float = 0.0,
) -> dict | None:
    """Whether a body-force candidate's coefficient agrees across objects.

    Returns None for a candidate that is not a body force. Otherwise {"objects": how many had
    an estimate, "per_object": {id: {"theta", "interval", "covariance"}}, "pooled", "chi2",
    "dof", "consistent"} (``agreement``); "consistent" is None with fewer than 2 estimates
    (nothing to compare). A discovered law (an ``expression`` candidate) is a body force of the
    objects' state: its basis holds each sample's features (``formula.object_designs``)."""
    designs = _object_designs(candidate, samples)
    if designs is None:
        return None
    per = {}
    for k, (basis, residual) in designs.items():
        fit = object_coefficient(basis, residual)
        if fit is None:  # too few free-flight samples of this object
            continue
        theta, cov = fit
        half = 1.96 * np.sqrt(np.clip(np.diag(cov), 0.0, None))
        per[str(k)] = {
            "theta": theta.tolist(),
            "interval": np.stack([theta - half, theta + half], 1).tolist(),
            "covariance": np.asarray(cov).tolist(),
        }
    return {"objects": len(per), "per_object": per, **agreement(per, level, tolerance)}


def agreement(per_object: dict, level: float, tolerance: float) -> dict:
    """The chi-square test that the objects' estimates (``consistency``'s "per_object") share
    one coefficient: {"pooled", "chi2", "dof", "consistent"} ("consistent" None with fewer than
    two estimates).

    Each estimate's covariance (a record without one: its 95 % interval read as 1.96 standard
    deviations) is widened by (``tolerance`` x |pooled|)^2 on every coefficient: another
    simulator than the recording's leaves each body's estimate a few percent off the others',
    which intervals of free flight alone, narrow for a well-sampled effect, would call a
    disagreement. 0 tests the intervals alone."""
    fits = []
    for record in per_object.values():
        theta = np.asarray(record["theta"], dtype=float)
        if record.get("covariance") is not None:
            cov = np.asarray(record["covariance"], dtype=float)
        else:
            half = (np.asarray(record["interval"], dtype=float) @ [-0.5, 0.5]) / 1.96
            cov = np.diag(half**2)
        fits.append((theta, cov))
    if len(fits) < 2:
        return {"pooled": None, "chi2": None, "dof": 0, "consistent": None}
    pooled, weights = _pooled(fits)
    if tolerance > 0:  # widen by the tolerance about the first pooled estimate, pool again
        spread = (tolerance * float(np.linalg.norm(pooled))) ** 2
        fits = [(t, c + spread * np.eye(len(t))) for t, c in fits]
        pooled, weights = _pooled(fits)
    stat = float(sum((t - pooled) @ w @ (t - pooled) for (t, _), w in zip(fits, weights)))
    dof = len(pooled) * (len(fits) - 1)
    return {
        "pooled": pooled.tolist(),
        "chi2": stat,
        "dof": dof,
        "consistent": bool(stat <= chi2.ppf(level, dof)),
    }


def _pooled(fits: list) -> tuple[np.ndarray, list[np.ndarray]]:
    """The inverse-covariance-weighted mean of (theta, covariance) estimates, and the weights
    (each inverse covariance)."""
    weights = [np.linalg.pinv(cov) for _, cov in fits]
    pooled = np.linalg.pinv(sum(weights)) @ sum(w @ t for (t, _), w in zip(fits, weights))
    return pooled, weights


def nuisance_displacement(
    residual: np.ndarray, fit_frames: list[int], fps: float, degree: int
) -> np.ndarray:
    """[T, 3] the per-object smooth residual: sum_j b_j t^j (j = 1..degree, t in s) per axis,
    fitted by least squares to the centroid residual [T, 3] (zero at frame 0) on
    ``fit_frames``, evaluated at every frame."""
    t = np.arange(residual.shape[0]) / fps
    basis = np.stack([t**j for j in range(1, degree + 1)], axis=1)
    rows = [f for f in fit_frames if f < residual.shape[0]]
    coef, *_ = np.linalg.lstsq(basis[rows], residual[rows], rcond=None)
    return basis @ coef


def nuisance_errors(ctx, null_traj, fit_frames: list[int], degree: int) -> np.ndarray | None:
    """[K, T] Chamfer error (m^2) of the null's rollout with every object moved by its
    ``nuisance_displacement``; None without a null trajectory."""
    from mosiv_framework.diagnose.locate import _chamfer, object_residuals

    if null_traj is None:
        return None
    frames = ctx.n_frames
    residuals = object_residuals(ctx, null_traj, frames)
    table = np.zeros((len(ctx.object_ids), frames))
    for row, k in enumerate(ctx.object_ids):
        shift = nuisance_displacement(residuals[k].centroid, fit_frames, ctx.fps, degree)
        sim = null_traj.object_positions(k)[:frames].detach().cpu().double().numpy()
        tgt = ctx.targets[k][:frames].double().numpy()
        table[row] = [_chamfer(sim[t] + shift[t], tgt[t]) for t in range(frames)]
    return table


def nuisance_parameters(n_objects: int, degree: int) -> int:
    """Free scalars of the nuisance correction: a polynomial per object and axis."""
    return 3 * degree * n_objects


def judge_physical(nuisance: np.ndarray | None, cand: np.ndarray, judged, consistent, options):
    """(passes_consistency, passes_nuisance, nuisance_drop, nuisance_spread, consistency) of a
    candidate's [K, T] errors ``cand`` against the nuisance table on the ``judged`` held-out
    frames, given its ``consistent`` record (``consistency``; None where not a body force),
    whose agreement is decided again under the options' level and tolerance (``agreement``)
    where it holds the per-object estimates; a record of intervals only, judged without a
    tolerance, keeps its saved outcome (its covariances are not all in the intervals)."""
    from mosiv_framework.diagnose.decide import bootstrap_drop

    consistent = _agreement_under(consistent, options)
    passes_consistency = consistent is None or consistent.get("consistent") is not False
    if nuisance is None or not judged or not np.isfinite(cand[:, judged]).all():
        return passes_consistency, True, None, None, consistent
    drop, spread = bootstrap_drop(
        nuisance[:, judged],
        cand[:, judged],
        block=options.block,
        resamples=options.bootstrap,
        seed=options.seed,
        statistic=options.heldout_statistic,
    )
    beats = drop > 0 and drop > options.z * spread and drop >= options.nuisance_min_drop
    ties = math.isfinite(spread) and drop > -options.z * spread
    agreed = consistent is not None and consistent.get("consistent") is True
    return passes_consistency, beats or (agreed and ties), drop, spread, consistent


def _agreement_under(record: dict | None, options) -> dict | None:
    """``record`` with its agreement decided under ``options`` (see ``judge_physical``)."""
    if not record or len(record.get("per_object") or {}) < 2:
        return record
    per = record["per_object"]
    has_covariance = all(r.get("covariance") is not None for r in per.values())
    if not has_covariance and options.consistency_tolerance == 0:
        return record
    return {
        **record,
        **agreement(per, options.consistency_level, options.consistency_tolerance),
        "tolerance": options.consistency_tolerance,
    }
