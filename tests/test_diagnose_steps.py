"""The saved steps of a diagnosis (diagnose/steps.py): what their key covers, and that only an
unbroken prefix of them is reused. The end-to-end resume is in test_diagnose.py."""

from __future__ import annotations

import json
import logging

from omegaconf import OmegaConf

from mosiv_framework.diagnose.steps import FOLDER, DiagnosisSteps, diagnosis_key
from mosiv_framework.pipeline.rundir import RunDir

RECIPE = {
    "simulator": {"name": "warp-mpm", "grid": 48, "substeps": 60, "device": "auto"},
    "identify": {"identify_friction": True, "param_iterations": 80},
    "losses": {"chamfer": {"weight": 1.0, "max_points": 1000}},
    "diagnose": {"iterations": None},
    "physics_terms": {},
}
BASE = {"budget": {"iterations": 20}, "fit_frames": [1, 2, 3], "heldout": [4, 5]}


def _run(tmp_path) -> RunDir:
    run = RunDir(tmp_path / "run")
    run.save_json("identified.json", {"objects": {"1": {"E": 1.0e5}}})
    return run


def _key(run, recipe=RECIPE, **changes) -> str:
    return diagnosis_key(run, recipe=OmegaConf.create(recipe), **{**BASE, **changes})


def test_the_key_follows_what_a_refit_depends_on_but_not_the_device(tmp_path) -> None:
    run = _run(tmp_path)
    key = _key(run)
    assert key == _key(run)
    assert key == _key(run, simulator_overrides={"device": "cuda:1"})
    assert key != _key(run, budget={"iterations": 21})
    assert key != _key(run, fit_frames=[1, 2])
    assert key != _key(run, simulator_overrides={"substeps": 120})
    for section, change in (
        ("identify", {"identify_friction": False}),
        ("losses", {"chamfer": {"weight": 1.0, "max_points": 500}}),
        ("simulator", {"grid": 64}),
    ):
        recipe = {**RECIPE, section: {**RECIPE[section], **change}}
        assert key != _key(run, recipe), section
    run.save_json("identified.json", {"objects": {"1": {"E": 2.0e5}}})
    assert key != _key(run)  # the run was identified again


def test_saved_steps_are_reused_only_as_an_unbroken_prefix(tmp_path, caplog) -> None:
    run = _run(tmp_path)
    calls = []

    def compute(name):
        return lambda: calls.append(name) or {"value of": name}

    first = DiagnosisSteps(run, "k1")
    for name in ("locate", "screen", "refit-null"):
        first.get(name, compute(name))
    assert calls == ["locate", "screen", "refit-null"] and first.resumed == []

    again = DiagnosisSteps(run, "k1")
    assert again.get("locate", compute("locate")) == {"value of": "locate"}
    assert again.resumed == ["locate"] and calls == ["locate", "screen", "refit-null"]

    # the screening's file is unreadable: it and every later step are computed again
    (run.path(FOLDER) / "screen.pt").write_bytes(b"not a torch file")
    broken = DiagnosisSteps(run, "k1")
    with caplog.at_level(logging.WARNING, logger="mosiv_framework.diagnose.steps"):
        for name in ("locate", "screen", "refit-null"):
            broken.get(name, compute(name))
    assert broken.resumed == ["locate"]
    assert calls[-2:] == ["screen", "refit-null"]
    assert any("could not read the saved step screen" in m for m in caplog.messages)

    # another key (another budget or identified model) reuses nothing
    other = DiagnosisSteps(run, "k2")
    other.get("locate", compute("locate"))
    assert other.resumed == [] and calls[-1] == "locate"
    other.clear()
    assert not run.path(FOLDER).exists()
    assert json.loads(run.path("identified.json").read_text())  # the run itself is untouched


def test_steps_computed_together_resume_their_saved_prefix(tmp_path) -> None:
    """``get_many``: the saved steps of an unbroken prefix are read, the rest computed by one
    call and each saved, so a later diagnosis resumes every one of them."""
    run = _run(tmp_path)
    calls = []

    def compute(names):
        calls.append(list(names))
        return [{"value of": n} for n in names]

    names = ["refit-null", "refit-wind", "refit-linear_drag"]
    first = DiagnosisSteps(run, "k1")
    assert first.get_many(names, compute) == [{"value of": n} for n in names]
    assert calls == [names]

    again = DiagnosisSteps(run, "k1")
    assert again.get_many(names, compute) == [{"value of": n} for n in names]
    assert again.resumed == names and calls == [names]

    # the middle step is lost: it and the steps after it are computed again, together
    (run.path(FOLDER) / "refit-wind.pt").unlink()
    partly = DiagnosisSteps(run, "k1")
    assert partly.get_many(names, compute)[0] == {"value of": "refit-null"}
    assert partly.resumed == ["refit-null"] and calls[-1] == names[1:]
    # and a step after them is not read from its old file either
    assert partly.get("interval", lambda: "computed") == "computed"
