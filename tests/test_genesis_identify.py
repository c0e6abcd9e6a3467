"""benchmarks/genesis_identify.py: the table from per-scene metrics, the RESULTS.md section,
and one end-to-end run on the committed tiny Genesis scene."""

from __future__ import annotations

import datetime
import json
import statistics
import sys
from pathlib import Path

import pytest

from mosiv_framework.testing.scripts import load_script

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "benchmarks" / "genesis_identify.py"
TINY = ROOT / "plugins" / "mosiv-genesis" / "tests" / "data" / "tiny_scene"


def _bench():
    return load_script(SCRIPT)


def _interval(low, high, kind):
    return {"low": low, "high": high, "kind": kind}


def _metrics(*, e_true, e_value, rho1, kind, future_cd, sand=None, v0_rel=0.01):
    """metrics.json of a two-object scene: object 1 elastic (the gauge object, identified
    density 1000 against a true ``rho1``), object 2 plasticine or, with ``sand`` = (true, value)
    of the friction angle, sand. ``e_true``/``e_value``: E of both objects; ``kind``: the kind
    of both E intervals (two-sided ones span +-10 % around the identified value)."""
    gauge = rho1 / 1000.0

    def e_err(true, value):
        return {
            "value": value,
            "true": true,
            "rel_error": abs(value - true) / true,
            "rel_error_gauge_free": abs(value * gauge - true) / true,
        }

    def e_interval(value):
        if kind == "two-sided":
            return _interval(0.9 * value, 1.1 * value, kind)
        return _interval(0.5 * value, None, kind)

    v0 = {"value": [1, 0, 0], "true": [1, 0, 0], "rel_error": v0_rel}
    errors = {
        "1": {
            "E": e_err(e_true[0], e_value[0]),
            "rho": {"value": 1000.0, "true": rho1, "rel_error": abs(1000 - rho1) / rho1},
            "initial_velocity": v0,
        },
        "2": {"E": e_err(e_true[1], e_value[1]), "initial_velocity": v0},
    }
    intervals = {"obj1": {"E": e_interval(e_value[0])}, "obj2": {"E": e_interval(e_value[1])}}
    family2 = "plasticine"
    if sand is not None:
        family2 = "sand"
        errors["2"]["friction_angle"] = {
            "value": sand[1],
            "true": sand[0],
            "abs_error_deg": abs(sand[1] - sand[0]),
        }
        intervals["obj2"]["friction_angle"] = _interval(None, None, "unconstrained")
    else:
        errors["2"]["yield_stress"] = e_err(2000.0, 2400.0)
    identified = {
        "objects": {
            "1": {"family": "elastic", "params": {"E": e_value[0], "friction": 0.3}},
            "2": {"family": family2, "params": {"E": e_value[1]}, "initial_velocity": [1, 0, 0]},
        },
        "ground_friction": 0.45,
        "intervals": intervals,
    }
    block = {"cd_mm2": 1.0, "emd_mm": 2.0}
    return {
        "observed": block,
        "future": {"cd_mm2": future_cd, "emd_mm": 5.0},
        "params": identified,
        "param_error": errors,
        "peak_memory_gb": 1.5,
    }


def _rows(bench):
    data = {"generator": "mosiv-genesis (Genesis 1.4.5, MPM, cpu)", "ranges": "wide"}
    # scene A: density gauge 0.8 (true first density 800); the identified E values are exact in
    # the gauge: value * 0.8 = true, so the gauge-free error is 0 and the raw one 25 %
    a = _metrics(
        e_true=[8e4, 4e5], e_value=[1e5, 5e5], rho1=800.0, kind="two-sided", future_cd=100.0
    )
    # scene B: no gauge (true first density 1000); E off by 40 % and 100 %, intervals one-sided
    b = _metrics(
        e_true=[1e5, 1e5],
        e_value=[1.4e5, 2e5],
        rho1=1000.0,
        kind="lower-bound",
        future_cd=900.0,
        sand=(30.0, 33.0),
    )
    return [
        bench.scene_row("A", a, time_s=100.0, data={**data, "seed": 0}, device="X", code="c1"),
        bench.scene_row("B", b, time_s=700.0, data={**data, "seed": 1}, device="X", code="c1"),
        {"scene": "C", "error": "SimulationDiverged: boom", "data": {**data, "seed": 2}},
    ]


