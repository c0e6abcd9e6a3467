"""Time offsets of ``mosiv data import``: offsets given by hand or none, and what becomes of
cameras that started late (``--late-cameras`` trim, drop, keep), on the capture of the rendered
scene that tests/test_import.py builds; the import's general flow is tested there.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from mosiv_framework.capture import CaptureError, import_recording
from mosiv_framework.scene import read_scene, validate_scene

pytest.importorskip("imageio_ffmpeg")

# the rendered scene, its capture and the shared helpers (--import-mode=importlib leaves this
# folder off sys.path)
HERE = Path(__file__).resolve().parent
if str(HERE) not in sys.path:
    sys.path.insert(0, str(HERE))
from capture_fakes import (  # noqa: E402
    LATE,
    N_FRAMES,
    expect_error,
    psnr,
    render_spheres,
    settings,
    sphere_paths,
    write_capture,
)


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Path:
    return render_spheres(tmp_path_factory.mktemp("scene") / "s", "slide", sphere_paths())


@pytest.fixture(scope="module")
def capture(scene, tmp_path_factory) -> Path:
    return write_capture(scene, tmp_path_factory.mktemp("capture") / "c")


# ------------------------------------------------------------------ offsets given or none
def test_given_offsets_and_objects_yaml(capture, tmp_path):
    import json

    yaml_path = tmp_path / "objects.yaml"
    yaml_path.write_text(
        "objects:\n  1: {material: elastic, name: red, initial_velocity: [0, 1, 0]}\n"
        "  2: sand\noffsets: {cam_00: 2, cam_02: 2, cam_03: 1}\n"
    )
    out = import_recording(
        settings(capture, tmp_path / "s", materials=None, objects_yaml=yaml_path)
    )
    record = json.loads((out / "import.json").read_text())
    assert record["offsets_estimated"] is False
    assert record["hints"] == {"1": {"initial_velocity": [0, 1, 0]}}
    assert [o.name for o in read_scene(out).objects] == ["red", "object_2"]


def test_frame_counts_that_differ_after_offsets(capture, tmp_path):
    expect_error(
        settings(capture, tmp_path / "s", offsets="none", late_cameras="trim"),
        CaptureError, "different frame counts", "'cam_01': 26", "'cam_00': 28",
    )  # fmt: skip


# ------------------------------------------------------------ cameras that started late
def test_cameras_that_started_late_can_be_left_out_to_keep_every_frame(scene, tmp_path):
    """``late_cameras="drop"`` (``--late-cameras drop``): the camera that started late is
    left out, the others keep every frame (frame t is the scene's frame t); under the default
    trim every camera drops to the common frames; "drop" that would leave one camera, or an
    unknown policy, is refused with the cameras named."""
    import json

    from mosiv_framework.capture.offsets import cameras_left_out
    from mosiv_framework.capture.reference import reference_shift

    capture = write_capture(scene, tmp_path / "c", late={"cam_01": 2})
    out = import_recording(settings(capture, tmp_path / "s", late_cameras="drop"))
    original, got = read_scene(scene), read_scene(out)
    assert validate_scene(out) == []
    record = json.loads((out / "import.json").read_text())
    assert record["late_cameras_left_out"] == ["cam_01"]
    assert got.camera_ids == [c for c in original.camera_ids if c != "cam_01"]
    assert got.n_frames == N_FRAMES
    for cam in got.camera_ids:
        ref = np.stack([original.rgb(cam, t) for t in range(N_FRAMES)])
        mine = np.stack([got.rgb(cam, t) for t in range(N_FRAMES)])
        assert psnr(mine, ref) > 28, cam
    # the reference ground truth of such an import starts at the kept cameras' first frame
    capture_record = {
        "cameras": [{"id": "cam_00", "start_frame": 0}, {"id": "cam_01", "start_frame": 2}]
    }
    assert reference_shift(capture_record, record) == 0
    trimmed = {"offsets": {"cam_00": 2, "cam_01": 0}}
    assert reference_shift(capture_record, trimmed) == 2
    with pytest.raises(CaptureError, match="do not undo the capture's late starts"):
        reference_shift(capture_record, {"offsets": {"cam_00": 0, "cam_01": 0}})
    assert cameras_left_out({"a": 2, "b": 0, "c": 2}, "trim") == []
    with pytest.raises(CaptureError, match=r"would leave 1 camera \(a\).*b, c started later"):
        cameras_left_out({"a": 2, "b": 0, "c": 1}, "drop")
    assert cameras_left_out({"a": 2, "b": 0, "c": 1}, "keep") == []
    with pytest.raises(CaptureError, match="valid values are trim, drop, keep"):
        cameras_left_out({"a": 0}, "pad")


def test_cameras_that_started_late_can_be_kept_with_every_frame(scene, capture, tmp_path):
    """``late_cameras="keep"``: every camera and every frame; the late cameras are declared
    with the frames they recorded (cameras.json ``frames``), their views match the scene's, the
    other cameras' frame 0 is the scene's frame 0, and the masks carve frame 0's hull from the
    cameras that recorded it."""
    import json

    from mosiv_framework.capture.reference import reference_shift

    out = import_recording(settings(capture, tmp_path / "s", late_cameras="keep"))
    original, got = read_scene(scene), read_scene(out)
    assert validate_scene(out) == []
    assert got.camera_ids == original.camera_ids and got.n_frames == N_FRAMES
    assert got.camera_frames == {c: (d, N_FRAMES - 1) for c, d in LATE.items()}
    for cam in got.camera_ids:
        frames = list(got.recorded_frames(cam))
        ref = np.stack([original.rgb(cam, t) for t in frames])
        mine = np.stack([got.rgb(cam, t) for t in frames])
        assert psnr(mine, ref) > 28, cam
        masks_ref = np.stack([original.mask(cam, t) for t in frames]) > 0
        masks = np.stack([got.mask(cam, t) for t in frames]) > 0
        assert (masks & masks_ref).sum() / (masks | masks_ref).sum() > 0.7, cam
    assert [c.id for c in got.cameras_at(0)] == [c for c in got.camera_ids if c not in LATE]
    for cam in got.cameras_at(0):  # frame 0's hull from its two cameras: no ghost volume
        mine, ref = got.mask(cam.id, 0), original.mask(cam.id, 0)
        assert set(np.unique(mine)) == set(np.unique(ref)), cam.id
        iou = ((mine > 0) & (ref > 0)).sum() / ((mine > 0) | (ref > 0)).sum()
        assert iou > 0.7, (cam.id, iou)
    record = json.loads((out / "import.json").read_text())
    assert record["late_cameras_kept"] == {c: [d, N_FRAMES - 1] for c, d in LATE.items()}
    capture_record = {
        "cameras": [{"id": c, "start_frame": LATE.get(c, 0)} for c in original.camera_ids]
    }
    assert reference_shift(capture_record, record) == 0


def test_keep_pads_cameras_that_started_late_or_stopped_early():
    """pad_late_cameras: the clip runs from the earliest start to the latest end; each camera's
    frames land at their instants, the rest are zeros declared as not recorded; --frames cuts
    it; what cannot be kept is refused with the cameras named."""
    from mosiv_framework.capture.offsets import pad_late_cameras

    def video(n: int, value: int) -> np.ndarray:
        return np.stack([np.full((2, 2, 3), value + t, np.uint8) for t in range(n)])

    # a: started first (drops 2 to align), b: started 2 frames late, c: 1 late and stopped early
    videos = {"a": video(8, 0), "b": video(6, 100), "c": video(3, 200)}
    out, spans = pad_late_cameras(videos, {"a": 2, "b": 0, "c": 1}, None)
    assert {c: len(v) for c, v in out.items()} == {"a": 8, "b": 8, "c": 8}
    assert spans == {"b": (2, 7), "c": (1, 3)}
    assert out["a"][0, 0, 0, 0] == 0 and out["b"][2, 0, 0, 0] == 100
    assert out["c"][1, 0, 0, 0] == 200 and out["c"][3, 0, 0, 0] == 202
    assert not out["b"][:2].any() and not out["c"][4:].any()
    # a camera with nothing to pad is not copied: a long clip is held once
    assert np.shares_memory(out["a"], videos["a"]) and not np.shares_memory(out["b"], videos["b"])
    out, spans = pad_late_cameras(videos, {"a": 2, "b": 0, "c": 1}, 3)
    assert len(out["a"]) == 3 and spans == {"b": (2, 2), "c": (1, 2)}
    with pytest.raises(CaptureError, match="--frames 9: the cameras cover 8 frames at most"):
        pad_late_cameras(videos, {"a": 2, "b": 0, "c": 1}, 9)
    with pytest.raises(CaptureError, match="camera\\(s\\) b start after the last kept frame 1"):
        pad_late_cameras(videos, {"a": 2, "b": 0, "c": 1}, 2)
