"""Replaying the decision step on finished diagnoses, under another decision rule.

A diagnosis.json keeps every refitted model's [object, frame] Chamfer table
(``frame_errors_mm2``), the fit and held-out frames and the null model's parameter count, so the
last step of a diagnosis (``decide.py``: held-out drop against its bootstrap spread, and the
BIC margin) can be re-run with other ``DecideOptions`` without refitting anything. On a whole
``mosiv diagnose-suite`` folder this scores a candidate rule in seconds, where the suite itself
takes GPU-hours; a rule chosen this way is chosen on that suite, which a report must say.

The interval test (``DecideOptions.require_nonzero``) uses the intervals a diagnosis recorded;
files from before session 15 hold only the accepted candidate's, so there a candidate accepted
only after the replay has none and is not tested. Likewise the effect test (``min_effect``) uses
the recorded own effects and resolution floor: a candidate without a recorded effect passes.

Replayed scores lack the coefficient error of a candidate the original run did not accept when
the file predates session 16 (only then is its physical value missing); everything else is
recomputed. A folder kept without its scenes is scored against the suite entry's conceal
spec, the truth the generator was given.
"""

from __future__ import annotations

import json
from pathlib import Path

from mosiv_framework.diagnose.decide import (
    DecideOptions,
    Evidence,
    apply_effect_test,
    apply_interval_test,
    verdict,
    weigh,
)
from mosiv_framework.diagnose.report import MM2, loaded_table


def replay_diagnosis(diagnosis: dict, options: DecideOptions | None = None) -> dict:
    """The decision of one diagnosis.json under ``options`` (default: the rule it ran with,
    its ``rule``; files from before session 13 lack it and ran the rule of then, z 2, BIC
    margin 2 and no effect-size test, with their budget's bootstrap count): a copy of
    ``diagnosis`` with ``verdict``, ``evidence`` and ``accepted`` replaced. ``accepted`` keeps
    the original record when the same candidate is accepted again, else holds its name and,
    where the file recorded it (since session 16), the physical ``value`` of its fit."""
    if options is None:
        # files from before session 15 lack require_nonzero and ran without the interval test,
        # files from before session 17 lack min_effect and ran without the effect test
        options = DecideOptions(
            **(
                {"require_nonzero": False, "min_effect": 0.0, **diagnosis["rule"]}
                if diagnosis.get("rule")
                else {
                    "bootstrap": diagnosis.get("budget", {}).get("bootstrap", 200),
                    "bic_margin": 2.0,
                    "min_drop": 0.0,
                    "require_nonzero": False,
                    "min_effect": 0.0,
                }
            )
        )
    out = dict(diagnosis)
    tables = {name: loaded_table(t) / MM2 for name, t in _tables(diagnosis).items()}
    ranked: list[Evidence] = []
    if diagnosis["evidence"] and "null" in tables:
        ranked = weigh(
            tables,
            null_parameters=diagnosis["null_parameters"],
            candidates=[
                (e["name"], e["new_coefficients"], e["fit_loss_m2"]) for e in diagnosis["evidence"]
            ],
            fit_frames=diagnosis["frames"]["fit"],
            heldout_frames=diagnosis["frames"]["heldout"],
            options=options,
            special_cases=saved_special_cases(diagnosis),
        )
        ranked = apply_interval_test(ranked, saved_intervals(diagnosis), options)
        ranked = apply_effect_test(
            ranked, saved_effects(diagnosis), diagnosis.get("resolution_floor_mm2"), options
        )
        saved = {e["name"]: e for e in diagnosis["evidence"]}
        for e in ranked:  # what the fits were: unchanged by a new rule
            e.theta = saved[e.name].get("theta")
            e.started_from = saved[e.name].get("started_from")
            e.reidentified = bool(saved[e.name].get("reidentified", False))
            e.value = saved[e.name].get("value")
            e.diverged = saved[e.name].get("diverged")
    out["verdict"] = verdict(bool(diagnosis["where"]["significant"]), ranked)
    out["evidence"] = [e.to_json() for e in ranked]
    winner = ranked[0].name if ranked and ranked[0].accepted else None
    before = diagnosis.get("accepted")
    if winner is None:
        out["accepted"] = None
    elif before is not None and before["name"] == winner:
        out["accepted"] = before
    else:
        out["accepted"] = {"name": winner}
        if ranked[0].value is not None:
            out["accepted"]["value"] = ranked[0].value
    return out