def test_object_entries_use_the_gauge_for_errors_and_coverage():
    bench = _bench()
    rows = _rows(bench)
    e1 = rows[0]["objects"]["1"]["params"]["E"]
    assert e1["raw"] == pytest.approx(25.0)
    assert e1["gauge_free"] == pytest.approx(0.0, abs=1e-9)
    assert e1["error"] == e1["gauge_free"]
    # the interval 0.9e5..1.1e5 of the identified value misses the raw truth 8e4 but holds it
    # after the gauge (0.72e5..0.88e5)
    assert e1["kind"] == "two-sided" and e1["covered"] is True
    # the gauge object's density: no interval, nothing to cover
    assert rows[0]["objects"]["1"]["params"]["rho"]["covered"] is None
    angle = rows[1]["objects"]["2"]["params"]["friction_angle"]
    assert angle["deg"] == pytest.approx(3.0) and angle["kind"] == "unconstrained"
    assert rows[1]["objects"]["2"]["params"]["E"]["covered"] is True  # lower bound 1e5 <= 1e5


def test_summary_medians_shares_coverage_and_targets():
    bench = _bench()
    table = bench.make_table(_rows(bench))
    s = table["summary"]
    assert [r["scene"] for r in table["rows"]] == ["A", "B", "C"]
    assert s["scenes"] == 3 and s["failed"] == ["C"]
    # two-sided E intervals only in scene A, both exact in the gauge
    assert s["E_finite"]["n"] == 2 and s["E_finite"]["value"] == pytest.approx(0.0, abs=1e-9)
    assert s["E_finite"]["met"] is True
    # E errors 0, 0, 40, 100 %: three of four within 50 %
    assert s["E_within_50"]["value"] == pytest.approx(75.0) and s["E_within_50"]["met"] is False
    # two of four E intervals one-sided
    assert s["E_not_finite"]["value"] == pytest.approx(50.0)
    assert s["E_not_finite"]["one_sided"] == 2 and s["E_not_finite"]["met"] is False
    # the yield stress of scene A: 2400 in the 0.8 gauge is 1920 against 2000: 4 %
    assert s["yield_stress"]["value"] == pytest.approx(4.0) and s["yield_stress"]["met"] is True
    assert s["friction_angle"]["value"] == pytest.approx(3.0) and s["friction_angle"]["met"]
    assert s["viscosity"]["n"] == 0 and s["viscosity"]["met"] is None
    assert s["initial_velocity"]["value"] == pytest.approx(1.0)
    # intervals claiming something: 4 E intervals, all holding the truth; the friction angle's
    # unconstrained one is counted apart
    assert s["coverage"]["n"] == 4 and s["coverage"]["value"] == pytest.approx(100.0)
    assert s["coverage"]["unconstrained"] == 1
    assert s["future_cd"]["value"] == pytest.approx(statistics.fmean([100.0, 900.0]))
    assert s["future_cd"]["met"] is False
    assert s["time"]["value"] == pytest.approx(700.0) and s["time"]["met"] is False
    text = bench.markdown(table)
    assert "| A | 1 elastic | 0 / 25 [2s in] |" in text
    assert "failed: SimulationDiverged: boom" in text
    assert "| mean future CD | 2 | 500 mm^2 | <= 450 mm^2 | not met |" in text


