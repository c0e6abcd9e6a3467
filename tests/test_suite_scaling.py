"""benchmarks/suite_scaling.py: throughput and efficiency, the agreement test against the
run-to-run spread, and the whole command on CPU worker slots through a local Ray."""

from __future__ import annotations

import json
import random
from pathlib import Path

import pytest

from mosiv_framework.testing.scripts import load_script

ROOT = Path(__file__).resolve().parents[1]
BENCH = ROOT / "benchmarks"
TINY = ROOT / "plugins" / "mosiv-genesis" / "tests" / "data" / "tiny_scene"


def _load(name: str):
    return load_script(BENCH / f"{name}.py")


def _row(future_cd: float, e_values: list[float]) -> dict:
    """A genesis_identify row with a future and observed CD and one E per object (and an
    initial velocity, a vector, which is not compared)."""
    objects = {
        str(i + 1): {"params": {"E": {"value": e}, "initial_velocity": {"value": [1.0, 0, 0]}}}
        for i, e in enumerate(e_values)
    }
    return {
        "future_cd_mm2": future_cd,
        "observed_cd_mm2": future_cd / 10,
        "objects": objects,
        "time_s": 60.0,
    }


def _config(count: int, wall: float, rows: dict[tuple[str, int], dict], attempts=None) -> dict:
    attempts = attempts or {}
    tasks = [
        {
            "name": f"{s}.r{r}",
            "scene": s,
            "repeat": r,
            "ok": True,
            "seconds": wall / 2,
            "attempts": attempts.get((s, r), 1),
            "row": row,
        }
        for (s, r), row in rows.items()
    ]
    return {
        "label": f"{count}gpu",
        "count": count,
        "unit": "gpu",
        "slots": 4 * count,
        "wall_s": wall,
        "tasks": tasks,
    }


def _runs(rng: random.Random, noise: float, scenes: int = 12) -> dict:
    """Two repeats of ``scenes`` scenes, every number off its scene's value by up to
    ``noise`` (relative)."""
    out = {}
    for s in range(scenes):
        base_cd, base_e = 100.0 * (s + 1), 1e4 * (s + 1)
        for r in range(2):
            jitter = [1 + rng.uniform(-noise, noise) for _ in range(3)]
            out[(f"S{s}", r)] = _row(base_cd * jitter[0], [base_e * jitter[1], base_e * jitter[2]])
    return out


def test_throughput_speedup_and_efficiency():
    report = _load("suite_scaling_report")
    rows = {("A", 0): _row(1, [1]), ("A", 1): _row(1, [1]), ("B", 0): _row(1, [1])}
    rows[("B", 1)] = _row(1, [1])
    one = _config(1, 400.0, rows)
    four = _config(4, 160.0, rows, attempts={("B", 1): 2})
    (t1, t4) = report.throughput({"1gpu": one, "4gpu": four})
    assert t1["runs_per_hour"] == pytest.approx(4 * 3600 / 400)
    assert t1["speedup"] == pytest.approx(1.0) and t1["efficiency"] == pytest.approx(1.0)
    assert t4["speedup"] == pytest.approx(2.5)
    assert t4["efficiency"] == pytest.approx(2.5 / 4)
    assert t4["retried"] == ["B.r1 (1x)"] and t1["retried"] == []
    table = report.markdown({"throughput": [t1, t4], "agreement": {}})
    assert "| 4 | 16 | 4 | 160 s | 90 | 2.50x | 62% | 60 s |" in table


def test_symmetric_difference_and_compared_quantities():
    report = _load("suite_scaling_report")
    assert report.symmetric_difference(90.0, 110.0) == pytest.approx(0.2)
    assert report.symmetric_difference(0.0, 0.0) == 0.0
    q = report.quantities(_row(50.0, [2e4, 3e4]))
    assert q == {
        "future CD": {"": 50.0},
        "observed CD": {"": 5.0},
        "parameters": {"1.E": 2e4, "2.E": 3e4},
    }
    assert report.quantities({"scene": "X", "error": "diverged"}) == {}