def saved_intervals(diagnosis: dict) -> dict[str, list[list[float]]]:
    """Candidate -> [lower, upper] per coefficient, as a diagnosis recorded them: in its
    evidence (since session 15), or only the accepted candidate's (``interval_95``, before)."""
    out = {e["name"]: e["interval"] for e in diagnosis["evidence"] if e.get("interval")}
    accepted = diagnosis.get("accepted")
    if accepted and accepted.get("interval_95") and accepted["name"] not in out:
        out[accepted["name"]] = [list(v) for v in accepted["interval_95"].values()]
    return out


def saved_effects(diagnosis: dict) -> dict[str, dict]:
    """Candidate -> its own effect (``effect.summarise_effect``), where the diagnosis measured
    one (since session 17; or added to a copy by benchmarks/term_effect.py)."""
    return {e["name"]: e["effect"] for e in diagnosis["evidence"] if e.get("effect")}


def saved_special_cases(diagnosis: dict) -> dict[str, tuple[str, ...]]:
    """Candidate -> the candidates containing it, as recorded (since session 16), else as the
    built-in candidates declare it (``candidates.SPECIAL_CASES``)."""
    from mosiv_framework.diagnose.candidates import SPECIAL_CASES

    out = {}
    for e in diagnosis["evidence"]:
        saved = e.get("special_case_of")
        out[e["name"]] = tuple(saved) if saved is not None else SPECIAL_CASES.get(e["name"], ())
    return out


def _tables(diagnosis: dict) -> dict:
    if "frame_errors_mm2" not in diagnosis:
        raise ValueError(
            "diagnosis.json has no 'frame_errors_mm2': it was written before session 11's "
            "report format and cannot be replayed; run the diagnosis again"
        )
    return diagnosis["frame_errors_mm2"]


def replay_suite(out: Path, options: DecideOptions, *, small: bool = False) -> dict:
    """Re-score every finished entry of a ``mosiv diagnose-suite`` folder under ``options``;
    returns the suite summary (``suite.summarise``) of the replayed scores. Entries without a
    diagnosis.json (not finished, or failed) are left out and listed under ``missing``."""
    from mosiv_framework.conceal import parse_conceal
    from mosiv_framework.diagnose.suite import score_entry, suite_entries, summarise
    from mosiv_framework.scene import read_scene

    out = Path(out)
    scores, missing = [], []
    for entry in suite_entries(small):
        path = out / entry.name / "diagnosis.json"
        if not path.exists():
            missing.append(entry.name)
            continue
        diagnosis = replay_diagnosis(json.loads(path.read_text()), options)
        accepted = diagnosis["accepted"]
        # a newly accepted candidate of a file from before session 16 has no recorded value
        known = accepted is None or "value" in accepted
        # a folder kept without its scenes (benchmarks/data/) takes the truth from the entry's
        # conceal spec, which is what the generator wrote to gt/effects.json
        scene = out / entry.name / "scene"
        if not known:
            effects = []
        elif scene.is_dir():
            effects = read_scene(scene).gt_effects()
        else:
            effects = [effect.to_json() for effect in parse_conceal(entry.conceal or None)]
        scores.append(score_entry(entry, diagnosis, effects))
    summary = summarise(scores)
    summary["missing"] = missing
    summary["rule"] = dict(options.__dict__)
    return summary
