"""benchmarks/noise_suite.py's Genesis mode (benchmarks/genesis_noise.py): the per-setting
summary from rows, the RESULTS.md section, the flags of each mode, and one process per
(scene, noise setting) with the merge on the committed tiny Genesis scene."""

from __future__ import annotations

import importlib
import json
import statistics
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
BENCHMARKS = ROOT / "benchmarks"
TINY = ROOT / "plugins" / "mosiv-genesis" / "tests" / "data" / "tiny_scene"
#: the smallest identification that runs every stage on CPU (the recipe's contact choice too)
SMALL = [
    "simulator.device=cpu",
    "simulator.grid=16",
    "simulator.substeps=20",
    "identify.velocity_iterations=0",
    "identify.param_iterations=1",
    "identify.global_candidates=0",
    "identify.contact_iterations=1",
    "identify.law_choice=fixed",
    "identify.intervals=false",
    "losses.chamfer.max_points=256",
    "evaluate.emd_samples=128",
    "evaluate.render_videos=false",
]


@pytest.fixture
def mods(monkeypatch):
    """(noise_suite, genesis_noise), with benchmarks/ on the path as when run from there (the
    Genesis mode is imported when it is used)."""
    monkeypatch.syspath_prepend(str(BENCHMARKS))
    return importlib.import_module("noise_suite"), importlib.import_module("genesis_noise")


def _sets(sets: list[str]) -> list[str]:
    return [x for s in sets for x in ("--set", s)]


def _param(error: float, covered: bool | None = None) -> dict:
    kind = None if covered is None else "two-sided"
    return {"error": error, "kind": kind, "covered": covered, "method": None, "laplace": None}


def _row(scene, kind, alpha, *, e, other, v0, observed, future, time_s=10.0):
    """A genesis_identify row of an elastic (E ``e``) and a plasticine object (E ``other``, a
    yield stress off 10 %), both with v0 errors ``v0``; the elastic E interval holds the truth
    when its error is under 50 %."""
    name = "reference" if kind == "none" else f"{kind}-{alpha:g}"
    objects = {
        "1": {"family": "elastic", "params": {"E": _param(e, e < 50), "initial_velocity": _param(v0[0])}},
        "2": {
            "family": "plasticine",
            "params": {
                "E": _param(other),
                "yield_stress": _param(10.0),
                "initial_velocity": _param(v0[1]),
            },
        },
    }  # fmt: skip
    return {
        "scene": scene,
        "kind": kind,
        "alpha": alpha,
        "setting": name,
        "contact": {"choice": "auto", "mode": "single_field"},
        "objects": objects,
        "observed_cd_mm2": observed,
        "observed_emd_mm": 1.0,
        "future_cd_mm2": future,
        "future_emd_mm": 2.0,
        "time_s": time_s,
        "device": "GPU X",
        "code": "abc1234",
        "data": {"generator": "mosiv-genesis (Genesis 1.4.5, MPM, cuda)", "ranges": "wide"},
    }


def _rows() -> list[dict]:
    return [
        _row("A", "none", 0.0, e=10, other=20, v0=(1, 2), observed=4, future=100),
        _row("B", "none", 0.0, e=30, other=40, v0=(3, 4), observed=6, future=400),
        _row("A", "iid", 0.02, e=60, other=20, v0=(1, 5), observed=8, future=300, time_s=30),
        _row("B", "iid", 0.02, e=20, other=80, v0=(2, 2), observed=12, future=200),
        {"scene": "B", "kind": "shared", "alpha": 0.02, "setting": "shared-0.02", "error": "boom"},
        _row("A", "shared", 0.02, e=90, other=90, v0=(9, 9), observed=50, future=1000),
    ]


