"""benchmarks/genesis_resolution.py: the stability check of each (grid, substeps) against the
caps' formula, the chosen defaults' rule on made-up rows, and the whole study (runs, refusals,
table, CSV, plot, merge, resume, RESULTS section) on the committed tiny Genesis scene."""

from __future__ import annotations

import csv
import importlib
import json
import math
import sys
from pathlib import Path

import pytest

from mosiv_framework.errors import ConfigError
from mosiv_framework.laws import get_law
from mosiv_framework.recipes import check_recipe

ROOT = Path(__file__).resolve().parents[1]
BENCHMARKS = ROOT / "benchmarks"
TINY = ROOT / "plugins" / "mosiv-genesis" / "tests" / "data" / "tiny_scene"
RECIPE = ROOT / "recipes" / "genesis_oracle.yaml"
#: the smallest identification that still runs every stage of the pipeline on CPU
SMALL = [
    "simulator.device=cpu",
    "identify.velocity_iterations=0",
    "identify.param_iterations=1",
    "identify.global_candidates=0",
    # the contact and stress choices are the identification's business, not the study's (20
    # steps a variant)
    "identify.contact=fixed",
    "identify.law_choice=fixed",
    "identify.intervals=false",
    "losses.chamfer.max_points=256",
    "evaluate.emd_samples=128",
    "evaluate.render_videos=false",
]


def _modules():
    """(genesis_resolution, genesis_resolution_report), importing their benchmark siblings as
    they do when run from benchmarks/."""
    sys.path.insert(0, str(BENCHMARKS))
    try:
        return (
            importlib.import_module("genesis_resolution"),
            importlib.import_module("genesis_resolution_report"),
        )
    finally:
        sys.path.remove(str(BENCHMARKS))


def _sets(sets: list[str]) -> list[str]:
    return [x for s in sets for x in ("--set", s)]


# --------------------------------------------------------------------------------------------
# which substep counts a grid needs


def _analytic_need(grid: int) -> int:
    """The fewest substeps at which, for every object of the tiny scene, the stiffness cap holds
    both the law's starting E and the true E in the density gauge.

    Explicit MPM follows a P-wave of speed c only while c dt <= cfl dx; with the law's default
    density rho0 and Poisson ratio nu0 (what identification caps with) that allows
    E <= rho0 (cfl dx / dt)^2 (1 + nu0)(1 - 2 nu0) / (1 - nu0), with dt = 1 / (fps n)."""
    scene = json.loads((TINY / "scene.json").read_text())
    truth = json.loads((TINY / "gt" / "params.json").read_text())["objects"]
    lower, upper = scene["domain"]["lower"], scene["domain"]["upper"]
    dx = max(u - lo for lo, u in zip(lower, upper)) / grid
    gauge = 1000.0 / truth[0]["params"]["rho"]  # the first density held at the default
    need = 1
    for obj in truth:
        law = get_law(obj["material"])
        rho0, nu0, start = (law.param(n).default for n in ("rho", "nu", "E"))
        cap_at_one = rho0 * (0.5 * dx * scene["fps"]) ** 2 * (1 + nu0) * (1 - 2 * nu0) / (1 - nu0)
        wanted = max(start, obj["params"]["E"] * gauge)
        need = max(need, math.ceil(math.sqrt(wanted / cap_at_one) - 1e-9))
    return need


def test_unstable_pairs_are_refused_or_raised_to_the_count_the_caps_need():
    res, _ = _modules()
    recipe = res.study_recipe(RECIPE, ["simulator.device=cpu"])
    for grid in (16, 24, 64):
        need = res.substeps_needed(TINY, recipe, grid)
        assert need == _analytic_need(grid)
        assert res.check_configuration(TINY, recipe, grid, need) == []
        assert res.check_configuration(TINY, recipe, grid, need - 1)
    # 60 substeps keep grid 16 but not grid 24: the sand's true E is beyond the cap there
    assert res.check_configuration(TINY, recipe, 16, 60) == []
    (problem,) = res.check_configuration(TINY, recipe, 24, 60)
    assert "object 2 (sand)" in problem and "out of reach" in problem
    refused = res.plan_configuration(TINY, recipe, 24, 60, policy="refuse")
    assert refused["substeps"] is None and refused["need"] == _analytic_need(24)
    raised = res.plan_configuration(TINY, recipe, 24, 60, policy="raise")
    assert raised["substeps"] == raised["need"] == _analytic_need(24)
    assert "raised to" in res.describe(raised) and "refused" in res.describe(refused)