def test_a_missed_interval_lowers_the_coverage():
    bench = _bench()
    m = _metrics(e_true=[1e5, 1e5], e_value=[2e5, 1e5], rho1=1000.0, kind="two-sided", future_cd=1)
    row = bench.scene_row("A", m, time_s=1.0, data={}, device="CPU", code="c")
    s = bench.summarise([row])
    assert row["objects"]["1"]["params"]["E"]["covered"] is False  # 1.8e5..2.2e5 misses 1e5
    # every identified value stays in the row, those without a truth too (the ground's and a
    # contact friction), so the run can be rolled out again from the row alone
    assert row["identified"] == {
        "objects": {
            "1": {"family": "elastic", "params": {"E": 2e5, "friction": 0.3}},
            "2": {"family": "plasticine", "params": {"E": 1e5}, "initial_velocity": [1, 0, 0]},
        },
        "ground_friction": 0.45,
    }
    assert s["coverage"]["count"] == 1 and s["coverage"]["n"] == 2  # the two E intervals
    assert "ground_friction_start" not in row["identified"]  # no history, no start


def test_a_row_keeps_where_the_ground_friction_started():
    """The start is the velocity phase's value: that phase moves only the initial velocities;
    the contact modes' brief fits and the parameter phase after it move the coefficient."""
    bench = _bench()
    m = _metrics(e_true=[1e5, 1e5], e_value=[1e5, 1e5], rho1=1000.0, kind="two-sided", future_cd=1)
    history = [
        {"phase": "velocity", "iteration": 0, "values": {"ground_friction": 0.094}},
        {"phase": "velocity", "iteration": 1, "values": {"ground_friction": 0.094}},
        {"phase": "contact_fit", "values": {"ground_friction": 0.2}},
        {"phase": "params", "iteration": 0, "values": {"ground_friction": 0.31}},
    ]
    row = bench.scene_row("A", m, time_s=1.0, data={}, device="CPU", code="c", history=history)
    assert row["identified"]["ground_friction_start"] == pytest.approx(0.094)
    assert row["identified"]["ground_friction"] == pytest.approx(0.45)  # identified.json's
    # a history without a velocity record (a run that skipped the phase) says nothing
    later = bench.scene_row(
        "A", m, time_s=1.0, data={}, device="CPU", code="c", history=history[2:]
    )
    assert "ground_friction_start" not in later["identified"]
    # the scene table ends in the identified ground friction and its start, '-' where a row
    # has none
    scene_lines = [line for line in bench.markdown(bench.make_table([row])).splitlines()
                   if line.startswith("| A | ")]  # fmt: skip
    assert scene_lines[-1].endswith(" | 0.45 (0.094) |"), scene_lines
    later_lines = [line for line in bench.markdown(bench.make_table([later])).splitlines()
                   if line.startswith("| A | ")]  # fmt: skip
    assert later_lines[-1].endswith(" | 0.45 |"), later_lines
    old_row = {k: v for k, v in row.items() if k != "identified"}
    old_lines = [line for line in bench.markdown(bench.make_table([old_row])).splitlines()
                 if line.startswith("| A | ")]  # fmt: skip
    assert old_lines[-1].endswith(" | - |"), old_lines


def _tagged(intervals: dict, method: str) -> dict:
    """``intervals`` (obj -> name -> interval) with each interval naming its ``method``."""
    return {o: {n: {**i, "method": method} for n, i in p.items()} for o, p in intervals.items()}


