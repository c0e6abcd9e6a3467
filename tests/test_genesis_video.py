"""benchmarks/genesis_video.py: table 1 from per-run rows (means, the from-video targets,
runtime and memory), the ablation's differences beside their run-to-run spread, the methods'
recipes, the RESULTS.md section, and one run per process on the committed tiny Genesis scene
for ours and CoupNeRF*, merged into the table."""

from __future__ import annotations

import json
import shlex
from pathlib import Path

import pytest

from mosiv_framework.testing.scripts import load_script

ROOT = Path(__file__).resolve().parents[1]
BENCH = ROOT / "benchmarks"
TINY = ROOT / "plugins" / "mosiv-genesis" / "tests" / "data" / "tiny_scene"

#: every method, shrunk to the 32-pixel, 2-camera, 6-frame scene on CPU
COMMON = [
    "simulator.device=cpu",
    "simulator.grid=16",
    "simulator.substeps=20",
    "identify.velocity_iterations=1",
    "identify.param_iterations=1",
    "identify.horizon_start=2",
    "identify.checkpoint_every=1",
    "evaluate.emd_samples=64",
    "evaluate.render_videos=false",
]
OURS = [
    "reconstructor.device=cpu",
    "reconstructor.hull_resolution=24",
    "reconstructor.max_init_gaussians=200",
    "reconstructor.iterations=15",
    "reconstructor.views_per_step=2",
    "reconstructor.motion_init_iterations=10",
    "reconstructor.max_gaussians=400",
    "reconstructor.tile_size=8",
    "reconstructor.progress=false",
    "lifter.cell_size=0.03",
    "lifter.virtual_views=4",
    "lifter.virtual_resolution=24",
    "losses.chamfer.max_points=128",
    # the recipe's global stage and contact choice, shrunk
    "identify.global_candidates=2",
    "identify.contact_iterations=1",
]
COUPNERF = [
    "reconstructor.resolution=16",
    "reconstructor.iterations=15",
    "reconstructor.rays_per_step=512",
    "reconstructor.step_ratio=1.0",
    "reconstructor.hull_resolution=24",
    "reconstructor.hull_points=200",
    "reconstructor.device=cpu",
    "lifter.spacing=0",
    "lifter.max_particles_per_object=300",
    "losses.nerf-photometric.size=16",
    "losses.nerf-photometric.cameras_per_call=2",
]


def _load(name: str):
    # its dataclasses look their module up by name
    return load_script(BENCH / f"{name}.py", register=True)


def _row(scene, method, *, psnr, cd, time_s=100.0, gb=2.0, seed=0, stage1=None, ssim=0.95):
    block = {"psnr": psnr, "ssim": ssim, "cd_mm2": cd, "emd_mm": 10.0, "psnr_objects": 15.0}
    return {
        "scene": scene,
        "method": method,
        "seed": seed,
        "overrides": ["simulator.substeps=400"],
        "recipe": "recipes/video_paper.yaml",
        "data": {
            "generator": "mosiv-genesis (Genesis 1.4.5, MPM, cpu)",
            "ranges": "wide",
            "seed": {"E-P": 0, "E-S": 2}.get(scene, 9),
            "frames": 30,
            "observed_frames": 15,
            "cameras": 11,
            "resolution": 128,
            "materials": ["elastic", "sand"],
        },  # fmt: skip
        "observed": dict(block),
        "future": {**block, "psnr": psnr - 2.0, "cd_mm2": 2 * cd},
        "peak_memory_gb": gb,
        "memory": "GPU",
        "time_s": time_s,
        "device": "NVIDIA H100",
        "code": "c1",
        "stage1": stage1,
    }


def _stage1(multiples, ious, floor=20.0):
    return {
        "chamfer_floor_mm2": floor,
        "per_object": {
            str(k + 1): {"cd_mm2_max": m * floor, "cd_floor_multiple": m, "iou_min": i}
            for k, (m, i) in enumerate(zip(multiples, ious))
        },
    }


