"""The discovered formula as a model: an ``expression`` candidate from ``discover``'s result.

When no library term explains the residual, discovery writes it as a sparse law per axis,
a_axis = sum c phi (``discover``). Here that law becomes a ``Candidate`` of kind
``expression`` (the physics term of ``mosiv_framework.expression``, applied by the simulator
on its grid nodes): one coefficient per kept (axis, feature) pair, started at the discovered
value, refitted jointly with the run's free parameters through the differentiable rollout
(``model.refit``) and judged by the same held-out, information-criterion, interval and
physical-evidence tests as every library term (``decide``, ``physical``).

Discovery may keep features no simulator applies per node (the contact indicator) or that the
run's simulator cannot (the other objects' features without one velocity field per object);
``applicable_features`` says which it may use, and the diagnosis repeats the discovery within
those before building the candidate.
"""

from __future__ import annotations

import numpy as np
import torch

from mosiv_framework.diagnose.candidates import Candidate
from mosiv_framework.diagnose.discover import AXES, discover, feature_library, formula
from mosiv_framework.diagnose.locate import object_residuals
from mosiv_framework.expression import (
    FEATURES,
    NAME,
    NODE_FEATURES,
    ExpressionTerm,
    acceleration,
    coefficient_name,
    node_features,
    parse_coefficient,
    up_vector,
)

#: the expression's natural step: this fraction of a discovered coefficient (the refit's scale
#: and the interval's difference step), at least STEP_FLOOR of the coefficient's bound
STEP_FRACTION = 0.1
STEP_FLOOR = 1e-3


def applicable_features(simulator, contact: str | None) -> tuple[str, ...] | None:
    """The features an expression candidate may use on ``simulator`` (None: it has no
    expression term): the node-local ones, and the other objects' with one velocity field
    per object (``contact`` multi_field), of those the simulator applies
    (``Simulator.expression_features``)."""
    if NAME not in set(getattr(simulator, "supported_terms", ())):
        return None
    usable = FEATURES if contact in (None, "multi_field") else NODE_FEATURES
    applied = getattr(simulator, "expression_features", None) or FEATURES
    return tuple(f for f in usable if f in applied)


def scene_up(world) -> tuple[float, float, float]:
    """The scene's up (opposite its gravity), as discovery and the expression term use it."""
    return tuple(up_vector(world.gravity).tolist())


def discover_law(ctx, samples: dict) -> dict | None:
    """``discover`` on the residual samples of a run (``RunContext``) in its scene's frame."""
    return discover(samples, up=scene_up(ctx.world), ground_height=ctx.world.ground_height)


def law_to_test(ctx, samples: dict, discovered: dict | None) -> tuple[dict | None, str | None]:
    """(law, reason): the discovered law an expression candidate is built from, or None and
    why none is. Where ``discovered`` keeps a feature the run's simulator cannot apply, the
    discovery is repeated within those it can."""
    section = ctx.recipe.get("diagnose", None)
    if section is not None and (
        NAME in section.exclude or (section.terms and NAME not in section.terms)
    ):
        return None, f"{NAME}: left out by the recipe's diagnose.terms / diagnose.exclude"
    # the simulator's own option: identification may have chosen the contact (identify.contact)
    contact = getattr(getattr(ctx.simulator, "options", None), "contact", None)
    features = applicable_features(ctx.simulator, contact)
    if features is None:
        return None, f"{NAME}: simulator {ctx.simulator_name!r} does not implement it"
    if NAME in ctx.identified.terms:
        return None, f"{NAME}: already part of the fitted model"
    kept = {t["feature"] for ax in (discovered or {}).get("axes", {}).values() for t in ax["terms"]}
    law = discovered
    if discovered is not None and not kept <= set(features):
        law = discover(
            samples,
            up=scene_up(ctx.world),
            ground_height=ctx.world.ground_height,
            features=features,
        )
    if law is None or not any(ax["terms"] for ax in law["axes"].values()):
        return None, f"{NAME}: the discovered law keeps no term the simulator can apply"
    return law, None


