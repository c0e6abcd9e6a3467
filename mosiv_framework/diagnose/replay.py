"""Replaying the decision step on finished diagnoses, under another decision rule.

A diagnosis.json keeps every refitted model's [object, frame] Chamfer table
(``frame_errors_mm2``), the fit and held-out frames and the null model's parameter count, so the
last step of a diagnosis (``decide.py``: held-out drop against its bootstrap spread, and the
BIC margin) can be re-run with other ``DecideOptions`` without refitting anything. On a whole
``mosiv diagnose-suite`` folder this scores a candidate rule in seconds, where the suite itself
takes GPU-hours; a rule chosen this way is chosen on that suite, which a report must say
(docs/DIAGNOSIS.md).

Files are told apart by their ``format`` field (``formats.DIAGNOSIS_FORMAT``). A file without
it has the unversioned layout, whose fields grew over time: it may lack the rule it ran with
(then it ran z 2, BIC margin 2, no effect-size test, no interval or effect test), the interval
of every candidate but the accepted one, the candidates' physical values and their
special-case relations. Each of those is read where present and otherwise taken as that
layout implies (``legacy_rule``, ``saved_intervals``, ``saved_special_cases``); a candidate
without a recorded interval or effect is not tested on it, and one newly accepted without a
recorded physical value has no coefficient error. A folder kept without its scenes is scored
against the suite entry's conceal spec, the truth the generator was given.
"""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

from mosiv_framework.diagnose.decide import (
    DecideOptions,
    Evidence,
    apply_effect_test,
    apply_interval_test,
    apply_physical_tests,
    rank_evidence,
    verdict,
    weigh,
)
from mosiv_framework.diagnose.formats import DIAGNOSIS_FORMAT, FIELD, file_format
from mosiv_framework.diagnose.grid_stability import regrade_grid_check
from mosiv_framework.diagnose.report import MM2, loaded_table

#: the diagnosis.json formats ``replay_diagnosis`` reads (besides the unversioned layout)
SUPPORTED = (DIAGNOSIS_FORMAT,)


def load_diagnosis(path: str | Path) -> dict:
    """A diagnosis.json, its format checked (``formats.file_format``)."""
    diagnosis = json.loads(Path(path).read_text())
    file_format(diagnosis, path, SUPPORTED)
    return diagnosis


def replay_diagnosis(
    diagnosis: dict, options: DecideOptions | None = None, *, source: str | Path = "diagnosis.json"
) -> dict:
    """The decision of one diagnosis.json under ``options``: a copy of ``diagnosis`` with
    ``verdict``, ``evidence`` and ``accepted`` replaced.

    Args:
        diagnosis: the parsed file.
        options: the rule; default: the one the diagnosis ran with (``saved_rule``). Its
            bootstrap count is always the saved one (the budget's).
        source: where the file came from, named in errors.

    Returns:
        The copy. ``accepted`` keeps the original record when the same candidate is accepted
        again, else holds its name and, where the file recorded it, the physical ``value`` of
        its fit.

    Raises:
        formats.FormatError: the file's format is not one of ``SUPPORTED``.
        ValueError: the file holds no error tables to replay.
    """
    file_format(diagnosis, source, SUPPORTED)
    ran_with = saved_rule(diagnosis)
    # the bootstrap's resample count is the budget's, not a threshold of the rule: a replay
    # draws as many as the diagnosis did (a spread from fewer draws can flip a close test)
    options = ran_with if options is None else replace(options, bootstrap=ran_with.bootstrap)
    tables = {name: loaded_table(t) / MM2 for name, t in _tables(diagnosis, source).items()}
    ranked: list[Evidence] = []
    if diagnosis["evidence"] and "null" in tables:
        ranked = _redecide(diagnosis, tables, options)
    out = dict(diagnosis)
    out["verdict"] = verdict(bool(diagnosis["where"]["significant"]), ranked)
    out["evidence"] = [e.to_json() for e in ranked]
    out["accepted"] = _accepted(diagnosis.get("accepted"), ranked)
    return out


def _versioned(diagnosis: dict) -> bool:
    """Whether the file carries a format (checked by ``replay_diagnosis``), not the unversioned
    layout."""
    return diagnosis.get(FIELD) is not None


#: why a replay does not name a candidate that passes every other test under the new rule
#: but never reached the grid-stability check of the budget it ran with
GRID_NOT_CHECKED = (
    "not checked at a second grid: the diagnosis stopped this candidate before the check; "
    "diagnose again to run it"
)

