"""Unit tests of the diagnosis suite: resuming scored entries, preparing, scoring, its figure
and the refit budget a recipe sets (no simulator)."""

from __future__ import annotations

import json

import pytest

from mosiv_framework.errors import ConfigError


def test_suite_resumes_scored_entries_and_rejects_unknown_names(tmp_path):
    """A suite stopped part-way picks up the scores already on disk instead of recomputing,
    and ``only`` names that are not entries are refused with the valid ones."""
    from dataclasses import asdict

    from mosiv_framework.diagnose.formats import SUITE_FORMAT, FormatError
    from mosiv_framework.diagnose.suite import Score, run_suite, suite_entries
    from mosiv_framework.errors import ConfigError

    entry = suite_entries(small=True)[0]
    stored = Score(
        entry.name, entry.conceal, "missing physics", "wind", "wind", True, 9.0, 0.05, 0.9
    )
    (tmp_path / entry.name).mkdir()
    (tmp_path / entry.name / "score.json").write_text(json.dumps(asdict(stored)))
    summary = run_suite(tmp_path, small=True, only=[entry.name])
    assert summary["scores"] == [asdict(stored)]
    assert summary["missing"] == []
    assert summary["correct_first_rate"] == 1.0
    assert (tmp_path / "suite.png").stat().st_size > 0  # the suite's figure next to its table
    assert json.loads((tmp_path / "suite.json").read_text())["format"] == SUITE_FORMAT
    # a score of a format this version cannot read is refused, not misread
    (tmp_path / entry.name / "score.json").write_text(json.dumps({"format": "x/2"}))
    with pytest.raises(FormatError, match="score.json: field 'format' is 'x/2'"):
        run_suite(tmp_path, small=True, only=[entry.name])
    with pytest.raises(ConfigError, match="valid"):
        run_suite(tmp_path, small=True, only=["no-such-entry"])


def test_a_scored_entry_carries_its_format_and_is_resumed_from_it(tmp_path, monkeypatch):
    """run_entry writes score.json with its format; a second call reads it back instead of
    running anything."""
    from mosiv_framework.diagnose import suite
    from mosiv_framework.diagnose.formats import SCORE_FORMAT

    entry = next(e for e in suite.suite_entries(small=True) if not e.conceal)
    diagnosis = {
        "verdict": "no missing physics",
        "accepted": None,
        "evidence": [],
        "errors": {},
        "where": {"signal_to_noise": 1.5},
    }
    # the pipeline's part here: the run folder
    monkeypatch.setattr(suite, "run_pipeline", lambda recipe, run_dir: run_dir.mkdir())
    monkeypatch.setattr(suite, "diagnose_run", lambda run_dir, budget: diagnosis)
    monkeypatch.setattr(suite, "read_scene", lambda path: type("S", (), {"gt_effects": list})())
    recipe = suite.DEFAULT_RECIPES[True]
    score = suite.run_entry(entry, tmp_path, recipe, "small")
    saved = json.loads((tmp_path / entry.name / "score.json").read_text())
    assert saved["format"] == SCORE_FORMAT and saved["name"] == entry.name
    assert score.correct and score.signal_to_noise == 1.5

    def nothing_runs(*args, **kwargs):
        raise AssertionError("a scored entry is resumed from its score.json")

    monkeypatch.setattr(suite, "run_pipeline", nothing_runs)
    assert suite.run_entry(entry, tmp_path, recipe, "small") == score


def test_a_prepared_suite_runs_the_pipeline_and_diagnoses_nothing(tmp_path, monkeypatch):
    """``prepare_only``: the entries' pipelines run (into OUT/entry, for another machine to
    diagnose from their stages), no diagnosis starts, and nothing is scored."""
    from mosiv_framework.diagnose import suite

    ran = []
    monkeypatch.setattr(suite, "run_pipeline", lambda recipe, run_dir: ran.append(run_dir))

    def no_diagnosis(*args, **kwargs):
        raise AssertionError("a prepared suite must not diagnose")

    monkeypatch.setattr(suite, "diagnose_run", no_diagnosis)
    names = [e.name for e in suite.suite_entries(small=True)[:2]]
    summary = suite.run_suite(tmp_path, small=True, only=names, prepare_only=True)
    assert summary == {"prepared": sorted(names)}
    assert sorted(ran) == sorted(tmp_path / n for n in names)
    assert not list(tmp_path.glob("*/score.json")) and not (tmp_path / "suite.json").exists()


