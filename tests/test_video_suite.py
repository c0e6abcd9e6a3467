"""benchmarks/video_suite.py: the object-wise against scene-wise comparison is a paired test."""

from __future__ import annotations

from pathlib import Path

import pytest

from mosiv_framework.testing.scripts import load_script

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "video_suite.py"


def _suite():
    return load_script(SCRIPT)


def _metrics(psnr: float, cd: float) -> dict:
    block = {"psnr": psnr, "psnr_objects": psnr - 15, "ssim": 0.9, "cd_mm2": cd, "emd_mm": 1.0}
    errors = {"E_pct": None, "yield_pct": None, "friction_angle_deg": None, "v0_pct": None}
    return {
        "observed": block,
        "future": dict(block),
        "errors": errors,
        "time_s": 1.0,
        "peak_memory_gb": 1.0,
    }


def test_a_consistent_lead_is_significant_and_a_coin_flip_is_not():
    suite = _suite()
    # object-wise 0.5-1.4 dB ahead on all ten scenes; CD ahead on five, behind on five
    rows = []
    for i in range(10):
        cd_object, cd_scene = (100.0, 120.0 + i) if i % 2 else (120.0 + i, 100.0)
        rows.append(
            {
                "pair": f"S{i}",
                "object-cd-sil": _metrics(30.0 + 0.5 + 0.1 * i, cd_object),
                "scene-cd-sil": _metrics(30.0, cd_scene),
            }
        )
    summary = suite.summarise(rows)
    won, n, p = summary["object_beats_scene"]["object-cd-sil|future|psnr"]
    assert (won, n) == (10, 10)
    assert p == pytest.approx(2 / 2**10)  # exact signed-rank test: only the all-positive ranking
    won, n, p = summary["object_beats_scene"]["object-cd-sil|future|cd_mm2"]
    assert (won, n) == (5, 10) and p > 0.5
    text = suite.markdown(rows, summary)
    assert "future psnr: 10 of 10 (p = 0.002)" in text


def test_too_few_scenes_give_no_p_value():
    suite = _suite()
    assert suite.paired_p_value([(1.0, 0.0)] * 5) is None
    assert suite.paired_p_value([(1.0, 1.0)] * 10) is None  # no scene differs


def test_a_later_variant_waits_for_its_scenes_stage_one_and_two(tmp_path):
    import threading

    suite = _suite()
    shared = tmp_path / "object-cd-sil"
    (shared / "stages").mkdir(parents=True)
    timer = threading.Timer(0.2, lambda: (shared / "stages" / "lift.json").write_text("{}"))
    timer.start()
    try:
        suite.wait_for_shared_stages(shared, poll_s=0.02)  # returns once the lift is marked done
    finally:
        timer.cancel()
    assert (shared / "stages" / "lift.json").is_file()


def test_a_later_variant_stops_waiting_when_the_first_one_failed(tmp_path):
    suite = _suite()
    shared = tmp_path / "object-cd-sil"
    shared.mkdir()
    (shared / suite.STAGES_FAILED).write_text("RuntimeError: lifting found no cell\n")
    with pytest.raises(RuntimeError, match="no cell"):
        suite.wait_for_shared_stages(shared, poll_s=0.02)


def test_a_later_variant_stops_waiting_when_the_first_ones_process_died(tmp_path):
    import subprocess

    suite = _suite()
    shared = tmp_path / "ours"
    with suite.making_shared_stages(shared):  # a live owner: this process
        assert suite._owner_ended(shared) is None
    assert not suite.owner_path(shared).exists()  # let go when the block ends
    # a run killed hard leaves its owner file behind, naming a process that has ended
    dead = subprocess.Popen(["true"])
    dead.wait()
    owner = {"host": suite.socket.gethostname(), "pid": dead.pid}
    suite.owner_path(shared).write_text(suite.json.dumps(owner))
    with pytest.raises(RuntimeError, match=f"process {dead.pid} ended without them"):
        suite.wait_for_shared_stages(shared, poll_s=0.01)


def test_a_later_variant_gives_up_on_a_run_never_started(tmp_path):
    suite = _suite()
    with pytest.raises(RuntimeError, match="start the run that makes them"):
        suite.wait_for_shared_stages(tmp_path / "ours", poll_s=0.01, max_wait_s=0.05)


def test_copies_are_refreshed_and_their_use_is_told_apart(tmp_path):
    suite = _suite()
    shared, run = tmp_path / "ours", tmp_path / "library"
    for name in suite.SHARED_STAGES:
        (shared / name).parent.mkdir(parents=True, exist_ok=True)
        (shared / name).write_text(f"first {name}")
    suite.copy_shared_stages(shared, run, poll_s=0.01)
    assert suite.reused_shared_stages(shared, run)
    # the shared run's stages were made again (other settings): a rerun copies the new ones
    (shared / "stages" / "lift.json").write_text("second")
    assert not suite.reused_shared_stages(shared, run)
    suite.copy_shared_stages(shared, run, poll_s=0.01)
    assert (run / "stages" / "lift.json").read_text() == "second"
    # the copying run made its own Stage I (its settings differ): not a shared run
    (run / "stages" / "reconstruct.json").write_text("its own")
    assert not suite.reused_shared_stages(shared, run)