def test_the_validators_own_refusal_is_among_the_problems():
    res, _ = _modules()
    recipe = res.study_recipe(RECIPE, ["simulator.device=cpu"])
    pair = [f"scene.path={TINY}", "simulator.grid=24", "simulator.substeps=20"]
    with pytest.raises(ConfigError) as caught:
        check_recipe(RECIPE, pair)  # what `mosiv recipe validate` says of this pair
    # the validator's messages name the recipe file first
    said = [p.split(": ", 1)[1] for p in caught.value.problems]
    problems = res.check_configuration(TINY, recipe, 24, 20)
    assert said and all(p in problems for p in said)
    assert "identification starts from" in problems[0]


def test_a_part_of_an_unstable_pair_writes_its_refusal_and_exits_2(tmp_path):
    res, _ = _modules()
    out = tmp_path / "out"
    argv = ["--scenes", str(TINY), "--out", str(out), "--grid", "24", "--substeps", "60"]
    assert res.main([*argv, "--part", *_sets(SMALL)]) == 2
    row = json.loads((out / "parts" / "tiny_scene__g24__s60.json").read_text())
    assert row["substeps"] is None and row["need"] == _analytic_need(24)
    assert "out of reach" in row["refused"] and not (out / "configs").exists()


def test_the_output_folder_of_someone_else_or_of_another_study_is_refused(tmp_path):
    res, _ = _modules()
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("keep")
    argv = ["--scenes", str(TINY), "--grids", "24", "--substeps", "60", *_sets(SMALL)]
    with pytest.raises(SystemExit, match="not a study folder"):
        res.main([*argv, "--out", str(mine)])
    assert sorted(p.name for p in mine.iterdir()) == ["notes.txt"]
    study = tmp_path / "study"
    res.main([*argv, "--out", str(study)])  # only a refused pair: nothing runs
    with pytest.raises(SystemExit, match="holds a study of"):
        res.main([*argv, "--out", str(study), "--set", "identify.param_iterations=2"])


# --------------------------------------------------------------------------------------------
# the chosen defaults


def _row(scene, grid, substeps, e=None, angle=None, *, used=None, refused=False):
    row = {"scene": scene, "grid": grid, "substeps_requested": substeps, "problems": []}
    row |= {"substeps": None if refused else (used or substeps), "need": 50}
    if used:
        row["problems"] = ["too few substeps"]
    row["data"] = {"generator": "mosiv-genesis (Genesis 1.4.5, MPM, cpu)", "ranges": "wide"}
    if refused:
        row["problems"] = ["too few substeps"]
        return {**row, "refused": "too few substeps"}
    params = {
        "E": {"error": e, "value": 1.0, "true": 2.0},
        "friction_angle": {"error": angle, "value": 30.0, "true": 31.0},
    }
    objects = {"1": {"family": "sand", "params": params}}
    return {**row, "objects": objects, "time_s": float(grid), "peak_memory_gb": grid / 64}


def _rows():
    """Scenes A and B. The finest complete configuration, grid 64 with 200 substeps, has median
    E error 15 % and friction angle error 3 deg; grid 64 with 400 would be finer but scene B
    was refused there, and so was B at grid 16 with 200, which would otherwise qualify."""
    return [
        *(_row(s, 64, 200, e, a) for s, e, a in (("A", 10, 2), ("B", 20, 4))),
        _row("A", 64, 400, 1, 0),
        _row("B", 64, 400, refused=True),
        *(_row(s, 16, 100, e, a) for s, e, a in (("A", 40, 2), ("B", 50, 4))),
        _row("A", 16, 200, 10, 3),
        _row("B", 16, 200, refused=True),
        # E median 18 (within 5 points of 15), friction angle 3.5 (within 1 deg of 3)
        *(_row(s, 32, 100, e, a) for s, e, a in (("A", 16, 3), ("B", 20, 4))),
        # E median 15.5, friction angle 3.5; B ran with raised substeps
        _row("A", 32, 200, 15, 3),
        _row("B", 32, 200, 16, 4, used=260),
    ]