def expression_candidate(discovered: dict | None, *, up, ground_height) -> Candidate | None:
    """The candidate of a ``discover`` result: one coefficient per kept (axis, feature) pair,
    its start (``base["start"]``) the discovered value, its bounds the term's; None if the law
    keeps no term or a feature the expression term lacks. ``up`` and ``ground_height`` are
    the scene's, as the discovery used them (the height feature and ``object_designs``)."""
    if not discovered:
        return None
    term = ExpressionTerm()
    specs = {spec.name: spec for spec in term.params}
    names, start = [], []
    for axis in AXES:
        for t in discovered["axes"][axis]["terms"]:
            if t["feature"] not in FEATURES:
                return None
            names.append(coefficient_name(axis, t["feature"]))
            start.append(t["coefficient"])
    if not names:
        return None
    lower = torch.tensor([specs[n].lower for n in names])
    upper = torch.tensor([specs[n].upper for n in names])
    step = torch.maximum(
        STEP_FRACTION * torch.tensor(start).abs(), STEP_FLOOR * (upper - lower)
    ).float()
    return Candidate(
        NAME,
        "expression",
        names,
        [specs[n].unit for n in names],
        lower,
        upper,
        step,
        term.regimes,
        "discovered force law " + discovered["formula"],
        term,
        {
            "start": torch.tensor(start, dtype=torch.float32),
            "up": tuple(float(x) for x in up),
            "ground_height": ground_height,
            "discovered": discovered["formula"],
        },
    )


def expression_starts(candidate: Candidate, count: int, velocity_change=None) -> list:
    """Refit starts: the discovered coefficients with the ``velocity_change`` they imply (if
    any, ``law_velocity_change``), then without it, then half and one and a half times
    them; the first ``count`` (at least one)."""
    start = candidate.base["start"]
    starts = [(start, velocity_change)] if velocity_change else []
    starts += [(factor * start, None) for factor in (1.0, 0.5, 1.5)]
    return starts[: max(1, count)]


def law_velocity_change(
    candidate: Candidate,
    target: dict[int, np.ndarray],
    residual: dict[int, np.ndarray],
    regimes: dict[int, list[str]],
    fit_frames: list[int],
    fps: float,
) -> dict[int, torch.Tensor] | None:
    """Per object, the initial-velocity change (m/s) that, with the law at its discovered
    coefficients, best explains the centroid residual on the fit frames of the free flight
    from frame 0: r(t) = D(t) + dv0 t, D the double integral of the law along the target's
    centroid path (position, central-difference velocity, the other objects' centroids).

    Why: the model the law was discovered against fitted its initial velocities without the
    law, so they are biased; a refit begun at the right law but biased velocities traded the
    coefficients against them (a thrown block's linear drag came out 11 % low after 25 refit
    steps, its velocities 0.1 m/s off).

    Args:
        target: object id -> [T, 3] target centroid path (m).
        residual: object id -> [T, 3] target minus model centroid, relative to frame 0 (m).
        regimes: object id -> the model's regime per frame.
        fit_frames: the frames a refit may use.
        fps: frames per second.

    Returns:
        object id -> [3] velocity change, or None where no object has 3 free-flight frames.
    """
    ids = sorted(target)
    values = {n: c for n, c in zip(candidate.coefficient_names, candidate.base["start"])}
    frames = min(len(p) for p in target.values())
    t = np.arange(frames) / fps
    out = {}
    for k in ids:
        m = 0
        while m < frames and m <= max(fit_frames) and regimes[k][m] == "free_flight":
            m += 1
        rows = [f for f in range(1, m) if f in set(fit_frames)]
        if m < 3 or len(rows) < 2:
            continue
        acc = _law_acceleration(values, candidate.base, target, k, fps)[:m]
        moved = residual[k][:m] - _double_integral(acc, 1.0 / fps)
        tt = t[rows]
        out[k] = torch.tensor(tt @ moved[rows] / (tt @ tt), dtype=torch.float32)
    return out or None


def run_velocity_change(ctx, candidate: Candidate, traj, regimes, fit_frames: list[int]):
    """``law_velocity_change`` against a run's (``RunContext``) rollout ``traj`` (None if
    there is none)."""
    if traj is None:
        return None
    residuals = object_residuals(ctx, traj, max(fit_frames) + 1)
    return law_velocity_change(
        candidate,
        {k: r.target_centroid for k, r in residuals.items()},
        {k: r.centroid for k, r in residuals.items()},
        regimes,
        fit_frames,
        ctx.fps,
    )