#: the rule's settings that saved rules did not record at first, as those diagnoses ran
BEFORE_RECORDED = {"heldout_statistic": "sum", "consistency_tolerance": 0.0}


def saved_rule(diagnosis: dict) -> DecideOptions:
    """The rule a diagnosis ran with: its ``rule`` field, complete in a versioned file."""
    if _versioned(diagnosis):
        # a rule saved before the held-out statistic and the agreement's tolerance were
        # recorded summed the errors and compared the objects' intervals alone
        return DecideOptions(**{**BEFORE_RECORDED, **diagnosis["rule"]})
    return legacy_rule(diagnosis)


def legacy_rule(diagnosis: dict) -> DecideOptions:
    """The rule of a file in the unversioned layout. Its ``rule`` may lack the interval test
    (``require_nonzero``) and the effect test (``min_effect``), which it then ran without; a
    file without any ``rule`` ran z 2 with a BIC margin of 2 and no effect-size test, with its
    budget's bootstrap count."""
    if diagnosis.get("rule"):
        return DecideOptions(
            **{
                "require_nonzero": False,
                "min_effect": 0.0,
                **BEFORE_RECORDED,
                **diagnosis["rule"],
            }
        )
    return DecideOptions(
        **BEFORE_RECORDED,
        bootstrap=diagnosis.get("budget", {}).get("bootstrap", 200),
        bic_margin=2.0,
        min_drop=0.0,
        require_nonzero=False,
        min_effect=0.0,
    )


def _redecide(diagnosis: dict, tables: dict, options: DecideOptions) -> list[Evidence]:
    """Every test of ``decide`` on the saved tables, intervals and effects; ranked."""
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
    # the nuisance table and each body force's per-object coefficients, where recorded
    ranked = apply_physical_tests(
        ranked,
        tables,
        {e["name"]: e.get("consistency") for e in diagnosis["evidence"]},
        diagnosis["frames"]["heldout"],
        options,
    )
    saved = {e["name"]: e for e in diagnosis["evidence"]}
    checks_grid = bool(diagnosis.get("budget", {}).get("grid_check", False))
    for e in ranked:  # what the fits were: unchanged by a new rule
        e.theta = saved[e.name].get("theta")
        e.started_from = saved[e.name].get("started_from")
        e.reidentified = bool(saved[e.name].get("reidentified", False))
        e.value = saved[e.name].get("value")
        e.diverged = saved[e.name].get("diverged")
        # the check at a second grid refitted models, which a replay cannot: its tests are
        # decided again from the second grid's saved tables where recorded, else its outcome
        # stays (``grid_stability.regrade_grid_check``)
        e.grid, e.passes_grid = saved[e.name].get("grid"), saved[e.name].get("passes_grid", True)
        if e.grid:
            frames = diagnosis["frames"]
            e.grid = regrade_grid_check(e.grid, frames["fit"], frames["heldout"], options)
            e.passes_grid = bool(e.grid["stable"])
        elif checks_grid and e.accepted:
            # the rule it ran with stopped this candidate before the check: a replay cannot
            # refit it on the second grid, so it is not named until diagnosed again
            e.grid, e.passes_grid = {"stable": False, "reason": GRID_NOT_CHECKED}, False
    return rank_evidence(ranked, min_drop=options.min_drop)


def _accepted(before: dict | None, ranked: list[Evidence]) -> dict | None:
    """The replay's ``accepted`` record: None, the file's own if it names the same winner, or
    the winner's name and (where recorded) physical value."""
    if not ranked or not ranked[0].accepted:
        return None
    winner = ranked[0]
    if before is not None and before["name"] == winner.name:
        return before
    record = {"name": winner.name}
    if winner.value is not None:
        record["value"] = winner.value
    return record


def saved_intervals(diagnosis: dict) -> dict[str, list[list[float]]]:
    """Candidate -> [lower, upper] per coefficient, as a diagnosis recorded them in its
    evidence; a file in the unversioned layout may hold only the accepted candidate's
    (``accepted.interval_95``)."""
    out = {e["name"]: e["interval"] for e in diagnosis["evidence"] if e.get("interval")}
    accepted = diagnosis.get("accepted")
    legacy = not _versioned(diagnosis) and accepted and accepted.get("interval_95")
    if legacy and accepted["name"] not in out:
        out[accepted["name"]] = [list(v) for v in accepted["interval_95"].values()]
    return out