def test_defaults_are_the_coarsest_configuration_within_tolerance_of_the_finest():
    _, report = _modules()
    study = report.make_study(_rows(), tolerance=5.0, tolerance_deg=1.0)
    assert study["scenes"] == ["A", "B"] and study["params"] == ["E", "friction_angle"]
    configs = {(c["grid"], c["substeps_requested"]): c for c in study["configs"]}
    assert list(configs) == [(16, 100), (16, 200), (32, 100), (32, 200), (64, 200), (64, 400)]
    assert configs[(64, 200)]["errors"]["E"]["median"] == pytest.approx(15.0)
    assert configs[(64, 400)]["complete"] is False and configs[(64, 400)]["refused"] == ["B"]
    assert configs[(32, 200)]["substeps_used"] == [200, 260]
    assert configs[(32, 100)]["time_max_s"] == 32.0
    assert configs[(32, 100)]["peak_memory_max_gb"] == pytest.approx(0.5)
    d = study["defaults"]
    assert d["reference"] == {"grid": 64, "substeps": 200}
    assert (d["grid"], d["substeps"]) == (32, 100)
    # a tighter tolerance: grid 32 with 100 (E 18) drops out, 200 (E 15.5) stays, and its
    # default is the count every scene needed (260)
    tight = report.make_study(_rows(), tolerance=1.0, tolerance_deg=1.0)["defaults"]
    assert (tight["grid"], tight["substeps"]) == (32, 260)
    # the friction angle's tolerance is in degrees: 0.4 deg leaves only the reference
    strict = report.make_study(_rows(), tolerance=5.0, tolerance_deg=0.4)["defaults"]
    assert (strict["grid"], strict["substeps"]) == (64, 200)
    text = report.markdown(study, plot_link="convergence.png")
    assert "`simulator.grid=32 simulator.substeps=100`" in text
    assert "| 32 | 200 (raised to 260) | 2 / 0 / 0 |" in text
    assert "B at grid 64 with 400 substeps: refused (needs at least 50)" in text
    assert "| A | 1 sand | E % | 2 | 40 (1) | 10 (1) | 16 (1) | 15 (1) | 10 (1) | 1 (1) |" in text


def test_no_defaults_without_a_configuration_that_ran_every_scene():
    _, report = _modules()
    rows = [_row("A", 16, 100, 10, 1), _row("B", 16, 100, refused=True)]
    study = report.make_study(rows, tolerance=5.0, tolerance_deg=1.0)
    assert study["defaults"]["grid"] is None
    assert report.defaults_line(study).startswith("The study's choice: none")


def test_a_configuration_with_scenes_still_to_run_blocks_the_choice_and_is_compared_paired():
    """Grid 64 ran on A only (B has no row: stopped, not refused): the rule must not fall back
    to grid 32 as if it were the finest, and the two grids are compared on A alone."""
    _, report = _modules()
    rows = [_row("A", 32, 100, 40, 2), _row("B", 32, 100, 60, 6), _row("A", 64, 100, 10, 1)]
    for row, future in zip(rows, (900.0, 300.0, 500.0)):
        row["future_cd_mm2"] = future
    study = report.make_study(rows, tolerance=5.0, tolerance_deg=1.0)
    configs = {c["grid"]: c for c in study["configs"]}
    assert configs[64]["missing"] == ["B"] and configs[32]["missing"] == []
    assert configs[32]["future_cd"]["median"] == pytest.approx(600.0)
    d = study["defaults"]
    assert d["grid"] is None
    assert d["unfinished"] == [{"grid": 64, "substeps": 100, "missing": ["B"]}]
    line = report.defaults_line(study)
    assert line.startswith("The study's choice: none: the study is unfinished")
    assert "grid 64 with 100 substeps has no row for B" in line
    paired = {c["grid"]: c for c in study["paired"]["configs"]}
    assert study["paired"]["scenes"] == ["A"]
    assert paired[32]["errors"]["E"]["median"] == pytest.approx(40.0)
    assert paired[64]["errors"]["E"]["median"] == pytest.approx(10.0)
    assert paired[32]["future_cd"]["median"] == pytest.approx(900.0)
    text = report.markdown(study, plot_link="convergence.png")
    assert "On the scenes every configuration ran (A):" in text
    assert "| 64 | 100 | 10 | 1 | 500 |" in text
    # once every part is in there is no paired table, and the rule chooses
    rows.append(_row("B", 64, 100, 12, 2))
    done = report.make_study(rows, tolerance=5.0, tolerance_deg=1.0)
    assert done["paired"] is None and done["defaults"]["grid"] == 64


