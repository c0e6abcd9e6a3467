"""The sam2 segmenter's option errors, and its prompt / propagate / identity plumbing with a
stand-in predictor (the model itself needs weights that do not ship, so it is not run here)."""

from __future__ import annotations

import sys
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
import torch
from mosiv_sam2.segmenter import Sam2Segmenter, combine_logits, object_prompts

from mosiv_framework.errors import ConfigError, StageNotAvailable
from mosiv_framework.registry import get_registry
from mosiv_framework.scene import example
from mosiv_framework.scene.io import read_scene
from mosiv_framework.types import Frames


def test_missing_checkpoint_names_the_option_and_path(tmp_path):
    missing = tmp_path / "nothing.pt"
    with pytest.raises(ConfigError) as info:
        get_registry().create("segmenter", "sam2", {"checkpoint": str(missing), "config": "c"})
    assert "checkpoint" in str(info.value) and str(missing) in str(info.value)
    with pytest.raises(ConfigError, match="option config"):
        get_registry().create("segmenter", "sam2", {"checkpoint": str(missing)})
    with pytest.raises(ConfigError, match="prompt must be one of"):
        get_registry().create("segmenter", "sam2", {"prompt": "scribble"})


def test_missing_sam2_package_says_how_to_install(tmp_path, monkeypatch):
    checkpoint = tmp_path / "model.pt"
    checkpoint.write_bytes(b"weights")
    monkeypatch.setitem(sys.modules, "sam2", None)  # import sam2 -> ImportError
    options = {"checkpoint": str(checkpoint), "config": "configs/sam2.1/sam2.1_hiera_t.yaml"}
    with pytest.raises(StageNotAvailable, match="pip install sam2"):
        get_registry().create("segmenter", "sam2", options)


def test_prompts_box_and_inner_point():
    hull = np.zeros((3, 10, 12), dtype=np.uint8)
    hull[1, 2:6, 3:9] = 2  # object 2 appears at frame 1
    hull[0:3, 7:9, 0:2] = 1  # object 1 is tiny: below min_pixels
    prompts = object_prompts(hull, min_pixels=5)
    assert set(prompts) == {2}
    frame, box, point = prompts[2]
    assert frame == 1
    np.testing.assert_array_equal(box, [3, 2, 9, 6])
    assert hull[1, int(point[1]), int(point[0])] == 2


def test_combine_logits_picks_the_largest_positive():
    logits = np.full((2, 1, 2, 2), -1.0, dtype=np.float32)
    logits[0, 0, 0, :] = [2.0, 1.0]
    logits[1, 0, 0, :] = [1.0, 3.0]
    np.testing.assert_array_equal(combine_logits([4, 7], logits, (2, 2)), [[4, 7], [0, 0]])


class TruthPredictor:
    """Stands in for SAM2's video predictor: each prompt box is matched to the true object
    whose mask box on that frame overlaps it most, and propagation returns that object's true
    masks as logits (+-8) under the prompt's obj_id. A prompt in the wrong place, frame or
    coordinate order then picks the wrong object or none."""

    def __init__(self, true_masks: dict[str, np.ndarray]):
        self.true = true_masks
        self.calls = []

    def init_state(self, video_path):
        cam = Path(video_path).name
        n = len(list(Path(video_path).glob("*.jpg")))
        assert n == self.true[cam].shape[0]
        return {"cam": cam, "objects": {}}

    def add_new_points_or_box(self, inference_state, frame_idx, obj_id, box=None, **_):
        truth = self.true[inference_state["cam"]][frame_idx]
        best, best_iou = None, 0.0
        for k in (int(v) for v in np.unique(truth) if v):
            rows, cols = np.nonzero(truth == k)
            tb = np.array([cols.min(), rows.min(), cols.max() + 1, rows.max() + 1])
            inter = np.prod(
                np.maximum(np.minimum(box[2:], tb[2:]) - np.maximum(box[:2], tb[:2]), 0)
            )
            union = np.prod(box[2:] - box[:2]) + np.prod(tb[2:] - tb[:2]) - inter
            if inter / union > best_iou:
                best, best_iou = k, inter / union
        assert best is not None and best_iou > 0.5
        inference_state["objects"][obj_id] = best
        self.calls.append((inference_state["cam"], frame_idx, obj_id, best))

    def propagate_in_video(self, inference_state):
        truth = self.true[inference_state["cam"]]
        ids = sorted(inference_state["objects"])
        for t in range(truth.shape[0]):
            logits = np.stack([truth[t] == inference_state["objects"][i] for i in ids])
            yield t, ids, torch.from_numpy(np.where(logits, 8.0, -8.0)[:, None])

    def reset_state(self, inference_state):
        inference_state["objects"].clear()


def test_prompts_propagation_and_ids_with_a_stand_in_predictor(tmp_path):
    scene = read_scene(
        example.write_example_scene(tmp_path / "s", n_frames=6, n_cameras=4, size=48, seed=1)
    )
    plate = tmp_path / "plate"
    plate.mkdir()
    far = torch.tensor([[0.0, 0.0, 50.0], [1.0, 0.0, 50.0]], dtype=torch.float64)
    for cam in scene.cameras:  # the empty table: both spheres far above every view
        o, d = cam.rays(dtype=torch.float64)
        rgb, _ = example._render(
            o, d, far, torch.full((2,), 0.1).double(), torch.zeros(2, 3).double()
        )
        iio.imwrite(plate / f"{cam.id}.png", rgb)
    ids = scene.camera_ids
    rgb = {c: np.stack([scene.rgb(c, t) for t in range(scene.n_frames)]) for c in ids}
    true = {c: np.stack([scene.mask(c, t) for t in range(scene.n_frames)]) for c in ids}
    frames = Frames(rgb, {c.id: c for c in scene.cameras}, 2, scene.domain)
    predictor = TruthPredictor(true)
    segmenter = Sam2Segmenter(predictor=predictor, classical={"background_dir": str(plate)})
    masks = segmenter.segment(frames)
    # every camera prompted both objects on frame 0, each hull id on the same true object
    assert sorted((c, f, o) for c, f, o, _ in predictor.calls) == [
        (c, 0, o) for c in sorted(ids) for o in (1, 2)
    ]
    hull_to_true = {(o, t) for _, _, o, t in predictor.calls}
    assert len(hull_to_true) == 2 and len({o for o, _ in hull_to_true}) == 2
    relabel = np.zeros(256, dtype=np.uint8)
    for o, t in hull_to_true:
        relabel[t] = o
    for c in ids:
        np.testing.assert_array_equal(masks[c], relabel[true[c]])
