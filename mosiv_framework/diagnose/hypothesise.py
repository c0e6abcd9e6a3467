"""Step 2 of a diagnosis: which candidate effects could explain the residual?

Screening is first order plus one probe, through the differentiable simulator:
1. one rollout with every allowed candidate switched on at zero (the fitted model itself) and
   one backward pass give the gradient g of the observed loss with respect to each coefficient;
2. per candidate, one more rollout at a probe step along the descent direction d (projected on
   the sign constraints) gives the curvature h along d, so the quadratic model
   L(a) = L0 + (g.d) a + h a^2 / 2 predicts the best step a* and the loss drop it buys; a few
   longer steps out to the bound are rolled out too, and one that beats the model's prediction
   (or the probe, where h < 0 and the model has no minimum) replaces a*;
3. candidates are ranked by a BIC-style score of that drop,
   n log(L0 / (L0 - drop)) - dim log n, with n the frame-object residual count, so a
   three-coefficient term must explain more than a one-coefficient term to rank above it.
A candidate is allowed only if it acts in a regime the location flagged (``PhysicsTerm.regimes``).
Candidates whose loss is flat at zero (plasticity: nothing yields at an unreachable yield
stress) have no useful gradient there; they are probed on their ``ladder`` of coefficients
instead, and the best rung gives the predicted drop and the refit's start.

For body-force candidates a second, simulator-free estimate of the coefficient comes from the
centroid paths: in free flight an extra acceleration a(v; theta) shifts an object's centroid by
its double time integral, and a changed initial velocity by dv0 t; least squares of the
centroid residual on both (``regression_estimate``) gives theta net of what the initial
velocity can absorb, which is where a refit should start. The screen also rolls the model out
at that estimate (``regression_drop``): the probe along the gradient at zero can undersell a
3-vector effect (a sideways wind, whose gradient at zero mixes with what the velocities already
absorbed), while the regression lands near its coefficient directly. A candidate's predicted
drop is the better of the two.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
import torch

from mosiv_framework.diagnose.candidates import Candidate
from mosiv_framework.diagnose.context import RunContext
from mosiv_framework.errors import SimulationDiverged
from mosiv_framework.types import SimulationParams


@dataclass
class Screen:
    """The screening result of one candidate; ``theta`` is the predicted best coefficient."""

    candidate: Candidate
    allowed: bool
    gradient: list[float]
    theta: torch.Tensor
    drop_fraction: float
    score: float
    note: str = ""
    regression: tuple[torch.Tensor, dict[int, torch.Tensor]] | None = None
    #: BIC decrease of the free-flight centroid regression (``regression_gain``)
    regression_gain: float | None = None
    #: the walk's furthest point along the descent direction (the bound, or FALLBACK_SPAN
    #: natural steps): a refit start for an effect whose loss falls only far from zero
    far: torch.Tensor | None = None

    def to_json(self) -> dict:
        return {
            "name": self.candidate.name,
            "allowed": self.allowed,
            "regimes": sorted(self.candidate.regimes),
            "coefficients": self.candidate.coefficient_names,
            "gradient": self.gradient,
            "predicted_theta": self.theta.tolist(),
            "predicted_drop_fraction": self.drop_fraction,
            "score": self.score if math.isfinite(self.score) else None,
            "regression_theta": None if self.regression is None else self.regression[0].tolist(),
            "regression_gain": self.regression_gain,
            "far_theta": None if self.far is None else self.far.tolist(),
            "note": self.note,
        }


def bic_gain(fraction: float, *, n: int, dim: int) -> float:
    """BIC decrease for explaining ``fraction`` of a Gaussian residual with ``dim`` new
    coefficients from ``n`` residuals: n log(1 / (1 - fraction)) - dim log n."""
    fraction = min(max(fraction, 0.0), 1.0 - 1e-12)
    return -n * math.log1p(-fraction) - dim * math.log(n)


def _double_integral(a: np.ndarray, dt: float) -> np.ndarray:
    """Displacement [T, 3] (m) from accelerations [T, 3] (m/s^2) at frames, starting at rest
    (trapezoidal rule twice)."""
    v = np.concatenate([np.zeros((1, 3)), np.cumsum(0.5 * (a[1:] + a[:-1]), axis=0) * dt])
    return np.concatenate([np.zeros((1, 3)), np.cumsum(0.5 * (v[1:] + v[:-1]), axis=0) * dt])


def _regression_system(
    ctx: RunContext,
    candidate: Candidate | None,
    residuals: dict,
    regimes: dict[int, list[str]],
    fit_frames: list[int],
) -> tuple[np.ndarray, np.ndarray, list[int]] | None:
    """The least-squares system of ``regression_estimate``: design [rows, dim + 3 objects],
    targets [rows] (m) and the objects in column order; None where it has no rows."""
    dt = 1.0 / ctx.fps
    objects = sorted(residuals)
    dim = 0 if candidate is None else candidate.dim
    fitted = set(fit_frames)  # held-out frames must not inform a refit's start either
    blocks, targets = [], []
    for index, k in enumerate(objects):
        m = 0
        while m <= max(fit_frames) and m < len(regimes[k]) and regimes[k][m] == "free_flight":
            m += 1
        if m < 3:
            continue
        velocity = torch.as_tensor(residuals[k].sim_velocity[:m], dtype=torch.float32)
        columns = []
        for j in range(dim):
            unit = candidate.zero()
            unit[j] = float(candidate.step[j])
            a = candidate.acceleration(velocity, unit)
            if a is None:
                return None
            columns.append(_double_integral(a.double().numpy() / float(candidate.step[j]), dt))
        design = np.zeros((m, 3, dim + 3 * len(objects)))
        if columns:
            design[:, :, :dim] = np.stack(columns, axis=-1)
        for axis in range(3):
            design[:, axis, dim + 3 * index + axis] = np.arange(m) * dt
        rows = [t for t in range(1, m) if t in fitted]
        if len(rows) < 2:
            continue
        blocks.append(design[rows].reshape(-1, design.shape[-1]))
        targets.append(residuals[k].centroid[rows].reshape(-1))
    if not blocks:
        return None
    return np.concatenate(blocks), np.concatenate(targets), objects


def _least_squares(design: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, float]:
    """Coefficients (columns without rows stay 0) and residual sum of squares (m^2)."""
    coef = np.zeros(design.shape[1])
    used = np.abs(design).sum(axis=0) > 0  # velocity columns of objects without rows
    coef[used] = np.linalg.lstsq(design[:, used], y, rcond=None)[0]
    return coef, float(((design @ coef - y) ** 2).sum())


def regression_estimate(
    ctx: RunContext,
    candidate: Candidate | None,
    residuals: dict,
    regimes: dict[int, list[str]],
    fit_frames: list[int],
) -> tuple[torch.Tensor, dict[int, torch.Tensor]] | None:
    """Least-squares (theta, initial-velocity change per object) from free-flight centroids.

    Per object, the fit frames of its free flight from frame 0 on give rows
    r_k(t) = sum_j theta_j X_kj(t) + dv0_k t dt per axis, X_kj the double integral of the
    candidate's acceleration at unit coefficient j along the simulated centroid velocity. With
    ``candidate`` None only dv0 is estimated (the null model's start). Returns None if the
    candidate is not a body force or no object has 3 free-flight frames (2 of them fitted).
    """
    system = _regression_system(ctx, candidate, residuals, regimes, fit_frames)
    if system is None:
        return None
    design, y, objects = system
    dim = 0 if candidate is None else candidate.dim
    coef, _ = _least_squares(design, y)
    theta = torch.tensor(coef[:dim], dtype=torch.float32)
    if candidate is not None:
        theta = candidate.clamp(theta)
    dv0 = {
        k: torch.tensor(coef[dim + 3 * i : dim + 3 * i + 3], dtype=torch.float32)
        for i, k in enumerate(objects)
    }
    return theta, dv0


def regression_gain(
    ctx: RunContext,
    candidate: Candidate,
    residuals: dict,
    regimes: dict[int, list[str]],
    fit_frames: list[int],
) -> float | None:
    """BIC decrease of the free-flight centroid regression when ``candidate``'s columns join
    the initial-velocity change: N log(RSS_velocity / RSS_candidate) - dim log N over its N
    rows; None for a candidate without a regression.

    This reads the candidate's signature straight off the paths, where the rollout at its
    estimate (``regression_drop``) also carries every later frame: a sideways wind regressed
    exactly (2.5 m/s^2 of 2.5) still scored no drop, because the identified material
    parameters, biased by the missing wind, spoiled the collision after it (wind-1, full
    suite)."""
    system = _regression_system(ctx, candidate, residuals, regimes, fit_frames)
    if system is None:
        return None
    design, y, _ = system
    _, rss = _least_squares(design, y)
    _, rss_velocity = _least_squares(design[:, candidate.dim :], y)
    floor = 1e-12 * max(float((y**2).sum()), 1e-30)  # an exact fit is not infinitely good
    n = len(y)
    return n * math.log(max(rss_velocity, floor) / max(rss, floor)) - candidate.dim * math.log(n)


def shifted_velocities(params, velocity_change: dict | None):
    """``params`` with each object's initial velocity moved by ``velocity_change`` (m/s)."""
    if not velocity_change:
        return params
    moved = {
        k: v + velocity_change[k].to(v) if k in velocity_change else v
        for k, v in params.initial_velocity.items()
    }
    return replace(params, initial_velocity=moved)


def regression_params(
    ctx: RunContext,
    candidate: Candidate,
    regression: tuple[torch.Tensor, dict[int, torch.Tensor]],
) -> SimulationParams:
    """The identified model with ``candidate`` at its regression estimate: coefficients and
    initial-velocity change together."""
    theta, velocity_change = regression
    return candidate.apply(shifted_velocities(ctx.identified, velocity_change), theta)


def drop_below(loss: float, reference: float) -> float:
    """Fraction of ``reference`` that ``loss`` removes; 0 for a loss not lower, not finite
    (a diverged rollout) or a reference that is not positive."""
    if not math.isfinite(loss) or reference <= 0:
        return 0.0
    return max(0.0, (reference - loss) / reference)


def regression_drop(
    ctx: RunContext,
    candidate: Candidate,
    regression: tuple[torch.Tensor, dict[int, torch.Tensor]],
    *,
    reference: float,
    fit_frames: list[int],
) -> float:
    """Fraction of ``reference`` that the model with ``candidate`` at its regression estimate
    (``regression_params``) removes from the loss on ``fit_frames``; 0 if it does not lower it
    or the rollout diverges. The screening rolls this model out in the batch of its probe and
    walk (``_screen_by_gradient``); this is the same number alone.

    ``reference`` should be the lower of the identified model's loss and the null model's at
    the null regression's velocity change, so the velocity change alone earns no credit."""
    params = regression_params(ctx, candidate, regression)
    try:
        with torch.no_grad():
            loss = float(ctx.loss(ctx.rollout(params, frames=max(fit_frames)), fit_frames))
    except SimulationDiverged:
        return 0.0
    return drop_below(loss, reference)


def _max_step(candidate: Candidate, direction: torch.Tensor) -> float:
    """Largest a with a * direction inside the candidate's bounds (theta starts at 0)."""
    limit = math.inf
    for d, lo, hi in zip(direction.tolist(), candidate.lower.tolist(), candidate.upper.tolist()):
        if d > 0:
            limit = min(limit, hi / d)
        elif d < 0:
            limit = min(limit, lo / d)
    return limit


#: rungs probed, per allowed sign, when a scalar candidate's gradient at zero gives no descent
#: direction (a contact effect such as a bounce can leave the loss flat at zero): evenly spaced
#: in log from its natural step to its bound, or to FALLBACK_SPAN steps if the bound is further
FALLBACK_RUNGS = 5
FALLBACK_SPAN = 100.0


def _walk_end(limit: float) -> float | None:
    """How many natural steps the walk goes out to (the bound, or FALLBACK_SPAN steps); None
    if that is no further than the probe."""
    top = min(limit, FALLBACK_SPAN)
    return top if top > 1.0 else None


def _probe_and_walk(
    ctx: RunContext,
    c: Candidate,
    direction: torch.Tensor,
    limit: float,
    *,
    fit_frames: list[int],
    also: tuple[SimulationParams, ...] = (),
) -> tuple[float, float, float, list[float]]:
    """(probe, step, loss, also_losses): the loss one natural step along ``direction`` (the
    probe), and the best of FALLBACK_RUNGS - 1 steps beyond it, evenly spaced in log from it to
    the bound (or FALLBACK_SPAN steps); (nan, inf) for the walk if there is no room or every
    rollout diverges; and the loss of each model of ``also`` (inf where it diverges). All are
    rolled out together (``RunContext.rollout_losses``); a probe that did not come back finite
    is rolled out again alone, so that a divergence raises SimulationDiverged with its reason.

    The probe's quadratic model sees the loss one natural step from zero only. A bounce lowers
    the loss slowly at small restitution and fast at large: at the generator's other parameters,
    ground_restitution-1's loss falls from 41 mm^2 at e = 0 to 33 at 0.15 and to 0 at its
    concealed 0.9. The model predicted 0.16 there, and refits begun near it ended at
    0.14-0.21; checking a few longer steps starts them near the loss's real minimum."""
    top = _walk_end(limit)
    steps = (
        [] if top is None else [top ** (i / (FALLBACK_RUNGS - 1)) for i in range(1, FALLBACK_RUNGS)]
    )
    thetas = [direction] + [step * direction for step in steps]
    params_list = [c.apply(ctx.identified, theta) for theta in thetas] + list(also)
    all_losses = ctx.rollout_losses(params_list, fit_frames)
    probe, losses, also_losses = (
        all_losses[0],
        all_losses[1 : len(thetas)],
        all_losses[len(thetas) :],
    )
    if not math.isfinite(probe):
        traj = ctx.rollout(c.apply(ctx.identified, direction), frames=max(fit_frames))
        probe = float(ctx.loss(traj, fit_frames))
    best_step, best_loss = math.nan, math.inf
    for step, loss in zip(steps, losses):
        if loss < best_loss:
            best_step, best_loss = step, loss
    return probe, best_step, best_loss, also_losses


def _losses_at(
    ctx: RunContext, c: Candidate, thetas: list[torch.Tensor], *, fit_frames: list[int]
) -> list[float]:
    """Fit-frame loss of the run's identified model with ``c`` on at each of ``thetas`` (inf
    where the rollout diverges); the probes are independent, so they are rolled out together
    (``RunContext.rollout_losses``)."""
    params_list = [c.apply(ctx.identified, theta) for theta in thetas]
    return ctx.rollout_losses(params_list, fit_frames)


def _screen_ladder(
    ctx: RunContext,
    c: Candidate,
    base: float,
    *,
    n: int,
    fit_frames: list[int],
    rungs: tuple[float, ...] | None = None,
) -> Screen:
    """Probe ``c`` at each rung of ``rungs`` (default: its ladder); the lowest loss is the
    predicted best."""
    rungs = c.ladder if rungs is None else rungs
    thetas = [c.clamp(torch.full((c.dim,), float(rung))) for rung in rungs]
    losses = _losses_at(ctx, c, thetas, fit_frames=fit_frames)
    best_theta, best_loss = c.zero(), base
    for theta, loss in zip(thetas, losses):
        if loss < best_loss:
            best_theta, best_loss = theta, loss
    fraction = max(0.0, (base - best_loss) / base) if base > 0 else 0.0
    note = "ladder " + ", ".join(f"{r:g}: {loss:.3g}" for r, loss in zip(rungs, losses))
    if fraction == 0.0:
        return Screen(c, True, [], c.zero(), 0.0, -math.inf, note + " (no rung lowers the loss)")
    return Screen(c, True, [], best_theta, fraction, bic_gain(fraction, n=n, dim=c.dim), note)


def _screen_flat(
    ctx: RunContext, c: Candidate, base: float, g: torch.Tensor, *, n: int, fit_frames: list[int]
) -> Screen:
    """A candidate whose gradient at zero gives no descent direction: a scalar one is probed on
    a log ladder from its natural step towards each bound it has room for (without it, ground
    restitution had "no descent direction" on both restitution scenes of the full suite and
    was never refitted)."""
    flat = Screen(c, True, g.tolist(), c.zero(), 0.0, -math.inf, "no descent direction")
    step = float(c.step[0]) if c.dim == 1 else 0.0
    rungs = []
    for sign, bound in ((1.0, float(c.upper[0])), (-1.0, -float(c.lower[0]))):
        if step <= 0 or bound < step:
            continue
        ratio = min(bound, FALLBACK_SPAN * step) / step
        rungs += [sign * step * ratio ** (i / (FALLBACK_RUNGS - 1)) for i in range(FALLBACK_RUNGS)]
    if not rungs:
        return flat
    probed = _screen_ladder(ctx, c, base, n=n, fit_frames=fit_frames, rungs=tuple(rungs))
    return replace(probed, gradient=g.tolist(), note="no descent direction at 0; " + probed.note)


def screen(
    ctx: RunContext,
    candidates: list[Candidate],
    *,
    flagged_regimes: list[str],
    fit_frames: list[int],
    residuals: dict | None = None,
    regimes: dict[int, list[str]] | None = None,
) -> list[Screen]:
    """Screen ``candidates`` on the loss over ``fit_frames``; returns them best first.

    A candidate acting in none of ``flagged_regimes`` is not screened. A candidate with a
    ladder (``Candidate.ladder``) is read off its rungs (``_screen_ladder``); every other one
    from the loss's gradient at zero, a probe one natural step along the descent direction and
    a walk further out (``_screen_by_gradient``). ``residuals`` and ``regimes`` (the location's)
    add the free-flight regression's estimate where a candidate has one.
    """
    allowed = [c for c in candidates if c.regimes & set(flagged_regimes)]
    out = [
        Screen(c, False, [], c.zero(), 0.0, -math.inf, f"acts only in {sorted(c.regimes)}")
        for c in candidates
        if c not in allowed
    ]
    if not allowed:
        return out
    n = len(fit_frames) * len(ctx.object_ids)
    laddered = [c for c in allowed if c.ladder is not None]
    by_gradient = [c for c in allowed if c.ladder is None]
    base, thetas = _loss_at_zero(ctx, by_gradient, fit_frames)
    out += [_screen_ladder(ctx, c, base, n=n, fit_frames=fit_frames) for c in laddered]
    reference = base  # what a velocity change alone reaches: candidates get no credit for it
    if residuals is not None and regimes is not None:
        reference = _velocity_only_loss(ctx, base, residuals, regimes, fit_frames)
    for c, theta in zip(by_gradient, thetas):
        out.append(
            _screen_by_gradient(
                ctx,
                c,
                theta.grad.detach().clone(),
                base,
                reference,
                n=n,
                fit_frames=fit_frames,
                residuals=residuals,
                regimes=regimes,
            )
        )
    out.sort(key=lambda s: s.score, reverse=True)
    return out


def _loss_at_zero(
    ctx: RunContext, by_gradient: list[Candidate], fit_frames: list[int]
) -> tuple[float, list[torch.Tensor]]:
    """The loss of the run's identified model over the fit frames, and each of ``by_gradient``
    's zero coefficient with the loss's gradient in ``.grad`` (one rollout for all)."""
    thetas = [c.zero().requires_grad_(True) for c in by_gradient]
    params = ctx.identified.detached()
    for c, theta in zip(by_gradient, thetas):
        params = c.apply(params, theta)
    with torch.set_grad_enabled(bool(by_gradient)):
        loss0 = ctx.loss(ctx.simulate(params, frames=max(fit_frames)), fit_frames)
    if by_gradient:
        loss0.backward()
    return float(loss0.detach()), thetas


def _velocity_only_loss(
    ctx: RunContext, base: float, residuals: dict, regimes: dict, fit_frames: list[int]
) -> float:
    """The lower of ``base`` and the loss with the initial-velocity change the null model's
    centroid regression implies (``base`` where there is none or its rollout fails)."""
    null = regression_estimate(ctx, None, residuals, regimes, fit_frames)
    if null is None:
        return base
    try:
        with torch.no_grad():
            moved = shifted_velocities(ctx.identified, null[1])
            loss = float(ctx.loss(ctx.rollout(moved, frames=max(fit_frames)), fit_frames))
    except SimulationDiverged:
        return base
    return min(base, loss) if math.isfinite(loss) else base


def _screen_by_gradient(
    ctx: RunContext,
    c: Candidate,
    g: torch.Tensor,
    base: float,
    reference: float,
    *,
    n: int,
    fit_frames: list[int],
    residuals: dict | None,
    regimes: dict | None,
) -> Screen:
    """One candidate screened from the gradient ``g`` of the loss at zero: the quadratic model
    through a probe one natural step along the descent direction, a walk further out, and
    (with ``residuals``) the regression estimate, whichever predicts the larger drop."""
    # descent direction preconditioned by each coefficient's natural size, then one
    # natural step long
    direction = -g * c.step**2
    at_lower = (direction < 0) & (c.lower >= 0)
    at_upper = (direction > 0) & (c.upper <= 0)
    direction[at_lower | at_upper] = 0.0
    size = float((direction / c.step).norm())
    if size == 0.0:
        return _screen_flat(ctx, c, base, g, n=n, fit_frames=fit_frames)
    direction = direction / size
    slope = float(g @ direction)
    limit = _max_step(c, direction)
    regression, gain = None, None
    if residuals is not None and regimes is not None:
        regression = regression_estimate(ctx, c, residuals, regimes, fit_frames)
        gain = regression_gain(ctx, c, residuals, regimes, fit_frames)
    also = () if regression is None else (regression_params(ctx, c, regression),)
    try:
        probe, far, far_loss, also_losses = _probe_and_walk(
            ctx, c, direction, limit, fit_frames=fit_frames, also=also
        )
    except SimulationDiverged as exc:
        return Screen(c, True, g.tolist(), c.zero(), 0.0, -math.inf, f"probe diverged: {exc}")
    curvature = 2.0 * (float(probe) - base - slope)
    if curvature > 0:
        step = min(-slope / curvature, limit)
        predicted = base + slope * step + 0.5 * curvature * step**2
    else:  # concave: the quadratic model has no minimum; the probe is what is known
        step, predicted = 1.0, float(probe)
    note = ""
    top = _walk_end(limit)
    if far_loss < predicted:
        step, predicted = far, far_loss
        note = f"walked {far:.3g} steps along the descent direction; "
    fraction = max(0.0, (base - predicted) / base) if base > 0 else 0.0
    if regression is not None:
        by_regression = drop_below(also_losses[0], reference)
        note += f"probe drop {fraction:.3g}, regression drop {by_regression:.3g}"
        fraction = max(fraction, by_regression)
    return Screen(
        c,
        True,
        g.tolist(),
        (step * direction).detach(),
        fraction,
        bic_gain(fraction, n=n, dim=c.dim),
        note,
        regression=regression,
        regression_gain=gain,
        far=None if top is None else (top * direction).detach(),
    )


#: a regression gain (BIC decrease) this large is "very strong" evidence (Kass and Raftery
#: 1995: 2 log Bayes factor > 10) that the candidate's signature is in the flight paths
REGRESSION_SLOT_GAIN = 10.0


def choose_refits(screens: list[Screen], max_candidates: int) -> list[Screen]:
    """The candidates to refit: the ``max_candidates`` best-scored that promise a drop, and
    one more, the candidate with the strongest free-flight regression, when that regression is
    very strong evidence (``REGRESSION_SLOT_GAIN``) but its score left it out.

    The score ranks by the drop of a rollout over the whole window, which a body force's
    collision aftermath can hide; the extra slot costs one refit and decides nothing: the
    evidence test still judges it against the null like every other candidate."""
    kept = [s for s in screens if s.allowed and s.drop_fraction > 0][:max_candidates]
    left_out = [
        s
        for s in screens
        if s.allowed
        and all(s is not k for k in kept)  # by identity: a Screen holds tensors
        and s.regression_gain is not None
        and s.regression_gain >= REGRESSION_SLOT_GAIN
    ]
    if left_out:
        kept.append(max(left_out, key=lambda s: s.regression_gain))
    return kept