def _law_acceleration(values, base: dict, target: dict, k: int, fps: float) -> np.ndarray:
    """[T, 3] the law's acceleration along object ``k``'s target centroid path."""
    as_t = {j: torch.as_tensor(p, dtype=torch.float64) for j, p in target.items()}
    p = as_t[k]
    v = torch.as_tensor(np.gradient(target[k], axis=0) * fps)
    others = [j for j in as_t if j != k]
    op = torch.stack([as_t[j] for j in others], 1) if others else None
    ov = (
        torch.stack([torch.as_tensor(np.gradient(target[j], axis=0) * fps) for j in others], 1)
        if others
        else None
    )
    features = node_features(
        p, v, torch.arange(len(p), dtype=torch.float64) / fps, up=base["up"],
        ground_height=base["ground_height"], others_position=op, others_velocity=ov,
    )  # fmt: skip
    return acceleration(values, features).numpy()


def _double_integral(a: np.ndarray, dt: float) -> np.ndarray:
    """Displacement [T, 3] from accelerations [T, 3] at frames, from rest (trapezoids twice;
    as ``hypothesise``'s regression)."""
    v = np.concatenate([np.zeros((1, 3)), np.cumsum(0.5 * (a[1:] + a[:-1]), axis=0) * dt])
    return np.concatenate([np.zeros((1, 3)), np.cumsum(0.5 * (v[1:] + v[:-1]), axis=0) * dt])


def object_designs(candidate: Candidate, samples: dict) -> dict:
    """Per object id: (basis [M, 3, d], residual [M, 3]) of its free-flight samples, basis[:,
    a, i] the feature of coefficient i where it acts on axis a (the acceleration per unit
    coefficient), for the consistency test across objects (``physical.consistency``)."""
    names, x, y, units = feature_library(
        samples, up=candidate.base["up"], ground_height=candidate.base["ground_height"]
    )
    if not len(y):
        return {}
    flight = x[:, names.index("contact")] == 0.0  # as ``consistency``: unknown regimes count
    out = {}
    for row, k in enumerate(sorted(samples)):
        rows = np.flatnonzero((units // 100000 == row) & flight)
        basis = np.zeros((len(rows), 3, candidate.dim))
        for i, name in enumerate(candidate.coefficient_names):
            axis, feature = parse_coefficient(name)
            if feature in names:
                basis[:, axis, i] = x[rows, names.index(feature)]
        out[k] = (basis, y[rows])
    return out


def formula_record(candidate: Candidate, theta, interval=None) -> dict:
    """The refitted law per axis as ``discover`` writes one (terms with coefficient and 95 %
    interval, formula text), and all three formulas joined. ``interval`` ([lower, upper] per
    coefficient, as ``decide.Evidence.interval``) is None for a candidate that failed the tests
    before it: each term's interval is then None."""
    theta = [float(x) for x in theta]
    bounds = interval if interval is not None else [None] * len(theta)
    axes = {}
    for a, axis in enumerate(AXES):
        terms = [
            {
                "feature": parse_coefficient(n)[1],
                "coefficient": c,
                "interval": None if b is None else [float(b[0]), float(b[1])],
            }
            for n, c, b in zip(candidate.coefficient_names, theta, bounds)
            if parse_coefficient(n)[0] == a
        ]
        axes[axis] = {"terms": terms, "formula": formula(axis, terms)}
    return {"axes": axes, "formula": "; ".join(ax["formula"] for ax in axes.values())}


#: the tests of ``decide.Evidence`` in the order the rule applies them, as the report names them
TESTS = (
    ("passes_heldout", "held-out"),
    ("passes_bic", "information criterion"),
    ("passes_interval", "interval"),
    ("passes_effect", "own effect"),
    ("passes_consistency", "agreement across objects"),
    ("passes_nuisance", "win over the nuisance model"),
)


def failed_tests(evidence) -> list[str]:
    """The names of the tests a candidate's ``decide.Evidence`` failed."""
    return [name for field, name in TESTS if not getattr(evidence, field)]
