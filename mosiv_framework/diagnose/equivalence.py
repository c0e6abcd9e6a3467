"""Equivalent forms: what the data can tell apart, and the physical quantity it pins down.

- A uniform extra acceleration a is a steady wind a or a gravity g + a: no recording of bodies
  alone tells the two apart, so the diagnosis reports the quantity (the acceleration vector,
  the equivalent gravity vector and its magnitude) and lists both terms as equivalent
  (``uniform_acceleration``).
- Drag a = -c |v|^(p-1) v: the speed exponent p is fitted with its 95 % interval by a profile
  over p of the least-squares fit of the residual accelerations (``drag_exponent``), and the
  form is named from it: linear if the interval holds 1 and not 2, quadratic if it holds 2 and
  not 1, otherwise "drag, exponent p +- dp".
- Candidates whose held-out errors differ from the best one's by less than the rule's bootstrap
  spread predict the recording equally well: they are listed as indistinguishable
  (``indistinguishable``).
"""

from __future__ import annotations

import math

import numpy as np

from mosiv_framework.diagnose.decide import bootstrap_drop
from mosiv_framework.diagnose.kinematics import ResidualSamples

#: the exponents the drag profile scans (a = -c |v|^(p-1) v)
DRAG_EXPONENTS = np.round(np.arange(0.5, 3.0001, 0.01), 2)
#: chi-square(1) quantile of the 95 % profile interval
CHI2_95_1 = 3.841
#: candidates that are a drag law, and the exponent each assumes
DRAG_TERMS = {"linear_drag": 1.0, "quadratic_drag": 2.0}
#: candidates that add a uniform acceleration
UNIFORM_TERMS = ("wind", "gravity")


def drag_exponent(
    velocity: np.ndarray, residual: np.ndarray, *, min_speed: float = 1e-3
) -> dict | None:
    """Fit a = -c |v|^(p-1) v to residual accelerations [M, 3] at velocities [M, 3].

    For each p in ``DRAG_EXPONENTS`` c(p) is the least-squares coefficient and SSR(p) the
    residual sum of squares; the profile statistic n log(SSR(p) / SSR_min) (n = 3M) below the
    chi-square(1) 95 % quantile gives the interval. Samples slower than ``min_speed`` (m/s)
    carry no drag and are left out.

    Returns:
        {"exponent", "interval" [lo, hi], "coefficient" (units m^(1-p) s^(p-2)),
        "form", "samples"}, or None with fewer than 3 usable samples or no speed spread.
    """
    v = np.asarray(velocity, dtype=np.float64)
    a = np.asarray(residual, dtype=np.float64)
    speed = np.linalg.norm(v, axis=1)
    keep = speed > min_speed
    if keep.sum() < 3 or np.ptp(speed[keep]) <= 0:
        return None
    v, a, speed = v[keep], a[keep], speed[keep]
    ssr, coef = [], []
    for p in DRAG_EXPONENTS:
        f = -(speed ** (p - 1.0))[:, None] * v
        c = float((f * a).sum() / max((f * f).sum(), 1e-300))
        coef.append(c)
        ssr.append(float(((a - c * f) ** 2).sum()))
    ssr = np.array(ssr)
    n = a.size
    best = int(np.argmin(ssr))
    floor = max(ssr[best], 1e-30 * max(float((a * a).sum()), 1e-300))
    stat = n * np.log(np.maximum(ssr, floor) / floor)
    inside = DRAG_EXPONENTS[stat <= CHI2_95_1]
    lo, hi = float(inside.min()), float(inside.max())
    return {
        "exponent": float(DRAG_EXPONENTS[best]),
        "interval": [lo, hi],
        "coefficient": coef[best],
        "form": drag_form(float(DRAG_EXPONENTS[best]), (lo, hi)),
        "samples": int(keep.sum()),
    }


def drag_form(p: float, interval: tuple[float, float]) -> str:
    """The drag law's name from its exponent's interval (see the module docstring)."""
    lo, hi = interval
    has1, has2 = lo <= 1.0 <= hi, lo <= 2.0 <= hi
    if has1 and not has2:
        return "linear drag"
    if has2 and not has1:
        return "quadratic drag"
    return f"drag, exponent {p:.2f} +- {(hi - lo) / 2:.2f}"


def drag_from_samples(samples: dict[int, ResidualSamples]) -> dict | None:
    """``drag_exponent`` on the free-flight samples of every object together (drag is the same
    law for every body of a scene; contacts add accelerations of their own)."""
    flight = [
        s.subset(np.array([r in ("free_flight", "") for r in s.regime])) for s in samples.values()
    ]
    flight = [s for s in flight if len(s)]
    if not flight:
        return None
    return drag_exponent(
        np.concatenate([s.velocity for s in flight]), np.concatenate([s.residual for s in flight])
    )