def test_contact_interval_method_and_laplace_intervals_of_the_same_runs():
    bench = _bench()
    # scene A: identify.contact auto chose single_field; sandwich intervals, and the history's
    # interval record keeps the Laplace intervals of the same probes. Density gauge 0.8: E of
    # object 1 is exact in the gauge (1.25e5 * 0.8 = 1e5), object 2's is 2e5 * 0.8 = 1.6e5
    a = _metrics(
        e_true=[1e5, 1e5], e_value=[1.25e5, 2e5], rho1=800.0, kind="two-sided", future_cd=1.0
    )
    sandwich = {
        "obj1": {"E": _interval(1.0e5, 1.5e5, "two-sided")},  # 0.8e5..1.2e5 in the gauge: in
        "obj2": {
            "E": _interval(1.0e5, None, "lower-bound"),  # >= 0.8e5: in
            "yield_stress": _interval(None, None, "unconstrained"),
        },
    }
    laplace = {
        "obj1": {"E": _interval(1.2e5, 1.3e5, "two-sided")},  # 0.96e5..1.04e5: in (raw: out)
        "obj2": {
            "E": _interval(1.9e5, 2.1e5, "two-sided"),  # 1.52e5..1.68e5: out
            "yield_stress": _interval(2400.0, 2450.0, "two-sided"),  # 1920..1960 vs 2000: out
        },
    }
    a["params"]["intervals"] = _tagged(sandwich, "sandwich")
    a["params"]["contact"] = {
        "choice": "auto",
        "mode": "single_field",
        "recipe_mode": "multi_field",
        "losses": {"multi_field": 0.04, "single_field": 0.01},
        "margin": 0.05,
        "frames": 9,
    }
    history_a = [
        {"phase": "param", "iteration": 0, "loss": 1.0},
        {
            "phase": "intervals",
            "method": "sandwich",
            "intervals": _tagged(sandwich, "sandwich"),
            "laplace": _tagged(laplace, "laplace"),
        },
    ]
    # scene B: the recipe's fixed contact and Laplace intervals (the history's record has no
    # separate Laplace ones: its intervals are Laplace's); E of object 2 is missed
    b = _metrics(
        e_true=[1e5, 1e5], e_value=[1e5, 2e5], rho1=1000.0, kind="two-sided", future_cd=1.0
    )
    b["params"]["intervals"] = _tagged(b["params"]["intervals"], "laplace")
    b["params"]["contact"] = {"choice": "fixed", "mode": "single_field"}
    history_b = [{"phase": "intervals", "method": "laplace", "intervals": b["params"]["intervals"]}]
    # scene C: a simulator without contact modes, no history
    c = _metrics(
        e_true=[1e5, 1e5], e_value=[1e5, 1e5], rho1=1000.0, kind="two-sided", future_cd=1.0
    )
    kw = {"time_s": 1.0, "data": {}, "device": "X", "code": "c"}
    rows = [
        bench.scene_row("A", a, history=history_a, **kw),
        bench.scene_row("B", b, history=history_b, **kw),
        bench.scene_row("C", c, **kw),
    ]
    assert rows[0]["contact"] == {k: v for k, v in a["params"]["contact"].items() if k != "frames"}
    assert rows[2]["contact"] is None
    e1 = rows[0]["objects"]["1"]["params"]["E"]
    assert e1["method"] == "sandwich" and e1["covered"] is True
    assert e1["laplace"] == {"kind": "two-sided", "covered": True}
    yield2 = rows[0]["objects"]["2"]["params"]["yield_stress"]
    assert yield2["kind"] == "unconstrained" and yield2["laplace"]["covered"] is False
    assert rows[1]["objects"]["2"]["params"]["E"]["laplace"] == {
        "kind": "two-sided",
        "covered": False,
    }
    assert rows[2]["objects"]["1"]["params"]["E"]["laplace"] is None
    table = bench.make_table(rows)
    s = table["summary"]
    # the runs' own intervals: A's two E in (its yield stress unconstrained), B's E 1 in and
    # E 2 out, C's two in (its intervals name no method)
    assert (s["coverage"]["count"], s["coverage"]["n"], s["coverage"]["unconstrained"]) == (
        5,
        6,
        1,
    )
    assert s["coverage"]["methods"] == {"sandwich": 3, "laplace": 2, "not recorded": 2}
    # the Laplace intervals of A and B (C's history holds none): A's E 1, B's E 1 in; A's E 2,
    # A's yield stress, B's E 2 out
    laplace_stat = s["coverage_laplace"]
    assert (laplace_stat["count"], laplace_stat["n"], laplace_stat["unconstrained"]) == (2, 5, 0)
    assert laplace_stat["value"] == pytest.approx(40.0) and laplace_stat["met"] is False
    assert s["contact"] == {"single_field (auto)": 1, "single_field (recipe)": 1, "-": 1}
    text = bench.markdown(table)
    assert "| A | 1 elastic | 0 / 25 [sw 2s in; lap 2s in] |" in text
    assert "| A | 2 plasticine | 60 / 100 [sw >= in; lap 2s out] |" in text
    assert "| B | 2 plasticine | 100 / 100 [lap 2s out] |" in text
    assert "| C | 1 elastic | 0 / 0 [2s in] |" in text
    assert "| A | single_field (auto): multi_field 0.04, single_field 0.01 | 1 |" in text
    assert "| B | single_field (recipe) | 1 |" in text and "| C | - | 1 |" in text
    assert (
        "| 95 % Laplace intervals of the same runs holding the truth | 5 | 40 % (2 of 5) "
        "| >= 90 % | not met |"
    ) in text
    assert "interval methods: sandwich 3, laplace 2, not recorded 2" in text


