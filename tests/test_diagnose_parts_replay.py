"""Unit tests of replaying kept diagnoses (benchmarks/data/diagnosis_rule_cases and the other
diagnoses kept under benchmarks/data) under the current decision rule and format (no
simulator)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

#: benchmarks/data/, where kept diagnoses are found by their content, not by folder names
KEPT = Path(__file__).resolve().parents[1] / "benchmarks" / "data"


def _kept_diagnosis(entry: str, accepted: str, match=lambda diagnosis: True) -> Path:
    """The first diagnosis.json of suite entry ``entry`` kept under benchmarks/data/ that
    accepted ``accepted`` as it ran and satisfies ``match``."""
    for path in sorted(KEPT.glob(f"**/{entry}/diagnosis.json")):
        diagnosis = json.loads(path.read_text())
        if (diagnosis.get("accepted") or {}).get("name") == accepted and match(diagnosis):
            return path
    pytest.fail(f"no diagnosis of {entry} accepting {accepted} is kept under {KEPT}")


def _interval_includes_zero(diagnosis: dict) -> bool:
    return any(lo <= 0.0 <= hi for lo, hi in diagnosis["accepted"]["interval_95"].values())


def test_replaying_with_the_interval_test_reports_the_out_of_library_entry_unexplained():
    """An out-of-library entry (a concealed drag with drag out of the library) that ran
    without the interval test accepted material damping with a viscosity interval of
    [0, 18.9] Pa s; replayed with the interval test it is unexplained, and a true effect's
    diagnosis of the same suite (its interval clear of zero) is unchanged."""
    from mosiv_framework.diagnose.decide import DecideOptions
    from mosiv_framework.diagnose.replay import replay_diagnosis

    outside_path = _kept_diagnosis(
        "outside-quadratic_drag", "material_damping", _interval_includes_zero
    )
    outside = json.loads(outside_path.read_text())
    true_path = outside_path.parents[1] / "material_damping-0" / "diagnosis.json"
    true = json.loads(true_path.read_text())
    strict = DecideOptions(**{**outside["rule"], "require_nonzero": True})
    assert replay_diagnosis(outside)["accepted"]["name"] == "material_damping"
    replayed = replay_diagnosis(outside, strict)
    assert replayed["verdict"] == "unexplained" and replayed["accepted"] is None
    assert replay_diagnosis(true, strict)["accepted"]["name"] == "material_damping"


def test_replaying_the_gravity_entry_names_gravity_not_a_vertical_wind():
    """A gravity-1 entry (gravity 7.5 m/s^2 instead of 9.81) diagnosed before the special-case
    preference accepted a nearly vertical wind; the decision with the preference names the
    gravity change, from the saved error tables alone. Files of the unversioned layout without
    a recorded ``special_case_of`` use the built-in declaration."""
    from mosiv_framework.diagnose.candidates import SPECIAL_CASES
    from mosiv_framework.diagnose.replay import replay_diagnosis, saved_special_cases

    diagnosis = json.loads(_kept_diagnosis("gravity-1", "wind").read_text())
    assert "format" not in diagnosis  # the unversioned layout
    assert diagnosis["accepted"]["name"] == "wind"  # as it ran, before the preference
    assert saved_special_cases(diagnosis)["gravity"] == SPECIAL_CASES["gravity"] == ("wind",)
    replayed = replay_diagnosis(diagnosis)
    assert replayed["verdict"] == "missing physics" and replayed["accepted"]["name"] == "gravity"
    assert replayed["evidence"][0]["special_case_of"] == ["wind"]
    assert replayed["evidence"][1]["name"] == "wind" and replayed["evidence"][1]["accepted"]
    assert replayed["evidence"][0]["theta"] == pytest.approx([-2.19], abs=0.01)  # kept from file
    # a file that records each fit's physical value: a newly accepted term carries it
    for e in diagnosis["evidence"]:
        if e["name"] == "gravity":
            e["value"] = {"acceleration": [0.0, 0.0, -7.62]}
    assert replay_diagnosis(diagnosis)["accepted"]["value"] == {"acceleration": [0.0, 0.0, -7.62]}


def test_a_replayed_suite_folder_without_scenes_scores_coefficients_from_the_entries(tmp_path):
    """benchmarks/data keeps diagnoses without their scenes; a replay scores the coefficient
    error against the entry's conceal spec (what the generator wrote to gt/effects.json)."""
    import shutil

    from mosiv_framework.diagnose.decide import DecideOptions
    from mosiv_framework.diagnose.replay import replay_suite

    kept = _kept_diagnosis("wind-0", "wind").parent
    shutil.copytree(kept, tmp_path / "wind-0")
    summary = replay_suite(tmp_path, DecideOptions())
    (score,) = summary["scores"]
    saved = json.loads((kept / "score.json").read_text())
    assert score["correct"] and score["accepted"] == "wind"
    assert score["coefficient_error"] == pytest.approx(saved["coefficient_error"], rel=1e-9)
    assert "control-0" in summary["missing"]