def uniform_acceleration(name: str, value: dict | None, interval, gravity) -> dict | None:
    """The physical quantity behind a wind or gravity candidate and its equivalent terms.

    Args:
        name: the candidate ("wind" or "gravity"; None is returned for others).
        value: the candidate's physical value (``Candidate.physical``): wind's or gravity's
            ``acceleration``.
        interval: its coefficients' [lower, upper] pairs (wind: per axis; gravity: the
            magnitude change along g), or None.
        gravity: the declared gravity vector (m/s^2).

    Returns:
        {"acceleration", "acceleration_interval", "gravity", "gravity_magnitude",
        "gravity_magnitude_interval", "equivalent": [{"term", "value"}]}."""
    if name not in UNIFORM_TERMS or value is None or "acceleration" not in value:
        return None
    g = np.asarray(gravity, dtype=np.float64)
    given = np.asarray(value["acceleration"], dtype=np.float64)
    extra = given if name == "wind" else given - g
    if interval is None:
        box = None
    elif name == "wind":
        box = [list(map(float, pair)) for pair in interval]
    else:  # a magnitude change along g: the box is the segment along g's direction
        unit = g / max(np.linalg.norm(g), 1e-300)
        ends = [float(x) * unit for x in interval[0]]
        box = [[float(min(e[i] for e in ends)), float(max(e[i] for e in ends))] for i in range(3)]
    total = g + extra
    out = {
        "acceleration": extra.tolist(),
        "acceleration_interval": box,
        "gravity": total.tolist(),
        "gravity_magnitude": float(np.linalg.norm(total)),
        "gravity_magnitude_interval": None,
        "equivalent": [
            {"term": "wind", "value": {"acceleration": extra.tolist()}},
            {"term": "gravity", "value": {"acceleration": total.tolist()}},
        ],
    }
    if box is not None:
        corners = [
            np.linalg.norm(g + np.array([box[0][i], box[1][j], box[2][m]]))
            for i in (0, 1)
            for j in (0, 1)
            for m in (0, 1)
        ]
        # |g + a| over the box: its minimum is 0 if the box holds -g, else at a corner or face
        inside = all(lo <= -gi <= hi for (lo, hi), gi in zip(box, g))
        out["gravity_magnitude_interval"] = [
            0.0 if inside else float(min(corners)),
            float(max(corners)),
        ]
    return out


def indistinguishable(
    best: str,
    errors: dict[str, np.ndarray],
    names: list[str],
    heldout: list[int],
    *,
    z: float,
    block: int,
    resamples: int,
    seed: int = 0,
    statistic: str = "log",
) -> list[dict]:
    """Candidates among ``names`` whose held-out error differs from ``best``'s by less than
    ``z`` bootstrap standard deviations (``decide.bootstrap_drop`` with ``statistic``): the
    data cannot tell them apart from it."""
    out = []
    ref = errors.get(best)
    if ref is None or not heldout:
        return out
    for name in names:
        if name == best or name not in errors:
            continue
        other = errors[name][:, heldout]
        if not np.isfinite(other).all() or not np.isfinite(ref[:, heldout]).all():
            continue
        diff, spread = bootstrap_drop(
            ref[:, heldout], other, block=block, resamples=resamples, seed=seed, statistic=statistic
        )
        if math.isfinite(spread) and abs(diff) <= z * spread:
            out.append({"term": name, "heldout_difference": diff, "spread": spread})
    return out


def equivalents(evidence, errors, samples, gravity, heldout, options) -> dict:
    """What the data pin down about the best candidate that improves the model (accepted or
    not): {"best", "uniform_acceleration" (``uniform_acceleration``), "drag" (the exponent fit
    where a drag law improved the model), "equivalent": the terms that cannot be told apart
    from it: the wind/gravity pair of a uniform acceleration and the candidates that predict
    the held-out frames as well (``indistinguishable``)}."""
    explaining = [e for e in evidence if e.explains]
    if not explaining:
        return {}
    best = explaining[0]
    uniform = uniform_acceleration(best.name, best.value, best.interval, gravity)
    drag = None
    if any(e.name in DRAG_TERMS for e in explaining):
        drag = drag_from_samples(samples)
    same = indistinguishable(
        best.name,
        errors,
        [e.name for e in explaining],
        heldout,
        z=options.z,
        block=options.block,
        resamples=options.bootstrap,
        seed=options.seed,
        statistic=options.heldout_statistic,
    )
    names = [e["term"] for e in (uniform or {}).get("equivalent", [])]
    names += [e["term"] for e in same if e["term"] not in names]
    return {
        "best": best.name,
        "uniform_acceleration": uniform,
        "drag": drag,
        "indistinguishable": same,
        "equivalent": [n for n in names if n != best.name] if names else [],
    }


def prefer_drag_form(evidence: list, drag: dict | None) -> list:
    """``evidence`` with the accepted drag term of the fitted form ("linear drag" or
    "quadratic drag") moved ahead of the other accepted drag term: the two often pass alike,
    and the exponent fitted to the residual accelerations is what tells them apart."""
    if drag is None or drag["form"] not in ("linear drag", "quadratic drag"):
        return evidence
    wanted = drag["form"].replace(" ", "_")
    order = list(evidence)
    names = [e.name for e in order]
    if wanted not in names:
        return order
    i = names.index(wanted)
    other = next(
        (j for j, e in enumerate(order) if e.name in DRAG_TERMS and e.name != wanted), None
    )
    if other is not None and other < i and order[i].accepted and order[other].accepted:
        order.insert(other, order.pop(i))
    return order


def told_from_lead(forms: dict, evidence: list) -> dict:
    """``forms`` (``equivalents``) said of the candidate the diagnosis finally ranks first among
    those that improve the model. The ranking can change after ``equivalents`` ran (the drag
    form's preference, the grid check); where the new lead is one of the terms that cannot be
    told apart from the old, the two swap places, so the report never says that the named term
    cannot be told apart from another while naming the other as the reference."""
    lead = next((e.name for e in evidence if e.explains), None)
    if not forms or lead is None or lead == forms["best"] or lead not in forms["equivalent"]:
        return forms
    others = [n for n in forms["equivalent"] if n != lead]
    return {**forms, "best": lead, "equivalent": [forms["best"], *others]}