def test_committed_rows_without_contact_or_method_render_as_before():
    """Rows made before rows recorded the contact and the interval method: the recipe's
    multi_field contact, no method, no Laplace line, and the committed summary's numbers."""
    bench = _bench()
    folder = ROOT / "benchmarks" / "data" / "genesis_identify_multi_field"
    committed = json.loads((folder / "table.json").read_text())
    rows = [json.loads(p.read_text()) for p in sorted(folder.glob("scene_*.json"))]
    assert rows and all("contact" not in r for r in rows)
    table = bench.make_table(rows)
    s = table["summary"]
    for key, *_ in bench.TARGETS:
        for field in ("value", "n", "count", "worst", "met"):
            assert s[key].get(field) == committed["summary"][key].get(field), (key, field)
    assert s["coverage_laplace"]["n"] == 0 and s["contact"] == {"multi_field (recipe)": len(rows)}
    judged = s["coverage"]["n"] + s["coverage"]["unconstrained"]
    assert s["coverage"]["methods"] == {"not recorded": judged}
    text = bench.markdown(table)
    assert "| E-S | 1 elastic | 63.3 / 52.8 [free in] |" in text
    assert "| E-S | multi_field (recipe) | 132 |" in text
    assert "Laplace intervals of the same runs" not in text
    assert f"interval methods: not recorded {judged}; contact: multi_field (recipe) 13." in text


def test_results_section_replacement_changes_only_that_section(tmp_path):
    bench = _bench()
    table = bench.make_table(_rows(bench)[:2])
    body = bench.section_text(table, command="python benchmarks/genesis_identify.py", date="D")
    words = " ".join(body.split())  # the prose is wrapped at 100 columns
    assert "2 scenes made by the Genesis engine (genesis-world 1.4.5, cpu backend)" in words
    assert "wide ranges, seeds 0-1" in words and "Machine: X. Date D. Code c1." in words
    original = (ROOT / "docs" / "RESULTS.md").read_text()
    once = bench.replace_section(original, body)
    head, _, rest = once.partition(f"## {bench.SECTION}\n")
    assert rest, "the section was not inserted"
    # everything outside the section is the original, in order
    after = rest[rest.index("\n## ") + 1 :]
    assert head + after == original.replace(_section_of(original, bench.SECTION), "")
    # a second write replaces the section instead of adding one
    other = body.replace("Date D", "Date E")
    twice = bench.replace_section(once, other)
    assert twice.count(f"## {bench.SECTION}") == 1 and "Date E" in twice and "Date D" not in twice
    assert twice.replace(_section_of(twice, bench.SECTION), "") == once.replace(
        _section_of(once, bench.SECTION), ""
    )
    # the last section of a file is replaced up to the end
    last = "# R\n\n## A\n\na\n\n## " + bench.SECTION + "\n\nold\n"
    assert bench.replace_section(last, body) == "# R\n\n## A\n\na\n\n" + body


