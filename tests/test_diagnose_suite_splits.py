"""The Genesis diagnosis suite's splits (diagnose/suite_splits.py) and their scoring: what each
split holds, that dev and test never share a scene, that entries carry nothing chosen for their
hidden effect, and that out-of-library entries are scored as outside the library."""

from __future__ import annotations

import json
import shutil
from collections import Counter
from pathlib import Path

import pytest

from mosiv_framework.cli.main import main
from mosiv_framework.conceal import parse_conceal
from mosiv_framework.conceal_fields import OUT_OF_LIBRARY_KINDS
from mosiv_framework.diagnose.suite import (
    SUITE_MARKER,
    check_suite_folder,
    default_recipe,
    entry_group,
    entry_overrides,
    score_entry,
    scored_law,
    suite_selection,
    summarise,
)
from mosiv_framework.diagnose.suite_splits import GENESIS_PAIRS, SPLIT_RECIPES, genesis_split
from mosiv_framework.errors import ConfigError
from mosiv_framework.recipes import load_recipe
from mosiv_framework.registry import get_registry

KEPT = Path(__file__).resolve().parents[1] / "benchmarks" / "data"


@pytest.mark.parametrize("split", ["dev", "test"])
def test_each_split_has_two_of_every_effect_and_six_controls(split):
    entries = genesis_split(split)
    kinds = Counter(e.kind or "control" for e in entries)
    assert kinds == {
        "linear_drag": 2,
        "quadratic_drag": 2,
        "wind": 2,
        "gravity": 2,
        "vortex": 2,
        "attractor": 2,
        "control": 6,
    }
    assert len({e.name for e in entries}) == len(entries) == 18
    for e in entries:
        group = entry_group(e.name, e.conceal or "-")
        outside = e.kind in OUT_OF_LIBRARY_KINDS
        assert group == ("control" if not e.conceal else "outside" if outside else "concealed")
        assert e.outside == outside


def test_dev_and_test_scenes_share_no_seed():
    dev, test = genesis_split("dev"), genesis_split("test")
    assert [e.name for e in dev] == [e.name for e in test]  # same effects, other scenes
    dev_seeds, test_seeds = {e.seed for e in dev}, {e.seed for e in test}
    assert len(dev_seeds) == len(test_seeds) == 18 and not dev_seeds & test_seeds


def test_entries_carry_nothing_chosen_for_their_hidden_effect():
    """No recipe override, no library restriction; the material pair follows the entry's
    position only, the same for a control as for a concealed effect."""
    for split in ("dev", "test"):
        for i, e in enumerate(genesis_split(split)):
            assert e.overrides == () and e.exclude == ""
            assert e.materials == GENESIS_PAIRS[i % len(GENESIS_PAIRS)]
            keys = {o.split("=", 1)[0] for o in entry_overrides(e, Path("out") / e.name)}
            assert keys <= {
                "scene.path",
                "output.dir",
                "scene.source.materials",
                "scene.source.seed",
                "scene.source.conceal",
            }


def test_every_spec_is_one_the_genesis_source_takes():
    """The Genesis source's options validate each entry (without importing the engine), and
    the out-of-library specs parse to out-of-library effects."""
    options = get_registry().get("scene_source", "genesis").options
    for e in genesis_split("dev") + genesis_split("test"):
        opts = options(conceal=e.conceal or None, materials=e.materials, seed=e.seed)
        assert len(opts.conceal) == (1 if e.conceal else 0)
        if e.outside:
            (effect,) = parse_conceal(e.conceal, kinds=OUT_OF_LIBRARY_KINDS)
            assert not effect.in_library


def test_the_suite_recipe_loads_with_every_entrys_overrides(tmp_path):
    recipe = default_recipe(False, "genesis")
    assert recipe == SPLIT_RECIPES["genesis"] and recipe.is_file()
    for e in genesis_split("dev")[::5]:
        loaded = load_recipe(recipe, entry_overrides(e, tmp_path / e.name))
        assert loaded.scene.source.name == "genesis"
        assert loaded.scene.source.seed == e.seed


@pytest.mark.parametrize(
    ("small", "source", "split", "message"),
    [
        (False, "synth", "dev", "only the genesis suite has splits"),
        (False, "genesis", None, "give --split dev or test"),
        (False, "genesis", "val", "give --split dev or test"),
        (True, "genesis", "dev", "no small form"),
        (False, "bullet", "dev", "valid: synth, genesis"),
    ],
)
def test_a_suite_that_does_not_exist_is_refused(small, source, split, message):
    with pytest.raises(ConfigError, match=message):
        suite_selection(small, source, split)


def test_the_cli_refuses_genesis_without_a_split(capsys, tmp_path):
    assert main(["diagnose-suite", str(tmp_path / "s"), "--source", "genesis"]) != 0
    assert "give --split dev or test" in capsys.readouterr().err
    assert not (tmp_path / "s").exists()