def _table1_rows():
    return [
        _row("E-P", "ours", psnr=33.0, cd=300.0, stage1=_stage1([2.0, 2.5], [0.95, 0.92])),
        _row(
            "E-S",
            "ours",
            psnr=31.0,
            cd=500.0,
            time_s=400.0,
            gb=3.0,
            stage1={**_stage1([1.5, 3.5], [0.91, 0.88]), "skipped_steps": 4},
        ),  # fmt: skip
        _row("E-P", "coupnerf", psnr=26.0, cd=900.0, time_s=900.0, gb=20.0),
        {"scene": "E-S", "method": "coupnerf", "seed": 0, "error": "SimulationDiverged: boom"},
    ]


def test_table_one_means_targets_and_runtime():
    table_mod = _load("genesis_video_table")
    table = table_mod.make_table(_table1_rows())
    s = table["summary"]
    assert s["scenes"] == ["E-P", "E-S"] and s["methods"] == ["coupnerf", "ours"]
    ours = s["means"]["ours"]
    assert ours["observed"]["psnr"]["value"] == pytest.approx(32.0)
    assert ours["future"]["cd_mm2"]["value"] == pytest.approx(800.0)
    # CoupNeRF* failed on E-S: its means are over the one scene it ran
    assert s["means"]["coupnerf"]["observed"]["psnr"] == {"value": 26.0, "n": 1}
    assert s["failed"] == [
        {"scene": "E-S", "method": "coupnerf", "error": "SimulationDiverged: boom"}
    ]
    t = s["targets"]
    assert t["observed_psnr"]["value"] == pytest.approx(32.0) and t["observed_psnr"]["met"]
    assert t["future_psnr"]["value"] == pytest.approx(30.0) and t["future_psnr"]["met"]
    assert t["future_cd"]["value"] == pytest.approx(800.0) and t["future_cd"]["met"]
    # worst object 3.5x the floor (3 of 4 within 3x); worst IoU 0.88 (3 of 4 at 0.9 or more)
    assert t["gaussian_cd"]["value"] == 3.5 and t["gaussian_cd"]["count"] == 3
    assert t["gaussian_cd"]["met"] is False
    assert t["iou"]["value"] == 0.88 and t["iou"]["count"] == 3 and t["iou"]["met"] is False
    assert t["time"]["value"] == 400.0 and t["time"]["met"]
    assert t["memory"]["value"] == 3.0 and t["memory"]["kinds"] == ["GPU"]
    runtime = s["runtime"]
    assert runtime["coupnerf"]["n"] == 1 and runtime["coupnerf"]["max_peak_gb"] == 20.0
    assert runtime["ours"]["median_time_s"] == pytest.approx(250.0)
    text = table_mod.markdown(table)
    assert "| PSNR dB | MOSIV (ours) | 33.00 | 31.00 | 32.00 |" in text
    assert "| PSNR dB | CoupNeRF* | 26.00 | - | 26.00 (n=1) |" in text
    assert "| E-S | 2 | sand | 70 | 20 | 3.5 | 0.880 |" in text
    assert "| mean observed PSNR | 2 | 32.00 dB | >= 31.5 dB | met |" in text
    assert "| mask IoU per object, worst frame | 4 | 0.880 (3 of 4 objects within) |" in text
    assert "- E-S CoupNeRF*: SimulationDiverged: boom" in text
    assert "Stage I steps skipped for a non-finite loss or gradient: E-S 4" in text


def test_development_scenes_are_marked_and_the_targets_judged_on_the_others():
    table_mod = _load("genesis_video_table")
    table = table_mod.make_table(_table1_rows(), development=["E-S"])
    s = table["summary"]
    assert s["development"] == ["E-S"]
    # judged on E-P alone (the test scene); all scenes' value beside it
    assert s["targets"]["observed_psnr"]["value"] == pytest.approx(33.0)
    assert s["targets"]["observed_psnr"]["n"] == 1 and not s["targets"]["observed_psnr"]["missing"]
    assert s["targets"]["gaussian_cd"]["value"] == 2.5 and s["targets"]["gaussian_cd"]["met"]
    assert s["targets_all"]["gaussian_cd"]["value"] == 3.5
    assert s["test_means"]["ours"]["future"]["cd_mm2"]["value"] == pytest.approx(600.0)
    text = table_mod.markdown(table)
    assert "| metric | method | E-P | E-S (dev) | mean | test mean |" in text
    assert "| PSNR dB | MOSIV (ours) | 33.00 | 31.00 | 32.00 | 33.00 |" in text
    assert "| mean observed PSNR | 1 | 33.00 dB | 32.00 dB | >= 31.5 dB | met |" in text
    assert "development scenes E-S" in text