def _section_of(text: str, title: str) -> str:
    """The ``## title`` section's text (heading to the next level-2 heading), '' if absent."""
    start = text.find(f"## {title}\n")
    if start < 0:
        return ""
    end = text.find("\n## ", start + 1)
    return text[start : end + 1 if end >= 0 else len(text)]


def test_command_line_names_no_machine_paths():
    bench = _bench()
    line = bench.command_line(
        ["--scenes", "/data/x", f"--out={ROOT}/runs/y", "--write-results", str(ROOT / "docs/R.md")]
    )
    assert line == (
        "python benchmarks/genesis_identify.py --scenes SCENES --out=OUT --write-results docs/R.md"
    )


def test_merge_tabulates_the_part_rows(tmp_path):
    """--merge: the rows that --part processes wrote (ordered by scene name), the summary over
    them and the RESULTS section; a scene without a part keeps its earlier row."""
    bench = _bench()
    data = ROOT / "benchmarks" / "data" / "genesis_identify"
    scenes, out = tmp_path / "scenes", tmp_path / "out"
    (out / "parts").mkdir(parents=True)
    scenes.mkdir()
    for name in ("P-P", "E-E", "S-S"):
        (scenes / name).symlink_to(TINY, target_is_directory=True)
    (scenes / "suite.json").write_text(json.dumps({"scenes": {"S-S": {}, "E-E": {}, "P-P": {}}}))
    for name in ("E-E", "P-P"):
        row = (data / f"scene_{name}.json").read_text()
        (out / "parts" / f"{name}.json").write_text(row)
    earlier = json.loads((data / "scene_S-S.json").read_text())
    (out / "table.json").write_text(json.dumps({"rows": [earlier]}))
    results = tmp_path / "RESULTS.md"
    results.write_text("# Results\n")
    argv = ["--scenes", str(scenes), "--out", str(out), "--merge", "--write-results", str(results)]
    assert bench.main(argv) == 0
    table = json.loads((out / "table.json").read_text())
    assert [r["scene"] for r in table["rows"]] == ["E-E", "P-P", "S-S"]
    assert table["rows"][2] == earlier
    expected = bench.make_table(table["rows"])["summary"]
    assert table["summary"] == json.loads(json.dumps(expected))
    assert f"## {bench.SECTION}" in results.read_text()
    with pytest.raises(SystemExit):
        bench.main(["--scenes", str(scenes), "--out", str(out), "--merge", "--part"])
    for part in (out / "parts").glob("*.json"):
        part.unlink()
    (out / "table.json").unlink()
    with pytest.raises(SystemExit, match="no rows"):
        bench.main(["--scenes", str(scenes), "--out", str(out), "--merge"])


