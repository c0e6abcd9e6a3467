"""Open-form discovery: a force law for what no candidate term explains.

Each object's residual acceleration (``kinematics``: finite differences of the target centroid
path minus the model's) is regressed, axis by axis and pooled over the objects of the scene
(one law for the scene), on a library of features of the object's state: a constant, its
position (the component along "up" as the height above the ground), velocity v and |v| v, the
time, a contact indicator, and the position and velocity of every other object relative to
it. Sparse regression by sequentially thresholded least squares (STLSQ, the SINDy estimator)
keeps the few features that matter, on the features of the subset with the best information
criterion (``best_subset`` says why); the kept terms are refitted by least squares and their
95 % intervals come from a bootstrap over (object, block of frames) units. The result is a
formula per axis ("a_x = -0.41 v_x - 0.02 |v|v_x") with coefficients and intervals.

Thresholds (``DiscoveryOptions``) are to be chosen on a development set.
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import combinations

import numpy as np

from mosiv_framework.diagnose.kinematics import ResidualSamples
from mosiv_framework.expression import NODE_FEATURES

AXES = ("x", "y", "z")
#: features that depend only on the state of the material at one place and time, which a
#: simulator applies per grid node (the ``expression`` term); the others need the objects
NODE_LOCAL = NODE_FEATURES


@dataclass(frozen=True)
class DiscoveryOptions:
    """threshold: STLSQ drops a feature whose coefficient times the feature's RMS is below
    this fraction of the residual acceleration's RMS (over all axes); iterations: STLSQ
    rounds; max_terms: the most features per axis (``best_subset``); bootstrap: resamples for the intervals; block: frames per resampled unit; level:
    the intervals' coverage; seed: resampling seed; min_samples: fewest samples worth a
    regression. To be chosen on a development set."""

    threshold: float = 0.01
    iterations: int = 10
    max_terms: int = 3
    bootstrap: int = 200
    block: int = 4
    level: float = 0.95
    seed: int = 0
    min_samples: int = 8


def feature_library(
    samples: dict[int, ResidualSamples],
    *,
    up: tuple[float, float, float] = (0.0, 0.0, 1.0),
    ground_height: float | None = None,
    block: int = 4,
) -> tuple[list[str], np.ndarray, np.ndarray, np.ndarray]:
    """(names, X [M, F], y [M, 3], unit [M]) pooled over objects; ``unit`` labels each row with
    its (object, block of ``block`` frames) for the bootstrap.

    The other objects enter as the sums of their positions and velocities relative to the
    object (dp, dv; a pairwise law of the separation, to first order): one feature set for
    every object whatever the number of others. Only frames every object has a sample at
    are used."""
    up_vec = np.asarray(up, dtype=np.float64)
    up_vec = up_vec / np.linalg.norm(up_vec)
    up_axis = int(np.argmax(np.abs(up_vec))) if np.isclose(np.abs(up_vec).max(), 1.0) else None
    ids = sorted(samples)
    common = set.intersection(*(set(samples[k].frames.tolist()) for k in ids)) if ids else set()
    rows, names, ys, units = [], None, [], []
    for n_obj, k in enumerate(ids):
        s = samples[k]
        for i, t in enumerate(s.frames.tolist()):
            if len(ids) > 1 and t not in common:
                continue
            feats = _state_features(s, i, up_vec, up_axis, ground_height)
            others = [j for j in ids if j != k]
            if others:
                here_p, here_v = s.position[i], s.velocity[i]
                rel_p = sum(_at(samples[j], t).position[0] - here_p for j in others)
                rel_v = sum(_at(samples[j], t).velocity[0] - here_v for j in others)
                for a, axis in enumerate(AXES):
                    feats[f"dp_{axis}"] = float(rel_p[a])
                for a, axis in enumerate(AXES):
                    feats[f"dv_{axis}"] = float(rel_v[a])
            names = list(feats) if names is None else names
            rows.append([feats[n] for n in names])
            ys.append(s.residual[i])
            units.append(n_obj * 100000 + t // block)
    if not rows:
        return [], np.zeros((0, 0)), np.zeros((0, 3)), np.zeros(0, dtype=int)
    return names, np.array(rows), np.array(ys), np.array(units)


def _at(s: ResidualSamples, t: int) -> ResidualSamples:
    """The sample of ``s`` at frame ``t``."""
    return s.subset(s.frames == t)


def _state_features(s, i, up_vec, up_axis, ground_height) -> dict[str, float]:
    # velocity terms come before positions and time: along a path of a drag law the position
    # is a linear function of the velocity, and ``independent_columns`` keeps the first of a
    # dependent set, the physical form
    p, v = s.position[i], s.velocity[i]
    speed = float(np.linalg.norm(v))
    feats = {"1": 1.0}
    for a, axis in enumerate(AXES):
        feats[f"v_{axis}"] = float(v[a])
    for a, axis in enumerate(AXES):
        feats[f"|v|v_{axis}"] = speed * float(v[a])
    height = float(p @ up_vec) - (ground_height or 0.0)
    for a, axis in enumerate(AXES):
        # the height replaces the position component along "up" (same span with the constant)
        feats["h" if a == up_axis else axis] = height if a == up_axis else float(p[a])
    if up_axis is None:
        feats["h"] = height
    feats["t"] = float(s.time[i])
    feats["contact"] = 1.0 if s.regime[i] in ("ground_contact", "object_contact", "rest") else 0.0
    return feats


def independent_columns(x: np.ndarray, *, tol: float = 1e-8) -> list[int]:
    """Indices of columns kept greedily, each not (numerically) in the span of those before:
    an all-zero contact indicator, or a height equal to a position plus a constant, would make
    the regression's coefficients arbitrary."""
    keep: list[int] = []
    for j in range(x.shape[1]):
        col = x[:, j]
        norm = np.linalg.norm(col)
        if norm == 0:
            continue
        if keep:
            basis = x[:, keep]
            coef, *_ = np.linalg.lstsq(basis, col, rcond=None)
            if np.linalg.norm(col - basis @ coef) <= tol * norm:
                continue
        keep.append(j)
    return keep


