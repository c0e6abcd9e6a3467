"""How well the recording pins down each identified parameter: a 95 % interval per parameter.

Both methods (``identify.interval_method``) work in the optimiser's coordinates (each
parameter's normalised coordinate, affine in log(value) for scale parameters, so intervals are
symmetric in log space) around the identified point u0, with the Hessian H of the loss there
from central finite differences of its gradient (autograd through the simulator, 1 + 2 d
backward rollouts for d parameters; one-sided near a bound), symmetrised. Both give the
marginal interval, which widens where parameters trade off against each other (a stiffer body
with a larger Poisson ratio moving much like a softer one).

``laplace``: near u0 the loss is L(u) ~ L0 + (u - u0)^T H (u - u0) / 2. Read as the mean of n
Gaussian residuals of variance sigma^2, the negative log-likelihood is n L / (2 sigma^2); with
sigma^2 estimated by the residual level L0 its Hessian is n H / (2 L0), so the posterior
covariance of u is (2 L0 / n) H^-1 and each parameter's 95 % interval is u0_i +- 1.96
sqrt((2 L0 / n) [H^-1]_ii). n counts the independent residuals: the points of one body move
together, so each (observed frame, object) pair counts as one. This assumes the model is right
(the misfit is noise, not a bias) and the loss is a calibrated likelihood; where another
engine made the data, it is too narrow.

``sandwich``: the covariance H^-1 J H^-1 of ``mosiv_framework.pipeline.sandwich``, with one
block per fitted frame (the objectives average over frames, so each frame's loss over the
number of frames is its share of the loss) and J the Bartlett-weighted covariance of the
frames' gradients at u0: how much the frames disagree about where the optimum lies, which is
what a wrong model shows. The frames' gradients are differences of the frames' losses at the
same probes as the Hessian (no extra rollout; one more forward-and-backward rollout per
parameter within a step of its bound, for a second-order one-sided difference). Its interval
is the wider of the sandwich one and the Laplace one (``interval_estimates`` says why).

A parameter along which the loss does not change (zero curvature, e.g. a yield stress above
every stress the motion reaches) is ``unconstrained``. A direction of the Hessian with (near)
zero or negative curvature (a trade-off the data cannot settle, or a saddle of a model that is
not the data's) is followed as far as the box [0, 1]^d lets it from u0: each coordinate's
interval widens by how far that segment moves it. The coordinates that make up such a direction
reach their bounds (``unconstrained`` or one-sided); one with little weight on it widens a
little, instead of every coordinate inheriting an unbounded variance from it (which on Genesis
scenes left every interval unconstrained). Where an interval
runs past one of the parameter's bounds, only the other side is supported by the data:
``E >= x`` (``lower-bound``, ``high`` None) or ``E <= x`` (``upper-bound``, ``low`` None).
Every probe draws the same random point subsets (the losses' generators are set back before
each evaluation), so differences between probes are not subsampling noise.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import torch

from mosiv_framework.errors import SimulationDiverged
from mosiv_framework.pipeline.sandwich import (
    block_scores,
    hac_meat,
    newey_west_lag,
    sandwich_covariance,
    t_quantile,
)
from mosiv_framework.recipes.schema import INTERVAL_METHODS
from mosiv_framework.types import GeometryFrames

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

#: u -> (loss, gradient [d]) or (loss, gradient [d], block shares [T] summing to the loss)
LossGrad = Callable[[torch.Tensor], tuple]


@dataclass
class Probes:
    """What the finite-difference probes around u0 found: the loss there, the Hessian and,
    where the loss came in block shares, the per-block scores ([T, d], else None)."""

    loss: float
    hessian: torch.Tensor
    scores: torch.Tensor | None = None


def probe(loss_grad: LossGrad, u0: torch.Tensor, *, step: float = STEP, blocks: bool = False):
    """The Hessian from central differences of the gradient, one-sided (pointing into [0, 1])
    where a central step would leave it, symmetrised; with ``blocks``, also each block's
    gradient from differences of the block shares at the same probes (one forward-and-backward
    evaluation more per one-sided coordinate, for a second-order difference). float64."""
    u0 = u0.double()
    first = loss_grad(u0.clone())
    l0, g0 = first[0], first[1].double()
    d = u0.numel()
    hessian = torch.zeros(d, d, dtype=torch.float64)
    plus, minus, steps = [], [], []
    for i in range(d):
        e = torch.zeros(d, dtype=torch.float64)
        e[i] = step
        if u0[i] - step >= 0.0 and u0[i] + step <= 1.0:
            up, down = loss_grad(u0 + e), loss_grad(u0 - e)
            hessian[i] = (up[1].double() - down[1].double()) / (2 * step)
            if blocks:
                plus.append(_shares(up))
                minus.append(_shares(down))
                steps.append(step)
            continue
        sign = 1.0 if u0[i] + step <= 1.0 else -1.0
        up = loss_grad(u0 + sign * e)
        hessian[i] = (up[1].double() - g0) / (sign * step)
        if blocks:
            plus.append(torch.stack([_shares(up), _shares(loss_grad(u0 + 2 * sign * e))]))
            minus.append(None)
            steps.append(sign * step)
    scores = block_scores(_shares(first), plus, minus, steps) if blocks else None
    return Probes(l0, 0.5 * (hessian + hessian.T), scores)


def _shares(evaluated: tuple) -> torch.Tensor:
    """The block shares of one ``loss_grad`` evaluation (float64)."""
    if len(evaluated) < 3:
        raise ValueError("the sandwich needs loss_grad to return (loss, gradient, block shares)")
    return torch.as_tensor(evaluated[2], dtype=torch.float64).reshape(-1)


def finite_difference_hessian(
    loss_grad: LossGrad, u0: torch.Tensor, *, step: float = STEP
) -> tuple[float, torch.Tensor]:
    """(L(u0), H), see ``probe``."""
    found = probe(loss_grad, u0, step=step)
    return found.loss, found.hessian


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
    return interval_estimates(probe(loss_grad, u0, step=step), u0, n=n, step=step)["laplace"]


def sandwich_intervals(
    loss_grad: LossGrad, u0: torch.Tensor, *, n: int, step: float = STEP, lag: int | None = None
) -> list[dict]:
    """The sandwich 95 % interval of each coordinate of ``u`` in [0, 1]^d around u0, never
    narrower than the Laplace one (``interval_estimates``).

    Args:
        loss_grad: u -> (loss, gradient [d], block shares [T]) at u; the shares sum to the
            loss and come in the blocks' (time) order.
        u0: the identified coordinates, [d].
        n: the number of independent residuals the loss averages (for the Laplace floor).
        step: the finite-difference step in u.
        lag: the Bartlett lag over blocks (None: ``sandwich.newey_west_lag``).

    Returns:
        Per coordinate ``{"low", "high", "kind"}`` in u, as ``laplace_intervals``.
    """
    found = probe(loss_grad, u0, step=step, blocks=True)
    return interval_estimates(found, u0, n=n, step=step, lag=lag)["sandwich"]


def interval_estimates(
    found: Probes, u0: torch.Tensor, *, n: int, step: float = STEP, lag: int | None = None
) -> dict:
    """Both intervals from one set of probes.

    The Laplace variance of coordinate i is (2 L0 / n) [H^-1]_ii; the sandwich variance is
    [H^-1 J H^-1]_ii (``sandwich.hac_meat``) with Student's t quantile. The sandwich interval
    is the wider of the two: J comes from a few blocks and is itself uncertain, and a misfit
    that all blocks share (no disagreement between them) leaves J small while the Laplace
    width still reflects it. Both use the inverse of H on its curved directions; the
    directions of (near) zero or negative curvature widen each coordinate by how far following
    them within the box moves it (``box_reach``). Coordinates without curvature of their own
    are ``unconstrained`` under both.

    Returns:
        ``{"laplace": [...], "sandwich": [...] or None (no scores), "blocks": T, "lag": L}``.
    """
    d = u0.numel()
    free = [{"low": None, "high": None, "kind": "unconstrained"} for _ in range(d)]
    scores = found.scores
    out = {"laplace": list(free), "sandwich": None if scores is None else list(free)}
    if scores is not None:
        out["blocks"] = int(scores.shape[0])
        out["lag"] = newey_west_lag(out["blocks"]) if lag is None else int(lag)
    l0, hessian = found.loss, found.hessian
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
    # the inverse on the curved directions; the flat or negative ones are followed to the box
    curved = values > RANK_TOL * max(float(values.max()), 1e-300)
    kept = vectors[:, curved]
    inverse = (kept / values[curved]) @ kept.T
    down, up = box_reach(u0[seen].double(), vectors[:, ~curved])
    laplace = Z95 * (torch.diagonal(inverse) * 2.0 * max(l0, 0.0) / max(n, 1)).sqrt()
    for j, i in enumerate(seen):
        reach = (float(down[j]), float(up[j]))
        out["laplace"][i] = _interval(float(u0[i]), float(laplace[j]), reach)
    if scores is None or scores.shape[0] < 2 or not bool(torch.isfinite(scores).all()):
        return out  # the spread between blocks is unknown: the sandwich stays unconstrained
    cov = sandwich_covariance(inverse, hac_meat(scores[:, seen], out["lag"]))
    robust = t_quantile(out["blocks"]) * torch.diagonal(cov).clamp(min=0.0).sqrt()
    for j, i in enumerate(seen):
        half = max(float(robust[j]), float(laplace[j]))
        out["sandwich"][i] = _interval(float(u0[i]), half, (float(down[j]), float(up[j])))
    return out


def box_reach(u0: torch.Tensor, directions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """How far each coordinate moves down and up when u0 is moved along each direction (a
    column of ``directions``, [d, m]) as far as the box [0, 1]^d allows, both ways.

    Along a direction v the segment u0 + t v stays in the box for t in [t_lo, t_hi] (t_lo <= 0
    <= t_hi, set by the coordinates that reach a bound first); coordinate i then spans
    u0_i + t v_i over that range. The directions' reaches add up (each can be followed on its
    own, so the sum bounds what any combination reaches).

    Returns:
        (down [d], up [d]): the distances below and above u0, zero without directions.
    """
    d = u0.numel()
    down = torch.zeros(d, dtype=torch.float64)
    up = torch.zeros(d, dtype=torch.float64)
    for v in directions.double().T:
        moving = v.abs() > 1e-12
        if not bool(moving.any()):
            continue
        # the t at which each moving coordinate reaches 0 and 1
        to_zero, to_one = -u0[moving] / v[moving], (1.0 - u0[moving]) / v[moving]
        t_lo = float(torch.minimum(to_zero, to_one).max().clamp(max=0.0))
        t_hi = float(torch.maximum(to_zero, to_one).min().clamp(min=0.0))
        ends = torch.stack([t_lo * v, t_hi * v])
        down += (-ends.min(dim=0).values).clamp(min=0.0)
        up += ends.max(dim=0).values.clamp(min=0.0)
    return down, up


def _interval(u0: float, half: float, reach: tuple[float, float] = (0.0, 0.0)) -> dict:
    """``u0 +- half``, widened by ``reach`` (down, up: what flat directions move u0 by, see
    ``box_reach``), in [0, 1]: one-sided or unconstrained where it runs past a bound."""
    low, high = u0 - half - reach[0], u0 + half + reach[1]
    if low < 0.0 and high > 1.0:
        return {"low": None, "high": None, "kind": "unconstrained"}
    if low < 0.0:
        return {"low": None, "high": high, "kind": "upper-bound"}
    if high > 1.0:
        return {"low": low, "high": None, "kind": "lower-bound"}
    return {"low": low, "high": high, "kind": "two-sided"}


def interval_record(fit, vector, *, last: int, method: str = "laplace", step: float = STEP):
    """The history record of the intervals: per object and identified parameter, its 95 %
    interval in SI units by ``method``.

    Args:
        fit: a ``phases.Fit``; the loss is its objective over frames ``1..last``.
        vector: the identified ParameterVector (left as it was given).
        last: the last fitted frame.
        method: one of ``INTERVAL_METHODS``: ``laplace`` (the loss read as a Gaussian
            likelihood) or ``sandwich`` (one block per fitted frame, see
            ``mosiv_framework.pipeline.sandwich``; costs one forward-and-backward rollout more
            per parameter within a step of its bound).
        step: the finite-difference step in normalised coordinates.

    Returns:
        ``{"phase": "intervals", "horizon", "method", "intervals": {"obj1": {"E": {"low",
        "high", "kind", "method"}}, "ground_friction": {...}}}``; with ``sandwich`` also
        ``laplace`` (the Laplace intervals from the same probes, for comparison), ``blocks``
        and ``lag``. Physics-term leaves are not reported. A probe whose rollout diverges
        leaves every parameter ``unconstrained`` (the curvature there is unknown).
    """
    if method not in INTERVAL_METHODS:
        raise ValueError(
            f"identify.interval_method must be one of {list(INTERVAL_METHODS)}, got {method!r}"
        )
    record = {"phase": INTERVALS_PHASE, "horizon": last, "method": method, "intervals": {}}
    keys = [
        key
        for key, u in sorted(vector.normalized.items())
        if not key.startswith("term.") and u.numel() == 1
    ]
    if not keys:
        return record
    leaves = [vector.normalized[key] for key in keys]
    saved = [leaf.detach().clone() for leaf in leaves]
    draws = _CommonDraws(fit.objective)
    blocks = method == "sandwich"
    u0 = torch.stack([s.reshape(()) for s in saved]).double()
    try:
        loss_grad = _fit_loss_grad(fit, vector, leaves, last, draws, blocks)
        found = probe(loss_grad, u0, step=step, blocks=blocks)
    finally:
        draws.restore()
        with torch.no_grad():
            for leaf, value in zip(leaves, saved):
                leaf.copy_(value)
    estimates = interval_estimates(found, u0, n=last * len(vector.families), step=step)
    record["intervals"] = _by_parameter(vector, keys, estimates[method], method)
    if blocks:
        record["laplace"] = _by_parameter(vector, keys, estimates["laplace"], "laplace")
        record["blocks"], record["lag"] = estimates["blocks"], estimates["lag"]
    return record


def parameter_intervals(
    fit, vector, *, last: int, method: str = "laplace", step: float = STEP
) -> dict:
    """``interval_record(...)["intervals"]``."""
    return interval_record(fit, vector, last=last, method=method, step=step)["intervals"]


def _fit_loss_grad(fit, vector, leaves: list, last: int, draws, blocks: bool) -> LossGrad:
    """u -> (loss, gradient) of the fit's objective over frames 1..last with the leaves set to
    u, plus with ``blocks`` each frame's share (its loss over the number of frames: the
    objectives average over frames). Every evaluation draws the same random subsets."""

    def loss_grad(u: torch.Tensor) -> tuple:
        with torch.no_grad():
            for leaf, value in zip(leaves, u):
                leaf.fill_(float(value))
        try:
            draws.reset()
            predicted, target = fit.rollout_geometry(vector, last)
            loss = fit.objective(predicted, target)
            grads = torch.autograd.grad(loss, leaves, allow_unused=True)
        except SimulationDiverged:
            nan = torch.full((last,), math.nan, dtype=torch.float64)
            return math.inf, torch.full((len(leaves),), math.nan, dtype=torch.float64), nan
        flat = [0.0 if g is None else float(g.detach().reshape(())) for g in grads]
        out = (float(loss.detach()), torch.tensor(flat, dtype=torch.float64))
        if not blocks:
            return out
        shares = torch.zeros(len(predicted.frames), dtype=torch.float64)
        with torch.no_grad():
            for i in range(len(predicted.frames)):
                draws.reset()
                shares[i] = float(fit.objective(_frame(predicted, i), _frame(target, i)))
        return (*out, shares / len(shares))

    return loss_grad


def _frame(geometry: GeometryFrames, i: int) -> GeometryFrames:
    """The geometry of its ``i``-th frame alone."""
    silhouettes = geometry.silhouettes
    if silhouettes is not None:
        silhouettes = {k: alpha[i : i + 1] for k, alpha in silhouettes.items()}
    points = {k: [sets[i]] for k, sets in geometry.points.items()}
    return GeometryFrames([geometry.frames[i]], points, silhouettes)


class _CommonDraws:
    """The random-subset generators of the objective's terms, set back to one state before
    every evaluation: differences between probes then see the same points, not the noise of
    different subsets (and the probes leave the generators as they found them)."""

    def __init__(self, objective):
        terms = getattr(objective, "terms", {}) or {}
        gens = [getattr(term, "generator", None) for term in terms.values()]
        self.states = [(g, g.get_state()) for g in gens if isinstance(g, torch.Generator)]

    def reset(self) -> None:
        for generator, state in self.states:
            generator.set_state(state)

    def restore(self) -> None:
        """Leave the generators as the probes found them."""
        self.reset()


def _by_parameter(vector, keys: list[str], found: list[dict], method: str) -> dict:
    """Intervals in u per key -> ``{"obj1": {"E": entry}, "ground_friction": entry}`` in SI."""
    out: dict = {}
    for key, got in zip(keys, found):
        spec = vector.specs[key]
        entry = {
            "low": _si(spec, got["low"]),
            "high": _si(spec, got["high"]),
            "kind": got["kind"],
            "method": method,
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