def test_end_to_end_on_the_tiny_genesis_scene(tmp_path, capfd):
    """The whole command on CPU: a row per scene, table files, the RESULTS section, and the
    pipeline's progress on stderr."""
    bench = _bench()
    scenes = tmp_path / "scenes"
    scenes.mkdir()
    (scenes / "E-S").symlink_to(TINY, target_is_directory=True)
    results = tmp_path / "RESULTS.md"
    results.write_text("# Results\n\n## From video\n\nkept\n")
    sets = [
        "simulator.device=cpu",
        "simulator.grid=16",
        "simulator.substeps=20",
        "identify.velocity_iterations=2",
        "identify.param_iterations=2",
        "identify.global_candidates=2",
        "identify.global_polish=2",
        "identify.contact_iterations=1",  # the recipe's contact choice, briefly
        "losses.chamfer.max_points=256",
        "evaluate.emd_samples=128",
        "evaluate.render_videos=false",
    ]
    argv = ["--scenes", str(scenes), "--out", str(tmp_path / "out")]
    argv += [x for s in sets for x in ("--set", s)] + ["--write-results", str(results)]
    assert bench.main(argv) == 0
    # the global stage's candidates are logged at INFO, which the benchmark shows
    assert "global candidate 2/2" in capfd.readouterr().err
    table = json.loads((tmp_path / "out" / "table.json").read_text())
    (row,) = table["rows"]
    assert "error" not in row, row.get("error")
    truth = json.loads((TINY / "gt" / "params.json").read_text())
    families = [o["material"] for o in truth["objects"]]
    assert [o["family"] for o in row["objects"].values()] == families
    sand = row["objects"]["2"]["params"]
    assert {"E", "nu", "rho", "friction_angle", "initial_velocity"} <= set(sand)
    assert sand["E"]["kind"] in bench.KINDS and sand["E"]["gauge_free"] is not None
    assert row["device"] == "CPU" and row["data"]["seed"] == truth["generator_params"]["seed"]
    assert table["summary"]["initial_velocity"]["n"] == 2
    # the recipe chooses the contact and the elastic body's stress from the data and asks for
    # sandwich intervals, whose history keeps the Laplace intervals of the same probes
    assert row["contact"]["choice"] == "auto"
    modes = {"multi_field", "single_field"}
    assert set(row["contact"]["losses"]) == modes | {f"{m} + alternatives" for m in modes}
    assert row["contact"]["mode"] in modes and row["contact"]["laws"] in ("recipe", "alternatives")
    assert sand["E"]["method"] == "sandwich" and sand["E"]["laplace"]["kind"] in bench.KINDS
    laplace = table["summary"]["coverage_laplace"]
    assert laplace["n"] + laplace["unconstrained"] == sum(
        table["summary"]["coverage"]["methods"].values()
    )
    text = results.read_text()
    assert f"## {bench.SECTION}" in text and text.endswith("## From video\n\nkept\n")
    assert "--scenes SCENES --out OUT" in text and str(tmp_path) not in text
    assert f"| E-S | {row['contact']['mode']} (auto): multi_field " in text


def test_a_row_names_the_law_set_its_variant_used():
    """With identify.law_choice the row keeps the chosen law set, and the label says it."""
    bench = _bench()
    metrics = _metrics(
        e_true=[1e5, 1e5], e_value=[1e5, 1e5], rho1=1000.0, kind="two-sided", future_cd=1.0
    )
    metrics["params"]["contact"] = {
        "choice": "auto",
        "mode": "single_field",
        "recipe_mode": "multi_field",
        "losses": {"multi_field": 0.2, "single_field + alternatives": 0.1},
        "margin": 0.05,
        "laws": "alternatives",
        "law_map": {"1": "elastic_corotated"},
    }
    row = bench.scene_row("A", metrics, time_s=1.0, data={}, device="CPU", code="x")
    assert row["contact"]["laws"] == "alternatives" and "law_map" not in row["contact"]
    label = sys.modules["genesis_identify_table"].contact_label
    assert label(row) == "single_field + alternatives (auto)"
    row["contact"]["laws"] = "recipe"
    assert label(row) == "single_field (auto)"


def test_merge_command_names_the_part_runs_too():
    """The results file says how the rows were made (the --part runs) and then the merge."""
    line = _bench().merge_command_text(
        ["--scenes", "/data/x", "--out", "/tmp/o", "--merge", "--write-results", "R.md"]
        + ["--set", "simulator.grid=48"]
    )
    assert line == (
        "python benchmarks/genesis_identify.py --scenes SCENES --out OUT --only SCENE --part --set"
        " simulator.grid=48` for each scene, then `python benchmarks/genesis_identify.py --scenes"
        " SCENES --out OUT --merge --write-results R.md --set simulator.grid=48"
    )


