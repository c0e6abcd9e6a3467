"""A global look over the parameter space before gradient descent.

The parameter phase is local: Adam through the simulator follows the slope from wherever it
starts, and a Chamfer or silhouette loss of a contact-rich motion is not convex in the
stiffnesses over decades (a body too stiff bounces where the recorded one squashes, and the
loss between is flat or has ridges). ``global_search`` therefore first rolls out a scrambled
Sobol design of candidates over every object's identified scale parameters, jointly, inside their
bounds (the law's ParamSpec bounds, stiffnesses already lowered to the stiffness ceiling, see
``params.stiffness_ceilings``), and keeps the best: the start competes too, so the stage never
returns something worse than it was given.

The design lives in the optimiser's normalised coordinates (``ParamSpec.to_normalized``), which
are log space for scale parameters (stiffnesses, viscosities, yield stresses, densities): 16
candidates spread E over the whole 1e3-1e7 Pa range rather than clustering in the top decade.
Only scale parameters are searched: they span decades, so a start can be far off in them; the
bounded dimensionless ones (Poisson ratios, friction coefficients, angles) keep their start.
Drawing those too made the design so sparse that the best candidate's low loss came from a
lucky mix (a Poisson ratio of 0.015 with a friction of 1.7) in a basin the descent could not
leave: on the quickstart scene the future Chamfer distance went from 132 to 3090 mm^2 (with
scale parameters only, the stage keeps the law defaults there). A candidate's loss is still only
a guess at its basin: a yield stress above every stress reached fits a short window well and has
no gradient to come back with. ``coordinate_polish`` (``identify.global_polish``) then scans each
searched parameter alone from the best candidate, which finds the edge of such a plateau.
Rollouts run without a tape over frames ``1..frames``, the candidates together in batches
(``Fit.window_losses``, i.e. ``Simulator.rollout_batch``); a candidate the simulator cannot
follow scores ``inf``. Every candidate and its loss are recorded in the history (phase ``global``,
keyed ``global_loss`` so loss plots of the gradient phases are not mixed with it).
"""

from __future__ import annotations

import logging
import math
import warnings

import torch

from mosiv_framework.errors import SimulationDiverged
from mosiv_framework.pipeline.params import ParameterVector

log = logging.getLogger(__name__)

#: the history's phase name of the global stage
PHASE = "global"
#: the history's phase name of the coordinate sweep after it
POLISH = "global-polish"


def searched_keys(vector: ParameterVector) -> list[str]:
    """The normalised leaves the global stage designs over: every log-scale object parameter
    (physics-term leaves, which may be vectors, and linear parameters keep their start)."""
    return [
        key
        for key, u in sorted(vector.normalized.items())
        if key.startswith("obj") and u.numel() == 1 and vector.specs[key].log_scale
    ]


def sobol_design(n: int, dims: int, *, seed: int) -> torch.Tensor:
    """``n`` points of a scrambled Sobol sequence in [0, 1]^dims, [n, dims] float32.

    Sobol's balance properties hold for powers of two; other ``n`` are allowed (the design is
    then the first ``n`` points of the sequence), so scipy's warning about it is silenced."""
    from scipy.stats import qmc

    engine = qmc.Sobol(d=dims, scramble=True, seed=seed)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        points = engine.random(n)
    return torch.as_tensor(points, dtype=torch.float32)


def global_search(
    fit, vector: ParameterVector, *, candidates: int, frames: int, seed: int, history: list
) -> dict:
    """Score ``candidates`` Sobol points (and the current leaves) over frames ``1..frames`` and
    leave ``vector`` at the best of them; appends one history record per candidate.

    Args:
        fit: a ``phases.Fit`` (simulator, particles, world, targets, objective).
        vector: the parameter vector, changed in place (velocities are kept).
        candidates: how many design points (0: nothing is done).
        frames: the last frame of the rollouts.
        seed: the scrambling seed (the same seed gives the same design).
        history: the identification history the records are appended to.

    Returns:
        ``{"best": index (-1: the start), "best_loss", "start_loss", "losses": [...]}``.
    """
    keys = searched_keys(vector)
    if candidates <= 0 or not keys:
        return {"best": -1, "best_loss": math.nan, "start_loss": math.nan, "losses": []}
    vector.keep_stable()  # every point scored is one the simulator can follow
    start = torch.stack([vector.normalized[key].detach().clone().reshape(()) for key in keys])
    start_values = vector.to_json()
    start_loss = _score(fit, vector, frames)
    design = sobol_design(candidates, len(keys), seed=seed)
    # the candidates rolled out together (Fit.window_losses), 16 of them in one simulation
    values, params, scored = _members(vector, keys, list(design))
    points = [start, *scored]
    values.insert(0, start_values)
    losses = fit.window_losses(params, frames)
    best, best_loss = -1, start_loss
    history.append(_record(-1, frames, start_loss, values[0]))
    for i, loss in enumerate(losses):
        history.append(_record(i, frames, loss, values[i + 1]))
        log.info("global candidate %d/%d: loss %.4g", i + 1, candidates, loss)
        if loss < best_loss:
            best, best_loss = i, loss
    _set(vector, keys, points[best + 1])
    log.info(
        "global stage: %s (loss %.4g; start %.4g)%s",
        "kept the start" if best < 0 else f"candidate {best + 1} of {candidates}",
        best_loss,
        start_loss,
        _short(vector, keys),
    )
    return {"best": best, "best_loss": best_loss, "start_loss": start_loss, "losses": losses}