def test_runtime_names_each_stage_median_where_runs_recorded_it():
    table_mod = _load("genesis_video_table")
    rows = _table1_rows()
    stages = ("reconstruct", "lift", "identify", "evaluate")
    rows[0]["stage_times_s"] = dict(zip(stages, (300.0, 10.0, 200.0, 40.0)))
    rows[1]["stage_times_s"] = dict(zip(stages, (500.0, 30.0, None, 60.0)))
    runtime = table_mod.summarise(rows)["runtime"]
    assert runtime["ours"]["median_stage_s"] == {
        "reconstruct": 400.0, "lift": 20.0, "identify": 200.0, "evaluate": 50.0}  # fmt: skip
    assert runtime["coupnerf"]["median_stage_s"]["reconstruct"] is None  # none recorded
    text = table_mod.markdown(table_mod.make_table(rows))
    assert "| memory | median s, stage I / II / III / eval |" in text
    assert "| GPU | 400 / 20 / 200 / 50 |" in text and "| GPU | - / - / - / - |" in text


def test_a_scene_without_ours_leaves_every_target_unmet():
    table_mod = _load("genesis_video_table")
    rows = _table1_rows()[:1] + [_row("E-S", "coupnerf", psnr=40.0, cd=1.0)]
    t = table_mod.summarise(rows)["targets"]
    # ours alone would meet the PSNR target, but it did not run on E-S
    assert t["observed_psnr"]["value"] == pytest.approx(33.0)
    assert t["observed_psnr"]["met"] is False and t["observed_psnr"]["missing"] == ["E-S"]


def test_ablation_differences_beside_the_run_to_run_spread():
    table_mod = _load("genesis_video_table")
    rows = []
    # two scenes, two seeds; object-wise CD + silhouette (ours) leads the scene-wise one by
    # 2 dB future PSNR on both scenes, with a seed spread of 1 dB (ours) and 0.5 dB
    for scene in ("E-P", "E-S"):
        for seed in (0, 1):
            for method, psnr in (
                ("ours", 31.0 + seed),
                ("scene-cd-sil", 29.25 + 0.5 * seed),
                ("object-cd", 30.0),
                ("scene-cd", 30.0 + 0.1 * seed),
                ("object-sil", 29.0),
                ("scene-sil", 29.0),
            ):
                rows.append(_row(scene, method, psnr=psnr + 2.0, cd=100.0, seed=seed))
    rows.append({"scene": "F-S", "method": "scene-cd", "seed": 0, "error": "x"})
    ab = table_mod.ablation_summary(rows)
    assert ab["seeds"] == [0, 1] and ab["complete"] == ["E-P", "E-S"]
    assert ab["scenes"] == ["E-P", "E-S", "F-S"]
    ours = ab["variants"]["object-cd-sil"]["future"]["psnr"]
    assert ours["mean"] == pytest.approx(31.5) and ours["spread"] == pytest.approx(1.0)
    by = {(d["object"], d["block"], d["key"]): d for d in ab["differences"]}
    d = by[("object-cd-sil", "future", "psnr")]
    assert d["scene"] == "scene-cd-sil" and d["n"] == 2
    assert d["difference"] == pytest.approx(31.5 - 29.5)
    assert d["spread"] == pytest.approx(0.75)  # mean of the two variants' spreads
    assert d["beyond_spread"] == 2 and d["p"] is None  # too few scenes for a test
    d = by[("object-cd", "future", "psnr")]
    assert d["difference"] == pytest.approx(-0.05) and d["beyond_spread"] == 0
    text = table_mod.markdown(table_mod.make_table(rows))
    assert "| object-wise CD + silhouette (ours) | scene-wise CD + silhouette | future PSNR dB |"
    assert "2.00 | 0.75 | 2 of 2 | - |" in text
    assert table_mod.ablation_summary(_table1_rows()) is None


