"""How well the recording pins down each identified parameter: a 95 % interval per parameter.

A Laplace approximation in the optimiser's coordinate of each parameter (its normalised
coordinate, affine in log(value) for scale parameters, so the interval is symmetric in log
space): near the identified value u0 the loss is L(u) ~ L0 + H (u - u0)^2 / 2. Read as the
mean of n Gaussian residuals of variance sigma^2, the negative log-likelihood is
n L / (2 sigma^2); with sigma^2 estimated by the residual level L0 it has curvature n H / (2 L0),
so the posterior standard deviation of u is sqrt(2 L0 / (n H)) and the 95 % interval is
u0 +- 1.96 of them. The curvature H comes from central finite differences of the loss along
each coordinate (no tape, two rollouts per parameter; one-sided near a bound), the other
parameters held at their identified values, so correlations between parameters are ignored:
the interval is conditional on them.

n counts the independent residuals. The points of one body move together, so their distances
are far from independent; each (observed frame, object) pair counts as one residual. This is
conservative (wider) when the misfit is noise, and an honest width when the misfit is a bias.

Where the curvature vanishes (the loss does not change along the coordinate, e.g. a ground
friction no sliding ever tests) the parameter is ``unconstrained``; where the interval runs
past one of the parameter's bounds, only the other side is supported by the data: ``E >= x``
(``lower-bound``, ``high`` None) or ``E <= x`` (``upper-bound``, ``low`` None).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch

from mosiv_framework.errors import SimulationDiverged

#: the history's phase name of the interval record
INTERVALS_PHASE = "intervals"
#: two-sided 95 % quantile of the normal distribution
Z95 = 1.959963984540054
#: finite-difference step in normalised coordinates (2 % of the range: 20 % in E over 1e3-1e7 Pa)
STEP = 0.02
#: a loss change below this fraction of the loss (or of 1e-12 absolute) is no curvature
FLAT = 1e-6


def laplace_interval(
    loss: Callable[[float], float],
    u0: float,
    *,
    n: int,
    step: float = STEP,
    l0: float | None = None,
) -> dict:
    """The Laplace 95 % interval of the coordinate ``u`` in [0, 1] around ``u0``.

    Args:
        loss: u -> the loss with the coordinate set to u (others held).
        u0: the identified coordinate.
        n: the number of independent residuals the loss averages.
        step: the finite-difference step in u.
        l0: ``loss(u0)`` if already known (saves a rollout).

    Returns:
        ``{"low", "high", "kind", "curvature", "loss"}`` in u: kind ``two-sided``,
        ``lower-bound`` (``high`` None), ``upper-bound`` (``low`` None) or ``unconstrained``
        (both None).
    """
    l0 = loss(u0) if l0 is None else l0
    if u0 - step >= 0.0 and u0 + step <= 1.0:
        lo, hi = loss(u0 - step), loss(u0 + step)
        curvature = (hi - 2.0 * l0 + lo) / step**2
        change = max(abs(hi - l0), abs(lo - l0))
    else:  # one-sided second difference, pointing into the range
        d = step if u0 + 2 * step <= 1.0 else -step
        l1, l2 = loss(u0 + d), loss(u0 + 2 * d)
        curvature = (l2 - 2.0 * l1 + l0) / step**2
        change = max(abs(l1 - l0), abs(l2 - l0))
    out = {"low": None, "high": None, "kind": "unconstrained", "curvature": curvature, "loss": l0}
    flat = change <= max(FLAT * abs(l0), 1e-12)
    if not (math.isfinite(curvature) and math.isfinite(l0)) or flat or curvature <= 0.0:
        return out
    half = Z95 * math.sqrt(2.0 * max(l0, 0.0) / (max(n, 1) * curvature))
    low, high = u0 - half, u0 + half
    if low < 0.0 and high > 1.0:
        return out
    if low < 0.0:
        return {**out, "high": high, "kind": "upper-bound"}
    if high > 1.0:
        return {**out, "low": low, "kind": "lower-bound"}
    return {**out, "low": low, "high": high, "kind": "two-sided"}


def parameter_intervals(fit, vector, *, last: int, step: float = STEP) -> dict:
    """Per object and identified parameter, its 95 % interval in SI units.

    Args:
        fit: a ``phases.Fit``; the loss is its objective over frames ``1..last``.
        vector: the identified ParameterVector (left as it was given).
        last: the last fitted frame.
        step: the finite-difference step in normalised coordinates.

    Returns:
        ``{"obj1": {"E": {"low", "high", "kind"}}, "ground_friction": {...}}``; a diverged
        probe rollout counts as an infinite loss there.
    """
    n = last * len(vector.families)
    with torch.no_grad():
        try:
            l0 = fit.window_loss(vector, last)
        except SimulationDiverged:
            return {}  # the identified values themselves cannot be rolled out: nothing to say
    out: dict = {}
    for key, u in sorted(vector.normalized.items()):
        if key.startswith("term.") or u.numel() != 1:
            continue  # physics-term leaves (some are vectors) are not reported
        spec, u0 = vector.specs[key], float(u.detach())

        def loss_at(value: float, key=key) -> float:
            with torch.no_grad():
                saved = vector.normalized[key].detach().clone()
                vector.normalized[key].fill_(value)
                try:
                    return fit.window_loss(vector, last)
                except SimulationDiverged:
                    return math.inf
                finally:
                    vector.normalized[key].copy_(saved)

        got = laplace_interval(loss_at, u0, n=n, step=step, l0=l0)
        entry = {
            "low": _si(spec, got["low"]),
            "high": _si(spec, got["high"]),
            "kind": got["kind"],
        }
        if "." in key:
            owner, name = key.split(".", 1)
            out.setdefault(owner, {})[name] = entry
        else:
            out[key] = entry
    return out


def _si(spec, u: float | None) -> float | None:
    """A normalised coordinate in SI units (None stays None)."""
    if u is None:
        return None
    return float(spec.from_normalized(torch.tensor(float(u), dtype=torch.float64)))


def covered(interval: dict, true: float) -> bool:
    """Whether ``true`` lies in the interval (an unconstrained one covers everything)."""
    low, high = interval.get("low"), interval.get("high")
    return (low is None or true >= low) and (high is None or true <= high)


def attach_intervals(history: list[dict], identified_json: dict) -> None:
    """Copy the history's interval record, if any, into identified.json under ``intervals``."""
    records = [h for h in history if h.get("phase") == INTERVALS_PHASE]
    if records:
        identified_json["intervals"] = records[-1]["intervals"]