def coordinate_polish(
    fit, vector: ParameterVector, *, points: int, frames: int, history: list
) -> dict:
    """One sweep over the searched parameters, one at a time: each is set to ``points`` values
    spread evenly over its normalised range (log-even for scale parameters) with the others
    held, and kept at the best of those and its current value. Leaves ``vector`` at the result.

    The Sobol design samples all parameters jointly, so with a few candidates each parameter
    gets only a few values, and a candidate can win with one of them far off where the loss
    over the window does not depend on it, e.g. a yield stress above every stress the body
    reaches, whose gradient is then exactly zero and which descent can never lower. A scan
    along each coordinate finds such plateaus' edges at ``points`` rollouts a parameter.

    Args:
        fit: a ``phases.Fit`` (simulator, particles, world, targets, objective).
        vector: the parameter vector, changed in place (velocities are kept).
        points: values tried per parameter (0: nothing is done).
        frames: the last frame of the rollouts.
        history: the identification history; one record per rollout (phase ``global-polish``).

    Returns:
        ``{"start_loss", "best_loss", "changed": [keys moved]}``.
    """
    keys = searched_keys(vector)
    if points <= 0 or not keys:
        return {"start_loss": math.nan, "best_loss": math.nan, "changed": []}
    vector.keep_stable()  # every point scored is one the simulator can follow
    best_loss = start_loss = _score(fit, vector, frames)
    changed = []
    for key in keys:
        here = torch.stack([vector.normalized[k].detach().clone().reshape(()) for k in keys])
        axis = keys.index(key)
        tried = []
        for j in range(points):  # the others held where the sweep has left them
            point = here.clone()
            point[axis] = (j + 0.5) / points
            tried.append(point)
        values, params, tried = _members(vector, keys, tried)
        kept = here
        for j, loss in enumerate(fit.window_losses(params, frames)):
            history.append(
                {**_record(j, frames, loss, values[j]), "phase": POLISH, "parameter": key}
            )
            if loss < best_loss:
                best_loss, kept = loss, tried[j]
                changed.append(key)
        _set(vector, keys, kept)
    changed = sorted(set(changed))
    log.info(
        "global polish: loss %.4g -> %.4g, moved %s%s",
        start_loss,
        best_loss,
        ", ".join(changed) or "nothing",
        _short(vector, keys),
    )
    return {"start_loss": start_loss, "best_loss": best_loss, "changed": changed}


def _members(vector: ParameterVector, keys: list[str], points: list[torch.Tensor]):
    """For each point of the searched leaves: the vector's values (for the history), its
    detached SimulationParams (for ``Fit.window_losses``) and the point as set (``_set``: a
    stiffness past the simulator's stability limit lowered to it). Leaves the vector at the
    last."""
    values, params, scored = [], [], []
    for point in points:
        scored.append(_set(vector, keys, point))
        values.append(vector.to_json())
        params.append(vector.physical().detached())
    return values, params, scored


def _score(fit, vector: ParameterVector, frames: int) -> float:
    """The objective over frames 1..frames without a tape; inf when the rollout diverges or
    the loss is not finite."""
    try:
        value = fit.window_loss(vector, frames)
    except SimulationDiverged:
        return math.inf
    return value if math.isfinite(value) else math.inf


def _set(vector: ParameterVector, keys: list[str], point: torch.Tensor) -> torch.Tensor:
    """The searched leaves at ``point``, then every stiffness held to the simulator's
    stability limit (``ParameterVector.keep_stable``); returns the point as set."""
    with torch.no_grad():
        for key, u in zip(keys, point):
            vector.normalized[key].copy_(u.reshape(vector.normalized[key].shape))
    vector.keep_stable()
    return torch.stack([vector.normalized[key].detach().clone().reshape(()) for key in keys])


def _record(index: int, frames: int, loss: float, values: dict) -> dict:
    """A history record of one candidate (index -1: the start) with its vector's values."""
    return {
        "phase": PHASE,
        "candidate": index,
        "horizon": frames,
        "global_loss": loss if math.isfinite(loss) else None,
        "values": values,
    }


def _short(vector: ParameterVector, keys: list[str]) -> str:
    """``; obj1.E=1.2e+05, ...`` for the log."""
    parts = []
    for key in keys:
        value = float(vector.specs[key].from_normalized(vector.normalized[key].detach()))
        parts.append(f"{key}={value:.3g}")
    return "; " + ", ".join(parts)