def test_each_setting_summarised_over_its_scenes(mods):
    _, gn = mods
    table = gn.make_table(_rows(), {"recipe": "recipes/genesis_oracle.yaml", "overrides": []})
    assert [s["setting"] for s in table["settings"]] == ["reference", "iid-0.02", "shared-0.02"]
    reference, iid, shared = table["settings"]
    assert iid["scenes"] == 2 and iid["failed"] == []
    assert iid["observed_cd_mm2"] == pytest.approx(10.0)
    assert iid["future_cd_mm2"] == pytest.approx(250.0)
    # each scene against its own reference: 300 / 100 and 200 / 400
    assert iid["future_cd_ratio"]["value"] == pytest.approx(statistics.median([3.0, 0.5]))
    assert reference["future_cd_ratio"]["value"] == pytest.approx(1.0)
    errors = iid["errors"]
    assert errors["E_elastic"]["value"] == pytest.approx(40.0)  # median of 60 and 20
    assert errors["E_other"]["value"] == pytest.approx(50.0)  # the plasticine's 20 and 80
    assert errors["yield_stress"]["n"] == 2 and errors["friction_angle"]["n"] == 0
    assert errors["initial_velocity"]["value"] == pytest.approx(statistics.median([1, 5, 2, 2]))
    # the elastic E intervals: 60 % misses, 20 % holds
    assert (iid["coverage"]["count"], iid["coverage"]["n"]) == (1, 2)
    assert iid["contact"] == {"single_field (auto)": 2} and iid["time_s"] == 30
    assert shared["scenes"] == 1 and shared["failed"] == ["B"]
    assert shared["future_cd_ratio"]["value"] == pytest.approx(10.0)
    text = gn.markdown(table)
    assert "| iid | 0.02 | 2 | 10 | 250 | 1.75 | 40 | 50 | 10 | 2 | 50 % (1 of 2) |" in text
    assert (
        "| A | iid | 0.02 | single_field (auto) | 8 | 300 | 3 | 60 / 20 | 10 | 1 / 5 | 30 |" in text
    )
    assert "| B | shared | 0.02 | failed: boom |" in text and "Failed runs: B shared-0.02." in text
    assert "friction angle deg" not in text and "viscosity %" not in text  # no object has one
    elastic = [r["E_pct"] for r in gn.plot_rows(table)]
    assert elastic == [[10, 30], [60, 20], [90]]


def test_results_section_goes_after_the_own_synth_noise_section(mods, tmp_path):
    _, gn = mods
    table = gn.make_table(_rows(), {"recipe": "recipes/genesis_oracle.yaml", "overrides": ["a=1"]})
    png = tmp_path / "noise.png"
    png.write_bytes(b"png")
    results = tmp_path / "docs" / "RESULTS.md"
    results.parent.mkdir()
    results.write_text(
        "# R\n\n## Sensitivity to reconstruction noise\n\nown\n\n## Ablations\n\nx\n"
    )
    command = "python benchmarks/noise_suite.py --scenes SCENES --out OUT"
    gn.write_results(results, table, command=command, png=png)
    once = results.read_text()
    own, mine = (
        once.index("## Sensitivity to reconstruction noise\n"),
        once.index(f"## {gn.SECTION}"),
    )
    assert own < mine < once.index("## Ablations") and once.endswith("## Ablations\n\nx\n")
    section = once[mine : once.index("## Ablations")]
    assert f"`{command}`" in section and "`--set a=1`" in section
    assert "Machine: GPU X." in section and "Code abc1234." in section
    assert "Noise: iid, shared at alpha 0.02." in section
    assert (
        "2 scenes made by the Genesis engine (genesis-world 1.4.5, cuda backend), wide" in section
    )
    assert "![noise on Genesis scenes](img/genesis_noise.png)" in section
    assert (results.parent / "img" / gn.IMAGE).read_bytes() == b"png"
    gn.write_results(results, table, command=command.replace("OUT", "OUT2"), png=png)
    twice = results.read_text()
    assert twice.count(f"## {gn.SECTION}") == 1 and twice.replace("OUT2", "OUT") == once


def test_each_mode_refuses_the_others_flags(mods, tmp_path):
    ns, _ = mods
    for argv in (["--set", "a=1"], ["--part"], ["--only", "E-S"], ["--alpha", "0.1"]):
        with pytest.raises(SystemExit):
            ns.parse_args(argv)
    for argv in (["--scenes", "s", "--out", "o", "a=1"], ["--scenes", "s"], ["--merge"]):
        with pytest.raises(SystemExit):
            ns.parse_args(argv)
    own = ns.parse_args(["--jobs", "2", "scene.source.n_frames=14"])
    assert (own.genesis, own.recipe, own.out, own.threads) == (
        False,
        Path("recipes/paper.yaml"),
        Path("runs/noise_suite"),
        1,
    )
    assert own.overrides == ["scene.source.n_frames=14"] and own.levels == (0.005, 0.02, 0.05)
    # the own-synth runs: the reference first, then each kind at each level
    jobs = ns.jobs_for(recipe=Path("r.yaml"), out=Path("o"), extra=[], threads=1, levels=(0.02,))
    assert [(j["name"], j["overrides"][1:-1]) for j in jobs] == [
        ("reference", []),
        ("iid-0.02", ["reconstructor.noise_iid_rel=0.02"]),
        ("shared-0.02", ["reconstructor.noise_shared_rel=0.02"]),
    ]
    scenes = tmp_path / "scenes"
    scenes.mkdir()
    (scenes / "E-S").symlink_to(TINY, target_is_directory=True)
    base = ["--scenes", str(scenes), "--out", str(tmp_path / "out"), "--only", "E-S", "--part"]
    for noise in (["--noise", "none", "--alpha", "0.02"], ["--noise", "iid"], []):
        with pytest.raises(SystemExit, match="--noise"):
            ns.main([*base, *noise])
    # another study's folder (genesis_resolution's record) is refused before anything runs
    other = tmp_path / "resolution"
    other.mkdir()
    (other / "study.json").write_text(json.dumps({"format": "mosiv-genesis-resolution/1"}))
    with pytest.raises(SystemExit, match="not a mosiv-genesis-noise/1 record"):
        ns.main([*base[:2], "--out", str(other), "--only", "E-S", "--noise", "none", "--part"])