def best_subset(x: np.ndarray, y: np.ndarray, *, max_terms: int) -> list[int]:
    """The columns of the subset (up to ``max_terms`` of them) with the lowest information
    criterion n log(SSR / n) + p log n, searched exhaustively size by size.

    Why not least squares on the whole library, or one feature at a time: along a few smooth
    paths the features are nearly collinear (a ballistic path's position, velocity and time;
    the objects' summed separation and a point attractor's pull), so a full fit spreads the law
    over many terms that cancel, and a greedy choice can take a proxy first and never leave
    it. A library of about twenty features has a few thousand subsets of four."""
    n = len(y)

    def criterion(cols: tuple[int, ...]) -> float:
        if not cols:
            ssr = float((y**2).sum())
        else:
            sub = x[:, list(cols)]
            coef, *_ = np.linalg.lstsq(sub, y, rcond=None)
            ssr = float(((y - sub @ coef) ** 2).sum())
        return n * np.log(max(ssr, 1e-300) / n) + len(cols) * np.log(n)

    best, best_ic = (), criterion(())
    for size in range(1, min(max_terms, x.shape[1]) + 1):
        for cols in combinations(range(x.shape[1]), size):
            ic = criterion(cols)
            if ic < best_ic:
                best, best_ic = cols, ic
    return list(best)


def stlsq(x: np.ndarray, y: np.ndarray, *, cutoff: float, iterations: int = 10) -> np.ndarray:
    """Sequentially thresholded least squares: fit, drop coefficients whose contribution
    |c_j| rms(x_j) is below ``cutoff``, refit on the rest; repeat until the support is
    stable. Returns the coefficient vector (zeros where dropped)."""
    scale = np.sqrt((x**2).mean(axis=0))
    scale[scale == 0] = 1.0
    xs = x / scale
    support = np.ones(x.shape[1], dtype=bool)
    coef = np.zeros(x.shape[1])
    for _ in range(iterations):
        coef = np.zeros(x.shape[1])
        if support.any():
            coef[support], *_ = np.linalg.lstsq(xs[:, support], y, rcond=None)
        new = np.abs(coef) >= cutoff
        if (new == support).all():
            break
        support = new
    coef[~support] = 0.0
    return coef / scale


