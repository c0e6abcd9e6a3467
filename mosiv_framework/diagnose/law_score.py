"""Scoring a discovered law against a concealed out-of-library field (suite scoring only).

The diagnosis never reads gt/; once it is done, a suite compares the law ``discover`` wrote
with the field gt/effects.json records (``conceal_fields``):

- **law error**: the discovered law and the field's true acceleration on the same states, the
  recorded bodies' centroids at the interior frames of the observed window (the frames the
  discovery saw), as the relative RMS difference sqrt(sum |a_law - a_true|^2 / sum |a_true|^2).
  The true acceleration of a body is the mean of the field over its recorded particles, at
  their positions and central-difference velocities. The law's contact term is left out (the
  field acts the same on a body in contact), so it is its body-force part that is scored;
- **right form**: for a field that is a linear law of the discovery's features (the vortex,
  ``conceal_fields.linear_form``), whether the discovered law keeps exactly the field's
  non-constant features on every axis. A field with no such form (the attractor) has none.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mosiv_framework.conceal_fields import OUT_OF_LIBRARY_KINDS, field_acceleration
from mosiv_framework.diagnose.discover import AXES, feature_library
from mosiv_framework.diagnose.kinematics import ResidualSamples

#: a truth coefficient counts as a term of the form when it is above this share of the largest
FORM_CUTOFF = 1e-9


def out_of_library_effect(effects: list[dict]) -> dict | None:
    """The first recorded out-of-library field, or None."""
    return next((e for e in effects if e.get("kind") in OUT_OF_LIBRARY_KINDS), None)


def law_score(discovered: dict | None, effects: list[dict], scene_dir: str | Path) -> dict | None:
    """The discovered law against the scene's out-of-library field; None if it has none.

    Args:
        discovered: the diagnosis' ``discovered`` record (None where nothing was discovered).
        effects: gt/effects.json's effects.
        scene_dir: the scene folder (its gt points and declarations).

    Returns:
        {"law_error": relative RMS difference or None without a law, "form_correct": bool, or
        None for a field without a linear form, "law_samples": states compared}.
    """
    field = out_of_library_effect(effects)
    if field is None:
        return None
    form = field.get("linear_form")
    if discovered is None:
        return {"law_error": None, "form_correct": None if form is None else False}
    names, x, truth = true_states(field, scene_dir)
    missing = sorted(
        {t["feature"] for ax in discovered["axes"].values() for t in ax["terms"]} - set(names)
    )
    if missing:
        raise ValueError(f"discovered features {missing} are not in the library {names}")
    predicted = np.zeros_like(truth)
    for a, axis in enumerate(AXES):
        for term in discovered["axes"][axis]["terms"]:
            if term["feature"] != "contact":
                predicted[:, a] += term["coefficient"] * x[:, names.index(term["feature"])]
    norm = float((truth**2).sum())
    error = float(np.sqrt(((predicted - truth) ** 2).sum() / norm)) if norm > 0 else None
    return {
        "law_error": error,
        "form_correct": None if form is None else form_matches(discovered, form),
        "law_samples": int(len(truth)),
    }


def form_matches(discovered: dict, form: dict[str, dict[str, float]]) -> bool:
    """Whether every axis of the law keeps exactly the form's non-constant features (those
    whose coefficient is not zero)."""
    for axis in AXES:
        coefs = form.get(axis, {})
        scale = max((abs(c) for c in coefs.values()), default=0.0)
        want = {f for f, c in coefs.items() if f != "1" and abs(c) > FORM_CUTOFF * scale}
        have = {t["feature"] for t in discovered["axes"][axis]["terms"]} - {"1", "contact"}
        if want != have:
            return False
    return True


def true_states(field: dict, scene_dir: str | Path) -> tuple[list[str], np.ndarray, np.ndarray]:
    """(feature names, features [M, F], true field acceleration [M, 3]) of every recorded body
    at the interior frames of the observed window (``discover.feature_library``'s features)."""
    from mosiv_framework.scene import read_scene

    scene = read_scene(scene_dir)
    fps = float(scene.fps)
    frames = np.arange(1, scene.observed_frames - 1)
    samples = {}
    for k, pts in scene.gt_points().items():
        p = pts.numpy().astype(np.float64)  # [T, N, 3]
        vel = (p[frames + 1] - p[frames - 1]) * fps / 2
        acc = np.stack(
            [
                field_acceleration(field, p[t], vel[i], t / fps).mean(axis=0)
                for i, t in enumerate(frames)
            ]
        )
        samples[k] = ResidualSamples(
            frames=frames,
            time=frames / fps,
            position=p[frames].mean(axis=1),
            velocity=vel.mean(axis=1),
            residual=acc,
            regime=["free_flight"] * len(frames),
        )
    up = -np.asarray(scene.gravity, dtype=np.float64)
    up = up / np.linalg.norm(up) if np.linalg.norm(up) > 0 else np.array([0.0, 0.0, 1.0])
    names, x, y, _ = feature_library(samples, up=tuple(up), ground_height=scene.ground_height)
    return names, x, y