def test_methods_recipes_and_overrides():
    bench = _load("genesis_video")
    sets = bench.parse_sets(["evaluate.emd_samples=64", "ours:reconstructor.iterations=5"], [
        *bench.METHODS, *bench.ABLATION])  # fmt: skip
    ours = bench.job_overrides(bench.Job("E-S", "ours"), sets)
    assert ours == [*bench.GENESIS_SETS, "evaluate.emd_samples=64", "reconstructor.iterations=5"]
    library = bench.job_overrides(bench.Job("E-S", "library"), sets)
    assert "identify.method=library" in library and "identify.library_scope=all" in library
    assert library[-1] == "reconstructor.iterations=5"  # ours' Stages I-II, ours' settings
    assert "reconstructor.iterations=5" not in bench.job_overrides(
        bench.Job("E-S", "coupnerf"), sets
    )
    oracle = bench.job_overrides(bench.Job("E-S", "library-oracle"), sets)
    # the oracle's scope comes after the library recipe's, so it wins
    assert oracle.index("identify.library_scope=family") > oracle.index(
        "identify.library_scope=all"
    )
    variant = bench.job_overrides(bench.Job("E-S", "scene-cd", 1), sets)
    assert variant[-2:] == ["reconstructor.iterations=5", "reconstructor.seed=1"]
    with pytest.raises(SystemExit, match="unknown method 'nope'"):
        bench.parse_sets(["nope:a=1"], list(bench.METHODS))
    with pytest.raises(SystemExit, match="key=value"):
        bench.parse_sets(["a"], list(bench.METHODS))
    # the library baselines run from video: ours' Stages I-II, the library's identification
    cfg = bench.load_job_recipe(
        bench.Job("E-S", "library-oracle"), scene=TINY, run_dir=Path("r"), overrides=oracle
    )
    assert cfg.reconstructor.name == "gauss-dynamic" and cfg.lifter.name == "gaussians"
    assert cfg.identify.method == "library" and cfg.identify.library_scope == "family"
    cfg = bench.load_job_recipe(
        bench.Job("E-S", "scene-cd"), scene=TINY, run_dir=Path("r"), overrides=variant
    )
    assert list(cfg.losses) == ["scene-chamfer"] and cfg.reconstructor.seed == 1


def test_settings_name_each_key_once_with_the_value_that_applied():
    table = _load("genesis_video_table")
    row = _row("E-S", "ours", psnr=31.0, cd=500.0)
    # the tool's default first, then the user's --set of the same key and another key
    row["overrides"] = ["simulator.substeps=400", "simulator.grid=48", "simulator.substeps=250"]
    (line,) = table.settings_lines([row])
    assert "`simulator.substeps=250` `simulator.grid=48`" in line
    assert "substeps=400" not in line


def test_jobs_share_stage_one_and_two_and_run_after_what_they_wait_for():
    bench = _load("genesis_video")
    jobs = bench.plan_jobs(["E-P", "E-S"], ["ours", "coupnerf"], ablation_scenes=["E-S"], seeds=2)
    names = [j.name for j in jobs]
    assert len(names) == len(set(names))  # ours seed 0 of E-S is table 1's run, once
    assert names[:5] == ["E-P/ours", "E-P/coupnerf", "E-S/ours", "E-S/coupnerf", "E-S/ours-seed1"]
    variants = jobs[5:]
    assert len(variants) == 2 * len(bench.ABLATION)
    assert {j.shares_from.name for j in variants} == {"E-S/ours", "E-S/ours-seed1"}
    assert bench.Job("E-S", "coupnerf").shares_from is None
    # the library baselines identify on ours' Stages I-II: ours' run comes first, once
    library = bench.plan_jobs(["E-P"], ["library", "library-oracle"])
    assert [j.name for j in library] == ["E-P/ours", "E-P/library", "E-P/library-oracle"]
    assert {j.shares_from.name for j in library[1:]} == {"E-P/ours"}