def test_results_within_the_spread_match_and_larger_differences_do_not():
    report = _load("suite_scaling_report")
    rng = random.Random(3)
    # same distribution on 1 and 4 GPUs: the verdict says "match" for nearly every suite (its
    # family-wise false-alarm rate is 5 %)
    matched = 0
    for _ in range(40):
        one = _config(1, 100.0, _runs(rng, 0.02))
        same = _config(4, 30.0, _runs(rng, 0.02))
        verdict = report.agreement({"1gpu": one, "4gpu": same}, "1gpu")
        matched += all(v["match"] for v in verdict.values())
    assert matched >= 36, matched
    # the same scenes, but every number of the 4-GPU runs 30 % off: not run-to-run noise
    shifted = {
        key: _row(
            row["future_cd_mm2"] * 1.3,
            [o["params"]["E"]["value"] * 1.3 for o in row["objects"].values()],
        )
        for key, row in _runs(rng, 0.02).items()
    }
    verdict = report.agreement({"1gpu": one, "4gpu": _config(4, 30.0, shifted)}, "1gpu")
    assert not verdict["future CD"]["match"] and not verdict["parameters"]["match"]
    assert verdict["parameters"]["cross_median"] > 5 * verdict["parameters"]["repeat_median"]
    assert verdict["parameters"]["repeat_n"] == 2 * 12 * 2  # 2 configs x 12 scenes x 2 objects


def test_counts_and_gpu_fractions():
    bench = _load("suite_scaling")
    assert bench.parse_counts("4,1,all", 4, "gpu") == [4, 1]
    with pytest.raises(SystemExit, match="8 GPUs asked for, 4 visible"):
        bench.parse_counts("1,8", 4, "gpu")
    with pytest.raises(SystemExit, match="not a positive count"):
        bench.parse_counts("0,2", 4, "gpu")
    for k in (3, 6, 7):
        assert k * bench.gpu_fraction(k) <= 1.0 and bench.gpu_fraction(k) > 1 / k - 1e-4


def test_an_out_folder_of_something_else_is_refused(tmp_path):
    bench = _load("suite_scaling")
    (tmp_path / "mine.txt").write_text("a user's file")
    with pytest.raises(SystemExit, match="holds no scaling.json"):
        bench.load_state(tmp_path, {"runs": []})
    (tmp_path / "scaling.json").write_text(json.dumps({"settings": {"runs": [["A", 0]]}}))
    with pytest.raises(SystemExit, match="other settings"):
        bench.load_state(tmp_path, {"runs": [["A", 0], ["A", 1]]})


SETS = [
    "simulator.device=cpu",
    "simulator.grid=16",
    "simulator.substeps=20",
    "identify.velocity_iterations=1",
    "identify.param_iterations=1",
    "identify.global_candidates=0",
    "identify.contact=fixed",
    "identify.law_choice=fixed",  # the recipe's 20 brief steps a stress: not this test's subject
    "identify.intervals=false",
    "losses.chamfer.max_points=256",
    "evaluate.emd_samples=128",
    "evaluate.render_videos=false",
]


def test_end_to_end_on_cpu_slots_through_ray(tmp_path, capsys):
    """The whole command, one and two CPU slots, the tiny Genesis scene twice each: both
    configurations finish, the section is written, and a second call measures nothing again."""
    bench = _load("suite_scaling")
    scenes = tmp_path / "scenes"
    scenes.mkdir()
    (scenes / "E-S").symlink_to(TINY, target_is_directory=True)
    notes = tmp_path / "BENCHMARKS.md"
    notes.write_text("# Benchmarks\n\n## Determinism cost\n\nkept\n")
    argv = ["--scenes", str(scenes), "--out", str(tmp_path / "out"), "--unit", "cpu"]
    argv += ["--counts", "1,2", "--runs-per-gpu", "1", "--warmup", "none"]
    argv += [x for s in SETS for x in ("--set", s)] + ["--write-results", str(notes)]
    assert bench.main(argv) == 0
    state = json.loads((tmp_path / "out" / "scaling.json").read_text())
    assert sorted(state["configurations"]) == ["1cpu", "2cpu"]
    for config in state["configurations"].values():
        assert [t["name"] for t in config["tasks"]] == ["E-S.r0", "E-S.r1"]
        assert all(t["ok"] and t["row"]["device"] == "CPU" for t in config["tasks"])
        assert config["wall_s"] > 0
    text = notes.read_text()
    assert text.index("## A suite over several GPUs") < text.index("## Determinism cost")
    assert "| quantity |" in text and "img/suite_scaling.png" in text
    assert (tmp_path / "img" / "suite_scaling.png").stat().st_size > 1000
    capsys.readouterr()
    assert bench.main(argv) == 0  # resumed: both configurations kept
    assert capsys.readouterr().out.count("measured earlier, kept") == 2
    # the section again from scaling.json alone, as on a machine without the devices
    notes.write_text("# Benchmarks\n")
    assert bench.main([*argv, "--report", "--counts", "64"]) == 0
    assert "--unit cpu --counts 1,2" in notes.read_text()  # the measuring command
    with pytest.raises(SystemExit, match="measure first"):
        bench.main(["--scenes", str(scenes), "--out", str(tmp_path / "none"), "--report"])