def mark_coverage(param_error: dict | None, identified_json: dict) -> None:
    """Add ``covered`` (whether the interval holds the truth) to each parameter's entry of
    metrics.json's ``param_error`` that has an interval in identified.json.

    Parameters with a ``rel_error_gauge_free`` (Pa, Pa*s, kg/m^3) are identified in the gauge
    where the first object's density keeps its given value (``params.GAUGE_PARAM``); their
    interval is scaled into the truth's gauge (by true / identified density of that object)
    before the comparison, as their gauge-free error is."""
    intervals = identified_json.get("intervals") or {}
    gauge = _gauge(param_error or {})
    for obj, errors in (param_error or {}).items():
        for name, err in errors.items():
            interval = intervals.get(f"obj{obj}", {}).get(name)
            if interval is None or not isinstance(err, dict) or "true" not in err:
                continue
            if "rel_error_gauge_free" in err and gauge is not None:
                interval = {
                    side: None if interval.get(side) is None else interval[side] * gauge
                    for side in ("low", "high")
                }
            err["covered"] = covered(interval, float(err["true"]))


def _gauge(param_error: dict) -> float | None:
    """True / identified density of the lowest-id object in ``param_error`` (None if absent)."""
    if not param_error:
        return None
    rho = param_error[min(param_error, key=int)].get("rho")
    if not rho or not rho.get("value"):
        return None
    return float(rho["true"]) / float(rho["value"])