def test_a_diagnosis_of_an_unknown_format_is_refused_naming_the_file_field_and_values(tmp_path):
    """A diagnosis.json of a format this version cannot read (e.g. from a newer MOSIV) is not
    misread: the replay stops with the file, the field, its value and the supported values."""
    from mosiv_framework.diagnose.decide import DecideOptions
    from mosiv_framework.diagnose.formats import DIAGNOSIS_FORMAT, FormatError
    from mosiv_framework.diagnose.replay import replay_suite

    diagnosis = json.loads(_kept_diagnosis("wind-0", "wind").read_text())
    path = tmp_path / "wind-0" / "diagnosis.json"
    path.parent.mkdir()
    path.write_text(json.dumps({**diagnosis, "format": "mosiv-diagnosis/99"}))
    with pytest.raises(FormatError) as info:
        replay_suite(tmp_path, DecideOptions())
    message = str(info.value)
    assert str(path) in message and "'format'" in message
    assert "'mosiv-diagnosis/99'" in message and repr(DIAGNOSIS_FORMAT) in message


def test_kept_diagnoses_of_the_unversioned_layout_replay_to_their_own_decision():
    """Files written before diagnosis.json carried a format replay, under the rule they record
    (or the one their layout implies), to the verdict and term they recorded; the one change
    allowed is the special-case preference, which names the special case of the term they
    accepted (a gravity change for a vertical wind)."""
    from mosiv_framework.diagnose.candidates import SPECIAL_CASES
    from mosiv_framework.diagnose.replay import replay_diagnosis

    paths = sorted(KEPT.glob("**/diagnosis.json"))
    unversioned = [p for p in paths if "format" not in json.loads(p.read_text())]
    assert unversioned
    changed = 0
    for path in unversioned:
        saved = json.loads(path.read_text())
        replayed = replay_diagnosis(saved, source=path)
        assert replayed["verdict"] == saved["verdict"], path
        before = (saved["accepted"] or {}).get("name")
        after = (replayed["accepted"] or {}).get("name")
        changed += after != before
        assert after == before or before in SPECIAL_CASES.get(after, ()), path
    assert changed < len(unversioned)


def test_the_format_field_decides_how_a_diagnosis_is_read():
    """The unversioned layout gets what its fields leave out from the layout (a file without a
    rule ran BIC margin 2 without the interval test; the accepted interval stands for the
    evidence's); a versioned file is read as written. A complete unversioned file replays the
    same once it carries the current format."""
    from mosiv_framework.diagnose.decide import DecideOptions
    from mosiv_framework.diagnose.formats import DIAGNOSIS_FORMAT
    from mosiv_framework.diagnose.replay import (
        replay_diagnosis,
        saved_intervals,
        saved_rule,
        saved_special_cases,
    )

    saved = json.loads(_kept_diagnosis("outside-quadratic_drag", "material_damping").read_text())
    rule_less = {k: v for k, v in saved.items() if k != "rule"}
    legacy = saved_rule(rule_less)
    assert legacy.bic_margin == 2.0 and not legacy.require_nonzero and legacy.min_effect == 0.0
    assert "material_damping" in saved_intervals(saved)  # from accepted.interval_95
    versioned = {**saved, "format": DIAGNOSIS_FORMAT}
    assert "material_damping" not in saved_intervals(versioned)
    assert all(v == () for v in saved_special_cases(versioned).values())

    complete = json.loads(_kept_diagnosis("gravity-1", "gravity").read_text())
    # a file written before the physical-evidence tests, the grid check's switch and the
    # held-out statistic lacks only their thresholds; without a nuisance table, consistency or
    # grid records those tests leave its decision as it was, and it replays with the sum it ran
    later = {
        "nuisance_degree",
        "nuisance_min_drop",
        "consistency_level",
        "grid_bic",
        "heldout_statistic",
        "consistency_tolerance",
    }
    assert set(complete["rule"]) | later == set(DecideOptions().__dict__)
    assert all("special_case_of" in e for e in complete["evidence"])
    as_unversioned = replay_diagnosis(complete)
    as_versioned = replay_diagnosis({**complete, "format": DIAGNOSIS_FORMAT})
    as_versioned.pop("format")
    assert as_versioned == as_unversioned
    assert saved_rule(complete).heldout_statistic == "sum"
    assert saved_rule({**complete, "format": DIAGNOSIS_FORMAT}).heldout_statistic == "sum"
    assert saved_rule(complete).consistency_tolerance == 0.0