def test_a_scenes_only_suite_generates_the_scenes_and_runs_nothing_else(tmp_path, monkeypatch):
    """``scenes_only``: each entry's scene is generated (the real scene source, with its
    concealed effect written to gt/effects.json), no pipeline or diagnosis starts; a second
    call keeps the scenes as they are, and a later full run of the folder starts from them."""
    from mosiv_framework.diagnose import suite
    from mosiv_framework.errors import ConfigError

    def nothing_runs(*args, **kwargs):
        raise AssertionError("scenes_only must not run the pipeline or diagnose")

    monkeypatch.setattr(suite, "run_pipeline", nothing_runs)
    monkeypatch.setattr(suite, "diagnose_run", nothing_runs)
    entry = next(e for e in suite.suite_entries(small=True) if e.conceal)
    summary = suite.run_suite(tmp_path, small=True, only=[entry.name], scenes_only=True)
    assert summary == {"generated": [entry.name]}
    scene = suite.read_scene(tmp_path / entry.name / "scene")
    kinds = [effect["kind"] for effect in scene.gt_effects()]
    assert kinds == [entry.conceal.split(":")[0]]
    assert sorted(p.name for p in (tmp_path / entry.name).iterdir()) == ["scene"]
    assert json.loads((tmp_path / suite.SUITE_MARKER).read_text())["source"] == "synth"
    stamp = (tmp_path / entry.name / "scene" / "scene.json").stat().st_mtime_ns
    suite.run_suite(tmp_path, small=True, only=[entry.name], scenes_only=True)
    assert (tmp_path / entry.name / "scene" / "scene.json").stat().st_mtime_ns == stamp
    with pytest.raises(ConfigError, match="give one of them"):
        suite.run_suite(tmp_path, small=True, prepare_only=True, scenes_only=True)


def test_concealed_plasticity_and_object_friction_specs():
    from mosiv_framework.conceal import YIELD_STRESS_RANGE, parse_conceal
    from mosiv_framework.laws import get_law

    spec = get_law("plasticine").param("yield_stress")
    assert YIELD_STRESS_RANGE == (spec.lower, spec.upper)
    assert parse_conceal("plasticity")[0].params == {"yield_stress": 3000.0}
    assert parse_conceal("object_friction:coefficient=0")[0].params == {"coefficient": 0.0}
    with pytest.raises(ValueError, match="yield_stress"):
        parse_conceal("plasticity:yield_stress=1")
    with pytest.raises(ValueError, match=">= 0"):
        parse_conceal("object_friction:coefficient=-0.1")


def test_suite_scores_a_per_object_plasticity_name_as_its_kind():
    from mosiv_framework.diagnose.suite import candidate_kind, suite_entries

    assert candidate_kind("plasticity@2") == "plasticity"
    assert candidate_kind("wind") == "wind"
    entries = {e.name: e for e in suite_entries(small=False)}
    for name in ("plasticity-0", "plasticity-1"):
        assert entries[name].materials.split(",").count("elastic") == 1
    assert entries["object_friction-0"].overrides == ("identify.identify_friction=false",)


def test_coefficient_error_is_relative_to_truth_or_to_the_change_when_truth_is_zero():
    from mosiv_framework.diagnose.suite import coefficient_error

    wind = {"kind": "wind", "params": {"acceleration": [2.0, 0.0, 0.0]}}
    assert coefficient_error({"value": {"acceleration": [2.2, 0.0, 0.0]}}, wind) == (
        pytest.approx(0.1)
    )
    # frictionless bodies (truth 0) against an assumed 0.3: 0.009 is 3 % of the 0.3 change
    frictionless = {"kind": "object_friction", "params": {"coefficient": 0.0}}
    fitted = {"value": {"friction_change": -0.291, "coefficient": 0.009}}
    assert coefficient_error(fitted, frictionless) == pytest.approx(0.03)
    # nothing to compare with: no error rather than a division by zero
    assert coefficient_error({"value": {"coefficient": 0.1}}, frictionless) is None