def test_tiny_genesis_scene_one_process_per_setting_then_merge(mods, tmp_path):
    """A part run in this process merges alone; the suite (one process per scene and setting,
    one level of each kind) resumes that run, adds the others, writes the tables, the plot and
    the section; the merge alone rebuilds the same table."""
    ns, gn = mods
    scenes = tmp_path / "scenes"
    scenes.mkdir()
    (scenes / "E-S").symlink_to(TINY, target_is_directory=True)
    out = tmp_path / "out"
    base = ["--scenes", str(scenes), "--out", str(out), *_sets(SMALL)]
    assert ns.main([*base, "--only", "E-S", "--noise", "iid", "--alpha", "0.02", "--part"]) == 0
    part = json.loads((out / "parts" / "E-S__iid-0.02.json").read_text())
    assert "error" not in part, part.get("error")
    assert ns.main(["--out", str(out), "--merge"]) == 0
    alone = json.loads((out / "table.json").read_text())
    assert [s["setting"] for s in alone["settings"]] == ["iid-0.02"]
    assert alone["settings"][0]["future_cd_ratio"]["value"] is None  # no reference yet
    results = tmp_path / "RESULTS.md"
    results.write_text("# Results\n\n## Sensitivity to reconstruction noise\n\na\n\n## Ablations\n")
    assert ns.main([*base, "--levels", "0.02", "--write-results", str(results)]) == 0
    table = json.loads((out / "table.json").read_text())
    rows = {r["setting"]: r for r in table["rows"]}
    assert set(rows) == {"reference", "iid-0.02", "shared-0.02"}
    truth = json.loads((TINY / "gt" / "params.json").read_text())
    for row in rows.values():
        assert "error" not in row, row.get("error")
        assert row["scene"] == "E-S" and row["device"] == "CPU" and row["time_s"] > 0
        assert row["data"]["seed"] == truth["generator_params"]["seed"]
        assert row["contact"]["choice"] == "auto"  # the recipe's contact choice ran
        assert [o["family"] for o in row["objects"].values()] == ["elastic", "sand"]
        assert row["observed_cd_mm2"] > 0 and row["future_cd_mm2"] > 0
    assert rows["iid-0.02"]["time_s"] == part["time_s"]  # resumed, not identified again
    assert rows["shared-0.02"]["noise_overrides"] == ["reconstructor.noise_shared_rel=0.02"]
    # the noise reached the points identification fitted: observed CD above the reference's
    for name in ("iid-0.02", "shared-0.02"):
        assert rows[name]["observed_cd_mm2"] > rows["reference"]["observed_cd_mm2"]
    settings = {s["setting"]: s for s in table["settings"]}
    assert settings["reference"]["future_cd_ratio"]["value"] == pytest.approx(1.0)
    ratio = rows["shared-0.02"]["future_cd_mm2"] / rows["reference"]["future_cd_mm2"]
    assert settings["shared-0.02"]["future_cd_ratio"]["value"] == pytest.approx(ratio)
    assert (out / "noise.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert (out / "table.md").read_text() == gn.markdown(table)
    text = results.read_text()
    assert text.index("noise\n\na\n") < text.index(f"## {gn.SECTION}") < text.index("## Ablat")
    words = " ".join(text.split())  # the command is wrapped in the section
    assert "--scenes SCENES --out OUT --set" in words and "--levels 0.02 --write-results" in words
    assert str(tmp_path) not in text
    assert (tmp_path / "img" / gn.IMAGE).is_file()
    for name in ("table.json", "table.md", "noise.png"):
        (out / name).unlink()
    assert ns.main(["--out", str(out), "--merge"]) == 0
    assert json.loads((out / "table.json").read_text()) == table