# --------------------------------------------------------------------------------------------
# the whole study on CPU


def test_study_on_the_tiny_genesis_scene(tmp_path, capsys):
    """Two grids and two substep counts: 30 substeps are too few at both grids (refused), 90
    keep both, so two configurations run, each in its own process; then the files, the merge,
    a resumed rerun and the RESULTS section."""
    res, report = _modules()
    scenes = tmp_path / "scenes"
    scenes.mkdir()
    (scenes / "E-S").symlink_to(TINY, target_is_directory=True)
    results = tmp_path / "docs" / "RESULTS.md"
    results.parent.mkdir()
    results.write_text("# Results\n\n## From video\n\nkept\n")
    out = tmp_path / "out"
    argv = ["--scenes", str(scenes), "--out", str(out), "--grids", "16", "24"]
    argv += ["--substeps", "30", "90", *_sets(SMALL), "--write-results", str(results)]
    assert res.main(argv) == 0
    study = json.loads((out / "table.json").read_text())
    by_key = {(r["grid"], r["substeps_requested"]): r for r in study["rows"]}
    assert sorted(by_key) == [(16, 30), (16, 90), (24, 30), (24, 90)]
    for grid in (16, 24):
        assert (
            by_key[(grid, 30)]["need"] == _analytic_need(grid) and "refused" in by_key[(grid, 30)]
        )
        ran = by_key[(grid, 90)]
        assert "error" not in ran, ran.get("error")
        assert ran["substeps"] == 90 and ran["device"] == "CPU" and ran["time_s"] > 0
        assert ran["peak_memory_gb"] > 0
        assert (out / "configs" / f"g{grid}-s90" / "runs" / "E-S" / "metrics.json").is_file()
        sand = ran["objects"]["2"]["params"]
        assert sand["E"]["true"] == pytest.approx(860152.6458487997)
        assert sand["E"]["value"] > 0 and sand["friction_angle"]["error"] is not None
    assert study["params"] == ["E", "nu", "rho", "friction_angle", "initial_velocity"]
    assert (study["defaults"]["grid"], study["defaults"]["substeps"]) in ((16, 90), (24, 90))
    with (out / "table.csv").open() as handle:
        lines = list(csv.DictReader(handle))
    assert sum(line["status"] == "refused" for line in lines) == 2
    ok = [line for line in lines if line["status"] == "ok"]
    # two objects: E, nu, rho, v0 each, and the sand's friction angle, at two configurations
    assert len(ok) == 2 * 9 and {line["unit"] for line in ok} == {"%", "deg"}
    png = (out / "convergence.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 10_000
    # the merge alone gives the same table
    for name in ("table.json", "table.csv", "table.md", "convergence.png"):
        (out / name).unlink()
    assert res.main(["--out", str(out), "--merge"]) == 0
    merged = json.loads((out / "table.json").read_text())
    assert {k: merged[k] for k in ("rows", "configs", "defaults")} == {
        k: study[k] for k in ("rows", "configs", "defaults")
    }
    assert (out / "convergence.png").is_file() and (out / "table.csv").is_file()
    # a rerun resumes: the finished configurations are not run again
    capsys.readouterr()
    assert res.main(argv) == 0
    assert capsys.readouterr().out.count("finished before") == 2
    text = results.read_text()
    assert f"## {report.SECTION}" in text and text.endswith("## From video\n\nkept\n")
    assert "--scenes SCENES --out OUT" in text and str(tmp_path) not in text
    assert report._fill(report.defaults_line(merged)) in text
    assert "![error against grid](img/genesis_resolution.png)" in text
    assert (results.parent / "img" / "genesis_resolution.png").is_file()
    assert text.count(f"## {report.SECTION}") == 1