def test_suite_figure_draws_every_kind_of_entry(tmp_path):
    """The suite figure takes controls and misses (no coefficient, no reduction), a term that
    made the future worse, and an exact coefficient, and refuses an empty suite."""
    import imageio.v3 as iio

    from mosiv_framework.diagnose.suite import Score, summarise
    from mosiv_framework.diagnose.suite_plot import plot_suite

    scores = [
        Score(
            "wind-0",
            "wind:acceleration=1.5,0,0",
            "missing physics",
            "wind",
            "wind",
            True,
            182.0,
            0.0,
            0.99,
        ),
        Score(
            "ground_restitution-1",
            "ground_restitution:coefficient=0.9",
            "unexplained",
            None,
            "ground_restitution",
            False,
            26.6,
            None,
            None,
        ),
        Score("control-1", "-", "missing physics", "gravity", "gravity", False, 49.3, None, -0.4),
        Score(
            "outside-gravity",
            "gravity:acceleration=0,0,-7.5",
            "unexplained",
            None,
            None,
            True,
            64.8,
            None,
            None,
        ),
    ]
    summary = summarise(scores)
    path = plot_suite(summary, tmp_path / "suite.png")
    image = iio.imread(path)
    assert image.ndim == 3 and image.shape[0] > 200 and image.shape[1] > 800
    # not a blank canvas: the green and red markers are drawn
    assert image[..., :3].std() > 10
    with pytest.raises(ValueError, match="no scored entries"):
        plot_suite(summarise([]), tmp_path / "empty.png")
    # the figure's title names its data
    from mosiv_framework.diagnose.suite_plot import _data_line

    genesis = _data_line({**summary, "source": "genesis", "split": "dev"})
    assert genesis.startswith("data: the dev split of the genesis suite, scenes made by the Gen")
    assert "mosiv-synth" in _data_line(summary)


def test_a_recipe_sets_the_refit_budget_and_bad_values_are_named(tmp_path):
    from omegaconf import OmegaConf

    from mosiv_framework.diagnose.diagnosis import BUDGETS, resolve_budget
    from mosiv_framework.recipes import load_recipe

    recipe = "recipes/diagnose_small.yaml"
    section = load_recipe(
        recipe, ["diagnose.iterations=40", "diagnose.refit_velocity_lr=1e-4"]
    ).diagnose
    budget = resolve_budget("full", section)
    assert (budget.iterations, budget.velocity_lr) == (40, 1e-4)
    # what the recipe leaves unset stays the budget's
    assert (budget.starts, budget.polish) == (BUDGETS["full"].starts, BUDGETS["full"].polish)
    assert not budget.far_start
    assert resolve_budget(
        "full", load_recipe(recipe, ["diagnose.far_start=true"]).diagnose
    ).far_start
    # the fresh identifications: the full budget's (every model) unless the recipe says
    assert BUDGETS["full"].reidentify == "every"
    fresh = load_recipe(recipe, ["diagnose.reidentify=null-model"]).diagnose
    assert resolve_budget("full", fresh).reidentify == "null-model"
    assert resolve_budget("full", OmegaConf.create({})) == BUDGETS["full"]
    with pytest.raises(ConfigError, match="budget 'huge' is unknown; valid: \\['full', 'small'\\]"):
        resolve_budget("huge")
    with pytest.raises(ConfigError, match="diagnose.reidentify='some': valid values are every, "):
        load_recipe(recipe, ["diagnose.reidentify=some"])
    with pytest.raises(ConfigError) as err:
        load_recipe(recipe, ["diagnose.refit_velocity_lr=0", "diagnose.polish=-1"])
    assert "diagnose.refit_velocity_lr=0.0: must be a positive step in m/s" in str(err.value)
    assert "diagnose.polish=-1: must be >= 0" in str(err.value)


def test_suite_overrides_are_checked_before_any_entry_runs(tmp_path):
    from mosiv_framework.diagnose.suite import run_suite

    with pytest.raises(ConfigError, match="diagnose.iterations=0: must be >= 1"):
        run_suite(tmp_path / "suite", small=True, overrides=["diagnose.iterations=0"])
    assert not any((tmp_path / "suite").glob("*/"))  # nothing generated