def test_a_folder_holds_one_split_only(tmp_path):
    (tmp_path / SUITE_MARKER).write_text(json.dumps({"source": "genesis", "split": "dev"}))
    check_suite_folder(tmp_path, "genesis", "dev")
    with pytest.raises(ConfigError, match="split 'dev', not 'genesis', 'test'"):
        check_suite_folder(tmp_path, "genesis", "test")
    with pytest.raises(ConfigError, match="source 'genesis'"):
        check_suite_folder(tmp_path, "synth", None)
    legacy = tmp_path / "legacy"
    legacy.mkdir()
    (legacy / "suite.json").write_text(json.dumps({"scores": []}))  # before splits existed
    check_suite_folder(legacy, "synth", None)
    with pytest.raises(ConfigError):
        check_suite_folder(legacy, "genesis", "dev")


def _diagnosis(verdict: str, accepted: str | None) -> dict:
    record = {"name": accepted, "value": {"acceleration": [1.0, 0.0, 0.0]}} if accepted else None
    errors = {"identified": {"future_cd_mm2": 10.0}}
    if accepted:
        errors[accepted] = {"future_cd_mm2": 4.0}
    return {
        "verdict": verdict,
        "accepted": record,
        "evidence": [{"name": accepted}] if accepted else [],
        "errors": errors,
        "where": {"signal_to_noise": 12.0},
    }


def test_out_of_library_entries_are_right_when_nothing_is_named():
    vortex = next(e for e in genesis_split("test") if e.kind == "vortex")
    effects = [parse_conceal(vortex.conceal, kinds=OUT_OF_LIBRARY_KINDS)[0].to_json()]
    law = {"law_error": 0.2, "form_correct": True, "law_samples": 24}
    right = score_entry(vortex, _diagnosis("unexplained", None), effects, law)
    assert right.correct and right.extra == law and right.coefficient_error is None
    wrong = score_entry(vortex, _diagnosis("missing physics", "wind"), effects, None)
    assert not wrong.correct and wrong.future_reduction == pytest.approx(0.6)
    # the discovered law accepted as a model names no library term either
    law_accepted = score_entry(vortex, _diagnosis("missing physics", "expression"), effects, law)
    assert law_accepted.correct and law_accepted.future_reduction == pytest.approx(0.6)
    summary = summarise([right, wrong])
    assert summary["outside_reported_unexplained_rate"] == 0.5
    assert summary["outside_median_law_error"] == 0.2
    assert summary["outside_law_form_rate"] == 1.0
    assert summary["correct_first_rate"] is None  # no library effect among them


def test_the_scored_law_is_the_one_the_diagnosis_ends_with():
    discovered, refitted = {"formula": "found"}, {"formula": "refitted"}
    none = _diagnosis("unexplained", None)
    assert scored_law({**none, "discovered": discovered}) is discovered
    expression = {**_diagnosis("missing physics", "expression"), "discovered": discovered}
    assert scored_law({**expression, "formula": {"refitted": refitted}}) is refitted
    assert scored_law(expression) is discovered
    assert scored_law({**_diagnosis("missing physics", "wind"), "discovered": discovered}) is None


def test_a_dev_folder_replays_under_its_split(tmp_path):
    """A finished entry of the dev split (a kept synth diagnosis standing in for it) replays
    with --source genesis --split dev; the other 17 are missing; the test split is refused."""
    kept = sorted(KEPT.glob("**/wind-0/diagnosis.json"))[0].parent
    shutil.copytree(kept, tmp_path / "wind-0")
    (tmp_path / SUITE_MARKER).write_text(json.dumps({"source": "genesis", "split": "dev"}))
    from mosiv_framework.diagnose.decide import DecideOptions
    from mosiv_framework.diagnose.replay import replay_suite

    summary = replay_suite(tmp_path, DecideOptions(), source="genesis", split="dev")
    assert [s["name"] for s in summary["scores"]] == ["wind-0"]
    assert len(summary["missing"]) == 17 and summary["split"] == "dev"
    with pytest.raises(ConfigError):
        replay_suite(tmp_path, DecideOptions(), source="genesis", split="test")


def test_a_tested_law_scores_its_future_on_out_of_library_entries():
    """An out-of-library entry whose diagnosis tested the discovered law as a model (its
    ``expression`` row) records how much of the identified model's future Chamfer the law
    removes, accepted or not; the summary counts the laws that at least halve it (issue 40's
    bar) and the table shows the figure where no term was accepted."""
    from mosiv_framework.diagnose.suite import table

    vortex = next(e for e in genesis_split("test") if e.kind == "vortex")
    halved = _diagnosis("unexplained", None)
    halved["errors"]["expression"] = {"future_cd_mm2": 4.0}
    worse = _diagnosis("unexplained", None)
    worse["errors"]["expression"] = {"future_cd_mm2": 15.0}
    scores = [score_entry(vortex, d, [], None) for d in (halved, worse)]
    assert scores[0].extra["law_future_reduction"] == pytest.approx(0.6)
    assert scores[1].extra["law_future_reduction"] == pytest.approx(-0.5)
    assert scores[0].future_reduction is None  # nothing accepted
    untested = score_entry(vortex, _diagnosis("unexplained", None), [], None)
    assert "law_future_reduction" not in untested.extra
    summary = summarise([*scores, untested])
    assert summary["outside_law_future_halved_rate"] == 0.5
    text = table(summary)
    assert "discovered law: 60 %" in text and "law's future Chamfer at least halved 50 %" in text
    control = next(e for e in genesis_split("test") if not e.conceal)
    assert "law_future_reduction" not in score_entry(control, halved, [], None).extra