def test_the_genesis_dev_entries_replay_under_both_held_out_statistics():
    """The Genesis suite's dev entries kept without their scenes (benchmarks/data/
    diagnosis_genesis_dev_full, an out-of-library vortex among them) replay, scored against
    their conceal specs. The held-out statistic decides gravity-0: summed, the last frames,
    where every prediction has left the recording, fail the gravity change; as a geometric
    mean of the (object, block) ratios it is named, within a few percent of the truth, and
    the control stays without an effect either way. The agreement test's tolerance lets
    gravity-1's gravity pass; its grid check never ran, so it is not named."""
    from mosiv_framework.diagnose.decide import DecideOptions
    from mosiv_framework.diagnose.replay import (
        GRID_NOT_CHECKED,
        load_diagnosis,
        replay_diagnosis,
        replay_suite,
    )

    folder = KEPT / "diagnosis_genesis_dev_full"
    # the replay draws the bootstrap resamples the entries ran with (1000, the full budget's)
    wind = replay_diagnosis(load_diagnosis(folder / "wind-1" / "diagnosis.json"), DecideOptions())
    assert {e["name"]: e for e in wind["evidence"]}["wind"]["passes_heldout"]
    by_rule = {}
    for statistic in ("sum", "log"):
        summary = replay_suite(
            folder, DecideOptions(heldout_statistic=statistic), source="genesis", split="dev"
        )
        by_rule[statistic] = {s["name"]: s for s in summary["scores"]}
        assert summary["control_false_discovery_rate"] == 0.0
        assert by_rule[statistic]["outside-vortex-0"]["correct"]  # no library term named
    assert by_rule["sum"]["gravity-0"]["verdict"] == "discrepancy"
    gravity = by_rule["log"]["gravity-0"]
    assert gravity["accepted"] == "gravity" and gravity["correct"]
    assert gravity["coefficient_error"] < 0.05
    # gravity-1: the two bodies' gravity changes differ by 2 %, beyond their intervals; the
    # agreement test's tolerance (a standard deviation of 5 % of the pooled value, the
    # default) lets them agree, and the gravity then passes every test a replay can decide,
    # but the entry never checked it at a second grid, so the replay does not name it
    saved = load_diagnosis(folder / "gravity-1" / "diagnosis.json")
    for tolerance, agrees in ((0.05, True), (0.0, False)):
        replayed = replay_diagnosis(saved, DecideOptions(consistency_tolerance=tolerance))
        gravity = {e["name"]: e for e in replayed["evidence"]}["gravity"]
        assert gravity["passes_consistency"] is agrees
        assert gravity["passes_heldout"] and gravity["passes_bic"] and gravity["passes_nuisance"]
    assert gravity["grid"] is None  # at tolerance 0 it failed before the grid check, as it ran
    named = replay_diagnosis(saved, DecideOptions())
    unchecked = {e["name"]: e for e in named["evidence"]}["gravity"]
    assert unchecked["grid"]["reason"] == GRID_NOT_CHECKED and not unchecked["passes_grid"]
    assert named["accepted"]["name"] == "quadratic_drag"  # grid-checked when the entry ran


def test_the_genesis_test_entries_replay_as_they_ran():
    """The Genesis suite's test split (benchmarks/data/diagnosis_genesis_test_full) ran under
    the current rule, so its replay must give every entry the verdict and the named term its
    own run wrote (score.json), and the suite's summary the same rates: no control with an
    effect, every out-of-library field without a library term."""
    import json

    from mosiv_framework.diagnose.decide import DecideOptions
    from mosiv_framework.diagnose.replay import replay_suite

    folder = KEPT / "diagnosis_genesis_test_full"
    summary = replay_suite(folder, DecideOptions(), source="genesis", split="test")
    replayed = {s["name"]: s for s in summary["scores"]}
    ran = {path.parent.name: json.loads(path.read_text()) for path in folder.glob("*/score.json")}
    assert replayed.keys() == ran.keys() and len(ran) >= 14
    for name, score in ran.items():
        assert (replayed[name]["verdict"], replayed[name]["accepted"]) == (
            score["verdict"],
            score["accepted"],
        ), name
    assert summary["control_false_discovery_rate"] == 0.0
    assert summary["outside_reported_unexplained_rate"] == 1.0
    drags = [s for n, s in replayed.items() if "drag" in n]
    assert len(drags) == 4 and all(s["correct"] for s in drags)
    # kept without scenes, the out-of-library entries carry the law scores their runs wrote
    for name, score in ran.items():
        if name.startswith("outside-"):
            law_error = replayed[name]["extra"]["law_error"]
            assert law_error == score["extra"]["law_error"] is not None
            assert replayed[name]["extra"]["law_future_reduction"] is not None
    assert summary["outside_law_future_halved_rate"] is not None
