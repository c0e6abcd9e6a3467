"""How well the recording pins down each identified parameter: a 95 % interval per parameter.

A Laplace approximation in the optimiser's coordinates (each parameter's normalised coordinate,
affine in log(value) for scale parameters, so intervals are symmetric in log space): near the
identified point u0 the loss is L(u) ~ L0 + (u - u0)^T H (u - u0) / 2. Read as the mean of n
Gaussian residuals of variance sigma^2, the negative log-likelihood is n L / (2 sigma^2); with
sigma^2 estimated by the residual level L0 its Hessian is n H / (2 L0), so the posterior
covariance of u is (2 L0 / n) H^-1 and each parameter's 95 % interval is u0_i +- 1.96
sqrt((2 L0 / n) [H^-1]_ii): the marginal interval, which widens where parameters trade off
against each other (a stiffer body with a larger Poisson ratio moving much like a softer one).
H comes from central finite differences of the loss's gradient (autograd through the simulator,
1 + 2 d backward rollouts for d parameters; one-sided near a bound), symmetrised.

n counts the independent residuals. The points of one body move together, so their distances
are far from independent; each (observed frame, object) pair counts as one residual. This is
conservative (wider) when the misfit is noise, and an honest width when the misfit is a bias.

A parameter along which the loss does not change (zero curvature, e.g. a yield stress above
every stress the motion reaches) is ``unconstrained``; so is one with weight on a direction of
(near) zero or negative curvature, whose marginal variance is then unbounded. Where an interval
runs past one of the parameter's bounds, only the other side is supported by the data:
``E >= x`` (``lower-bound``, ``high`` None) or ``E <= x`` (``upper-bound``, ``low`` None).
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
#: a loss change along a coordinate below this fraction of the loss is no curvature
FLAT = 1e-6
#: eigenvalues of H below this fraction of the largest count as zero curvature
RANK_TOL = 1e-9

LossGrad = Callable[[torch.Tensor], tuple[float, torch.Tensor]]


def finite_difference_hessian(
    loss_grad: LossGrad, u0: torch.Tensor, *, step: float = STEP
) -> tuple[float, torch.Tensor]:
    """(L(u0), H): the Hessian from central differences of the gradient, one-sided (pointing
    into [0, 1]) where a central step would leave it; symmetrised. float64 throughout."""
    u0 = u0.double()
    l0, g0 = loss_grad(u0.clone())
    d = u0.numel()
    hessian = torch.zeros(d, d, dtype=torch.float64)
    for i in range(d):
        e = torch.zeros(d, dtype=torch.float64)
        e[i] = step
        if u0[i] - step >= 0.0 and u0[i] + step <= 1.0:
            hessian[i] = (loss_grad(u0 + e)[1].double() - loss_grad(u0 - e)[1].double()) / (
                2 * step
            )
        else:
            sign = 1.0 if u0[i] + step <= 1.0 else -1.0
            hessian[i] = (loss_grad(u0 + sign * e)[1].double() - g0.double()) / (sign * step)
    return l0, 0.5 * (hessian + hessian.T)


def laplace_intervals(
    loss_grad: LossGrad, u0: torch.Tensor, *, n: int, step: float = STEP
) -> list[dict]:
    """The marginal Laplace 95 % interval of each coordinate of ``u`` in [0, 1]^d around u0.

    Args:
        loss_grad: u -> (loss, gradient [d]) at u (a diverged rollout: inf, NaN gradient).
        u0: the identified coordinates, [d].
        n: the number of independent residuals the loss averages.
        step: the finite-difference step in u.

    Returns:
        Per coordinate ``{"low", "high", "kind"}`` in u: kind ``two-sided``, ``lower-bound``
        (``high`` None), ``upper-bound`` (``low`` None) or ``unconstrained`` (both None).
    """
    l0, hessian = finite_difference_hessian(loss_grad, u0, step=step)
    d = u0.numel()
    out = [{"low": None, "high": None, "kind": "unconstrained"} for _ in range(d)]
    if not math.isfinite(l0) or not bool(torch.isfinite(hessian).all()):
        return out
    # a coordinate along which the loss changes by less than FLAT of itself over a step
    seen = [
        i
        for i in range(d)
        if hessian[i, i] > 0 and 0.5 * hessian[i, i] * step**2 > max(FLAT * abs(l0), 1e-15)
    ]
    if not seen:
        return out
    values, vectors = torch.linalg.eigh(hessian[seen][:, seen])
    # zero or negative curvature: an unbounded variance along that direction, which every
    # coordinate with weight on it inherits (its interval then spans the whole range)
    values = values.clamp(min=RANK_TOL * max(float(values.max()), 1e-300))
    variance = (vectors**2 / values).sum(dim=1) * 2.0 * max(l0, 0.0) / max(n, 1)
    for j, i in enumerate(seen):
        out[i] = _interval(float(u0[i]), Z95 * math.sqrt(float(variance[j])))
    return out


def _interval(u0: float, half: float) -> dict:
    """``u0 +- half`` in [0, 1], one-sided or unconstrained where it runs past a bound."""
    low, high = u0 - half, u0 + half
    if low < 0.0 and high > 1.0:
        return {"low": None, "high": None, "kind": "unconstrained"}
    if low < 0.0:
        return {"low": None, "high": high, "kind": "upper-bound"}
    if high > 1.0:
        return {"low": low, "high": None, "kind": "lower-bound"}
    return {"low": low, "high": high, "kind": "two-sided"}


def parameter_intervals(fit, vector, *, last: int, step: float = STEP) -> dict:
    """Per object and identified parameter, its 95 % interval in SI units.

    Args:
        fit: a ``phases.Fit``; the loss is its objective over frames ``1..last``.
        vector: the identified ParameterVector (left as it was given).
        last: the last fitted frame.
        step: the finite-difference step in normalised coordinates.

    Returns:
        ``{"obj1": {"E": {"low", "high", "kind"}}, "ground_friction": {...}}``; physics-term
        leaves are not reported. A probe whose rollout diverges leaves every parameter
        ``unconstrained`` (the curvature there is unknown).
    """
    keys = [
        key
        for key, u in sorted(vector.normalized.items())
        if not key.startswith("term.") and u.numel() == 1
    ]
    if not keys:
        return {}
    leaves = [vector.normalized[key] for key in keys]
    saved = [leaf.detach().clone() for leaf in leaves]

    def loss_grad(u: torch.Tensor) -> tuple[float, torch.Tensor]:
        with torch.no_grad():
            for leaf, value in zip(leaves, u):
                leaf.fill_(float(value))
        try:
            loss = fit.objective(*fit.rollout_geometry(vector, last))
            grads = torch.autograd.grad(loss, leaves, allow_unused=True)
        except SimulationDiverged:
            return math.inf, torch.full((len(keys),), math.nan, dtype=torch.float64)
        flat = [0.0 if g is None else float(g.detach().reshape(())) for g in grads]
        return float(loss.detach()), torch.tensor(flat, dtype=torch.float64)

    u0 = torch.stack([s.reshape(()) for s in saved]).double()
    try:
        found = laplace_intervals(loss_grad, u0, n=last * len(vector.families), step=step)
    finally:
        with torch.no_grad():
            for leaf, value in zip(leaves, saved):
                leaf.copy_(value)
    out: dict = {}
    for key, got in zip(keys, found):
        spec = vector.specs[key]
        entry = {"low": _si(spec, got["low"]), "high": _si(spec, got["high"]), "kind": got["kind"]}
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