def test_planned_runs_as_a_device_queue_job_file(tmp_path):
    bench = _load("genesis_video")
    queue = _load("device_queue")
    scenes = tmp_path / "scenes"
    scenes.mkdir()
    for name in ("E-P", "E-S"):
        (scenes / name).symlink_to(TINY, target_is_directory=True)
    jobs = tmp_path / "video.jobs"
    out = tmp_path / "out"
    sets = ["--set", "simulator.grid=48", "--set", "ours:reconstructor.iterations=5"]
    argv = ["--scenes", str(scenes), "--out", str(out), "--job-file", str(jobs)]
    argv += ["--methods", "library,coupnerf", *sets]
    assert bench.main(argv) == 0
    assert not out.exists()  # nothing ran, nothing claimed
    parsed = queue.read_jobs(jobs)
    names = [j.name for j in parsed]
    assert names == ["E-P-ours", "E-P-library", "E-P-coupnerf", "E-S-ours", "E-S-library",
                     "E-S-coupnerf"]  # fmt: skip
    library = shlex.split(parsed[1].command)
    assert library[:2] == ["python3", "benchmarks/genesis_video.py"]
    assert library[library.index("--scenes") + 1] == str(scenes.resolve())
    assert library[library.index("--out") + 1] == str(out.resolve())
    assert " ".join(sets) in parsed[1].command
    # each line parses back into the run it names
    again = bench.parse_args(library[2:])
    assert again.part and again.only == "E-P" and again.method == "library"
    with pytest.raises(SystemExit, match="exists; give a new file"):
        bench.main(argv)


def test_a_foreign_output_folder_is_refused(tmp_path):
    bench = _load("genesis_video")
    out = tmp_path / "out"
    out.mkdir()
    (out / "mine.txt").write_text("keep")
    with pytest.raises(SystemExit, match="not a folder of benchmarks/genesis_video.py"):
        bench.claim_output(out)
    assert sorted(p.name for p in out.iterdir()) == ["mine.txt"]
    fresh = tmp_path / "fresh"
    bench.claim_output(fresh)
    bench.claim_output(fresh)  # its own folder: accepted again
    assert (fresh / bench.MARKER).is_file()


def test_results_section_goes_after_from_video_and_is_replaced_in_place():
    table_mod = _load("genesis_video_table")
    table = table_mod.make_table(_table1_rows())
    body = table_mod.section_text(table, command="python benchmarks/genesis_video.py", date="D")
    words = " ".join(body.split())
    assert "Machine: NVIDIA H100. Date D. Code c1." in words
    assert "2 scenes made by the Genesis engine (genesis-world 1.4.5, cpu backend)" in words
    assert "wide ranges, seeds 0, 2" in words and "E-P, E-S; 30 frames (15 observed)" in words
    assert "Settings of MOSIV (ours): recipes/video_paper.yaml; overrides" in words
    text = "# R\n\n## From video\n\na\n\n### Spread\n\nb\n\n## Noise\n\nc\n"
    once = table_mod.place_section(text, body)
    assert once.index("### Spread") < once.index(f"## {table_mod.SECTION}") < once.index("## Noise")
    twice = table_mod.place_section(once, body.replace("Date D", "Date E"))
    assert twice.count(f"## {table_mod.SECTION}") == 1 and "Date D" not in twice
    assert twice.replace("Date E", "Date D") == once
    merged = table_mod.section_text(table, command="MERGE", date="D", merged=True)
    words = " ".join(merged.split())
    assert f"Command: `{table_mod.PART_COMMAND}` per scene and method" in words
    assert words.index(table_mod.PART_COMMAND) < words.index("`MERGE`")