def saved_effects(diagnosis: dict) -> dict[str, dict]:
    """Candidate -> its own effect (``effect.summarise_effect``), where the diagnosis measured
    one (or benchmarks/term_effect.py added it to a copy)."""
    return {e["name"]: e["effect"] for e in diagnosis["evidence"] if e.get("effect")}


def saved_special_cases(diagnosis: dict) -> dict[str, tuple[str, ...]]:
    """Candidate -> the candidates containing it, as recorded; a file in the unversioned layout
    that did not record them gets the built-in declaration (``candidates.SPECIAL_CASES``)."""
    from mosiv_framework.diagnose.candidates import SPECIAL_CASES

    out = {}
    for e in diagnosis["evidence"]:
        saved = e.get("special_case_of")
        if saved is None and not _versioned(diagnosis):
            saved = SPECIAL_CASES.get(e["name"], ())
        out[e["name"]] = tuple(saved or ())
    return out


def _tables(diagnosis: dict, source: str | Path) -> dict:
    if "frame_errors_mm2" not in diagnosis:
        raise ValueError(
            f"{source} has no 'frame_errors_mm2' (the per-frame error tables a replay "
            "re-decides on): it cannot be replayed; run the diagnosis again"
        )
    return diagnosis["frame_errors_mm2"]


def replay_suite(
    out: Path,
    options: DecideOptions,
    *,
    small: bool = False,
    source: str = "synth",
    split: str | None = None,
) -> dict:
    """Re-score every finished entry of a ``mosiv diagnose-suite`` folder under ``options``;
    returns the suite summary (``suite.summarise``) of the replayed scores. Entries without a
    diagnosis.json (not finished, or failed) are left out and listed under ``missing``.
    ``source`` and ``split`` name the suite the folder holds (``suite.suite_selection``); a
    folder whose suite.json records another is refused."""
    from mosiv_framework.diagnose.suite import (
        check_suite_folder,
        score_entry,
        suite_selection,
        summarise,
    )

    out = Path(out)
    entries = suite_selection(small, source, split)
    check_suite_folder(out, source, split)
    scores, missing = [], []
    for entry in entries:
        path = out / entry.name / "diagnosis.json"
        if not path.exists():
            missing.append(entry.name)
            continue
        diagnosis = replay_diagnosis(load_diagnosis(path), options, source=path)
        truth = _truth(entry, out, diagnosis["accepted"])
        scores.append(score_entry(entry, diagnosis, truth, _law(entry, out, diagnosis)))
    summary = summarise(scores)
    summary["missing"] = missing
    summary["rule"] = {**options.__dict__, "bootstrap": "each diagnosis's own"}
    summary.update(source=source, split=split)
    return summary


def _law(entry, out: Path, diagnosis: dict) -> dict | None:
    """The law's score of an out-of-library entry (``suite.scored_law`` of the replayed
    decision) against its kept scene; in a folder kept without scenes (benchmarks/data/), the
    score its own run wrote, where the replay accepts what the run accepted (the law scored is
    then the same one)."""
    from mosiv_framework.diagnose.law_score import law_score
    from mosiv_framework.diagnose.suite import scored_law
    from mosiv_framework.scene import read_scene

    scene = out / entry.name / "scene"
    if not entry.outside:
        return None
    if scene.is_dir():
        return law_score(scored_law(diagnosis), read_scene(scene).gt_effects(), scene)
    saved = out / entry.name / "score.json"
    if not saved.exists():
        return None
    ran = json.loads(saved.read_text())
    accepted = (diagnosis.get("accepted") or {}).get("name")
    if ran.get("accepted") != accepted:
        return None
    law_keys = ("law_error", "form_correct", "law_samples")
    return {k: v for k, v in (ran.get("extra") or {}).items() if k in law_keys} or None


def _truth(entry, out: Path, accepted: dict | None) -> list[dict]:
    """The concealed effects an entry is scored against: its scene's gt/effects.json, or for a
    folder kept without its scenes (benchmarks/data/) the entry's conceal spec, which is what
    the generator wrote there. None for a newly accepted candidate without a recorded physical
    value (an unversioned file): it has no coefficient to compare."""
    from mosiv_framework.conceal import ALL_DEFAULTS, parse_conceal
    from mosiv_framework.scene import read_scene

    if accepted is not None and "value" not in accepted:
        return []
    scene = out / entry.name / "scene"
    if scene.is_dir():
        return read_scene(scene).gt_effects()
    # a Genesis entry may conceal an out-of-library field (vortex, attractor)
    kinds = tuple(ALL_DEFAULTS)
    return [effect.to_json() for effect in parse_conceal(entry.conceal or None, kinds=kinds)]