def test_job_file_lists_one_part_run_per_scene_for_the_device_queue(tmp_path):
    """--job-file: one device_queue.py job per scene (in suite order), each the scene's --part
    run with the given overrides, absolute data paths (jobs run in snapshots of the checkout)
    and the recipe relative to the checkout; nothing runs and OUT is not made."""
    bench = _bench()
    sys.path.insert(0, str(ROOT / "benchmarks"))
    try:
        import device_queue
    finally:
        sys.path.remove(str(ROOT / "benchmarks"))
    scenes, out, jobs = tmp_path / "scenes", tmp_path / "out", tmp_path / "jobs.txt"
    scenes.mkdir()
    for name in ("P-P", "E-E"):
        (scenes / name).symlink_to(TINY, target_is_directory=True)
    (scenes / "suite.json").write_text(json.dumps({"scenes": {"P-P": {}, "E-E": {}}}))
    argv = ["--scenes", str(scenes), "--out", str(out), "--set", "identify.holdout_frames=3"]
    assert bench.main([*argv, "--job-file", str(jobs)]) == 0
    assert not out.exists()
    listed = device_queue.read_jobs(jobs)
    assert [job.name for job in listed] == ["gid_P-P", "gid_E-E"]
    for job, name in zip(listed, ("P-P", "E-E")):
        words = job.command.split()
        assert words[:2] == ["python3", "benchmarks/genesis_identify.py"]
        assert words[words.index("--only") + 1] == name and "--part" in words
        assert words[words.index("--out") + 1] == str(out.resolve())
        assert words[words.index("--scenes") + 1] == str(scenes.resolve())
        assert words[words.index("--recipe") + 1] == "recipes/genesis_oracle.yaml"
        assert words[words.index("--set") + 1] == "identify.holdout_frames=3"
    with pytest.raises(SystemExit):
        bench.main([*argv, "--job-file", str(jobs), "--merge"])


def test_a_row_keeps_the_day_its_run_ended_and_the_section_names_the_days():
    bench = _bench()
    m = _metrics(e_true=[1e5, 1e5], e_value=[1e5, 1e5], rho1=1000.0, kind="two-sided", future_cd=1)
    row = bench.scene_row("A", m, time_s=1.0, data={}, device="CPU", code="c", date="2026-11-29")
    assert row["date"] == "2026-11-29"
    today = bench.scene_row("B", m, time_s=1.0, data={}, device="CPU", code="c")["date"]
    assert today == datetime.date.today().isoformat()
    table = load_script(ROOT / "benchmarks" / "genesis_identify_table.py")
    assert table.run_dates([row]) == "2026-11-29"
    later = {**row, "date": "2026-12-01"}
    assert table.run_dates([later, row, row]) == "2026-11-29 to 2026-12-01"
    # a row without a date counts as today's, and so does no row at all
    assert table.run_dates([{k: v for k, v in row.items() if k != "date"}]) == today
    assert table.run_dates([]) == today


def test_the_section_dates_the_runs_and_skips_failed_rows(tmp_path):
    bench = _bench()
    m = _metrics(e_true=[1e5, 1e5], e_value=[1e5, 1e5], rho1=1000.0, kind="two-sided", future_cd=1)
    rows = [
        bench.scene_row("A", m, time_s=1.0, data={}, device="CPU", code="c", date="2026-11-29"),
        bench.scene_row("B", m, time_s=1.0, data={}, device="CPU", code="c", date="2026-11-30"),
        {"scene": "C", "error": "SimulationDiverged: boom", "data": {}},
    ]
    notes = tmp_path / "RESULTS.md"
    bench.write_results(notes, bench.make_table(rows), command="cmd")
    assert "Date 2026-11-29 to 2026-11-30." in " ".join(notes.read_text().split())
    # a table whose every scene failed still gets a section, dated today
    bench.write_results(notes, bench.make_table(rows[2:]), command="cmd")
    today = datetime.date.today().isoformat()
    assert f"Date {today}." in " ".join(notes.read_text().split())