def test_tiny_genesis_scene_one_process_per_run_then_merge(tmp_path):
    """ours and CoupNeRF* each as a --part run, the merge, and a rerun of ours through the
    suite's own process per run, which resumes the finished run."""
    bench = _load("genesis_video")
    scenes = tmp_path / "scenes"
    scenes.mkdir()
    (scenes / "E-S").symlink_to(TINY, target_is_directory=True)
    out = tmp_path / "out"
    sets = [*COMMON, *(f"ours:{s}" for s in OURS), *(f"coupnerf:{s}" for s in COUPNERF)]
    base = ["--scenes", str(scenes), "--out", str(out)] + [x for s in sets for x in ("--set", s)]
    for method in ("ours", "library", "coupnerf"):
        assert bench.main([*base, "--only", "E-S", "--method", method, "--part"]) == 0
    results = tmp_path / "RESULTS.md"
    results.write_text("# Results\n\n## From video\n\nkept\n\n## Noise\n\nkept too\n")
    assert bench.main(["--out", str(out), "--merge", "--write-results", str(results)]) == 0
    table = json.loads((out / "table.json").read_text())
    rows = {r["method"]: r for r in table["rows"]}
    assert set(rows) == {"ours", "library", "coupnerf"}
    # the library baseline copied ours' Stage I-II: its time counts them as they ran there
    library, ours = rows["library"], rows["ours"]
    assert library["shared_stages"] and not ours["shared_stages"]
    for stage in ("reconstruct", "lift"):
        assert library["stage_times_s"][stage] == ours["stage_times_s"][stage]
    stages_one_two = ours["stage_times_s"]["reconstruct"] + ours["stage_times_s"]["lift"]
    assert library["time_s"] == pytest.approx(library["own_time_s"] + stages_one_two)
    # and its peak memory counts what they needed there
    for stage in ("reconstruct", "lift"):
        peak = ours["stage_peak_memory_gb"][stage]
        assert library["stage_peak_memory_gb"][stage] == peak
        assert library["peak_memory_gb"] >= peak
    for row in rows.values():
        assert "error" not in row, row.get("error")
        for block in ("observed", "future"):
            assert row[block]["psnr"] > 10.0 and row[block]["cd_mm2"] > 0
        assert row["time_s"] > 0 and row["peak_memory_gb"] > 0 and row["memory"] == "RSS"
    assert rows["coupnerf"]["stage1"] is None  # a radiance field, no Gaussians to score
    for row in rows.values():  # every stage timed, within the run's wall time
        times = row["stage_times_s"]
        assert min(times.values()) > 0 and sum(times.values()) <= row["time_s"]
    stage1 = rows["ours"]["stage1"]
    assert stage1["chamfer_floor_mm2"] > 0 and set(stage1["per_object"]) == {"1", "2"}
    for obj in stage1["per_object"].values():
        assert obj["cd_floor_multiple"] == pytest.approx(obj["cd_mm2_max"] / stage1[
            "chamfer_floor_mm2"])  # fmt: skip
        assert 0.0 <= obj["iou_min"] <= 1.0
    targets = table["summary"]["targets"]
    assert targets["gaussian_cd"]["n"] == 2 and targets["iou"]["n"] == 2
    # ours identifies as on a recording: the contact chosen from the observed frames
    identified = json.loads((out / "runs" / "E-S" / "ours" / "identified.json").read_text())
    assert identified["contact"]["mode"] in ("multi_field", "single_field")
    text = results.read_text()
    assert text.startswith("# Results\n\n## From video\n\nkept\n\n## From video on Genesis")
    assert text.endswith("## Noise\n\nkept too\n") and str(tmp_path) not in text
    assert "--out OUT --merge" in text and "| E-S | 1 | elastic |" in text
    # the suite's own path: ours again in a process of its own resumes the finished run
    before = json.loads((out / "parts" / "E-S" / "ours.json").read_text())
    assert bench.main([*base, "--methods", "ours"]) == 0
    after = json.loads((out / "parts" / "E-S" / "ours.json").read_text())
    assert after["time_s"] == before["time_s"] and after["observed"] == before["observed"]
    merged = json.loads((out / "table.json").read_text())
    assert {r["method"] for r in merged["rows"]} == {"ours", "library", "coupnerf"}  # kept


def test_three_object_section_is_the_merge_of_its_committed_runs():
    """RESULTS' three-object tables are what the committed runs merge into, line for line."""
    table_mod = _load("genesis_video_table")
    data = BENCH / "data" / "genesis_video_three_objects"
    rows = [json.loads(p.read_text()) for p in sorted((data / "parts").glob("*/*.json"))]
    assert sorted(r["scene"] for r in rows) == ["E-P-F", "E-P-S", "P-F-S"]
    assert {r["method"] for r in rows} == {"ours"} and {r["code"] for r in rows} == {"e1c9376"}
    text = table_mod.markdown(table_mod.make_table(rows))
    results = (ROOT / "docs" / "RESULTS.md").read_text()
    section = results[results.index("### The three-object scenes from video") :]
    section = section[: section.index("\n## ")]
    table_lines = [line for line in section.splitlines() if line.startswith("| ")]
    assert len(table_lines) >= 20
    for line in table_lines:
        assert line in text, line
    means = table_mod.make_table(rows)["summary"]["means"]["ours"]
    assert means["future"]["cd_mm2"]["value"] == pytest.approx(2154, abs=1)
    assert "Mean future\n  PSNR 25.8 dB" in section and "mean future Chamfer 2,150" in section