def sparse_fit(x: np.ndarray, y: np.ndarray, *, cutoff: float, options) -> np.ndarray:
    """Coefficients over every column: ``best_subset`` picks the support, ``stlsq`` then
    drops the chosen terms too small to matter (below ``cutoff``)."""
    chosen = best_subset(x, y, max_terms=options.max_terms)
    coef = np.zeros(x.shape[1])
    if chosen:
        coef[chosen] = stlsq(x[:, chosen], y, cutoff=cutoff, iterations=options.iterations)
    return coef


def discover(
    samples: dict[int, ResidualSamples],
    *,
    up=(0.0, 0.0, 1.0),
    ground_height: float | None = None,
    options: DiscoveryOptions = DiscoveryOptions(),
    features: tuple[str, ...] | None = None,
) -> dict | None:
    """The sparse force law of the residual accelerations (see the module docstring), over
    the library's ``features`` only where given (those a simulator can apply).

    Returns:
        {"axes": {axis: {"terms": [{"feature", "coefficient", "interval"}], "formula"}},
        "formula": the three formulas joined, "samples", "features", "node_local": whether
        every kept feature is node-local (``NODE_LOCAL``)}, or None with too few samples."""
    names, x, y, units = feature_library(
        samples, up=up, ground_height=ground_height, block=options.block
    )
    if len(y) < options.min_samples:
        return None
    allowed = [j for j, n in enumerate(names) if features is None or n in features]
    cols = [allowed[j] for j in independent_columns(x[:, allowed])] if allowed else []
    names, x = [names[j] for j in cols], x[:, cols]
    cutoff = options.threshold * float(np.sqrt((y**2).mean()))
    rng = np.random.default_rng(options.seed)
    unit_ids = np.unique(units)
    draws = [rng.choice(unit_ids, len(unit_ids)) for _ in range(options.bootstrap)]
    rows_of = {u: np.flatnonzero(units == u) for u in unit_ids}
    axes = {}
    for a, axis in enumerate(AXES):
        coef = sparse_fit(x, y[:, a], cutoff=cutoff, options=options)
        support = np.flatnonzero(coef)
        boot = _bootstrap(x[:, support], y[:, a], draws, rows_of) if support.size else None
        terms = []
        for n, j in enumerate(support):
            lo, hi = np.quantile(boot[:, n], [(1 - options.level) / 2, (1 + options.level) / 2])
            terms.append({"feature": names[j], "coefficient": float(coef[j]), "interval": [lo, hi]})
        axes[axis] = {"terms": terms, "formula": formula(axis, terms)}
    kept = {t["feature"] for ax in axes.values() for t in ax["terms"]}
    return {
        "axes": axes,
        "formula": "; ".join(ax["formula"] for ax in axes.values()),
        "samples": int(len(y)),
        "features": names,
        "node_local": kept <= set(NODE_LOCAL),
    }


def _bootstrap(x, y, draws, rows_of) -> np.ndarray:
    """[B, S] least-squares coefficients of the kept features over resampled units."""
    out = []
    for draw in draws:
        rows = np.concatenate([rows_of[u] for u in draw])
        coef, *_ = np.linalg.lstsq(x[rows], y[rows], rcond=None)
        out.append(coef)
    return np.array(out)


def formula(axis: str, terms: list[dict]) -> str:
    """``a_x = -0.41 v_x - 0.02 |v|v_x`` from the kept terms (``a_x = 0`` if none)."""
    if not terms:
        return f"a_{axis} = 0"
    parts = []
    for i, t in enumerate(terms):
        c = t["coefficient"]
        mag = f"{abs(c):.3g}"
        body = mag if t["feature"] == "1" else f"{mag} {t['feature']}"
        sign = ("-" if c < 0 else "") if i == 0 else ("- " if c < 0 else "+ ")
        parts.append(f"{sign}{body}")
    return f"a_{axis} = " + " ".join(parts)
