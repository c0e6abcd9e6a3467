"""The Stage I scores of metrics.json: the Chamfer floor of a lattice and the per-object
Chamfer of the Gaussian centres to the true particles, with the reconstructor's mask IoU."""

from __future__ import annotations

import pytest
import torch

from mosiv_framework.metrics import chamfer_floor_mm2
from mosiv_framework.pipeline.evaluate import gt_particle_spacing, reconstruction_scores
from mosiv_framework.types import Reconstruction


def _lattice(n: int, spacing: float) -> torch.Tensor:
    axis = torch.arange(n, dtype=torch.float32) * spacing
    return torch.cartesian_prod(axis, axis, axis)


def test_floor_of_a_lattice_is_a_quarter_spacing_squared():
    # a point uniform in its particle's cubic cell has that particle as its nearest lattice
    # point (the cube is the lattice's Voronoi cell), at mean squared distance 3 s^2 / 12; the
    # way back, each particle to the nearest of its cell's samples, adds a little
    spacing = 0.01
    points = {1: _lattice(12, spacing).expand(2, -1, -1).contiguous()}
    floor = chamfer_floor_mm2(points, spacing=spacing, samples=8)
    quarter = (spacing * 1000.0) ** 2 / 4.0
    assert quarter * 0.97 < floor < quarter * 1.4


class _Scene:
    def __init__(self, gt: dict, params: dict):
        self._gt, self._params = gt, params

    def gt_points(self):
        return self._gt

    def gt_params(self):
        return self._params


def test_scores_per_object_against_the_floor_and_the_masks():
    spacing = 0.01
    body = _lattice(6, spacing)
    gt = {1: torch.stack([body, body + 0.1]), 2: torch.stack([body + 0.5, body + 0.5])}
    shift = torch.tensor([0.002, 0.0, 0.0])
    # object 1 exact; object 2 shifted 2 mm in frame 1: every point's nearest neighbour is its
    # own particle both ways (2 mm < half the spacing), so the Chamfer is 2 * (2 mm)^2
    points = {1: gt[1].clone(), 2: torch.stack([gt[2][0], gt[2][1] + shift])}
    training = {"iou": {"1": [0.95, 0.91], "2": [None, 0.8]}}
    recon = Reconstruction(points=points, extras={"training": training, "skipped_steps": 3})
    scene = _Scene(gt, {"generator_params": {"particle_size": spacing}})
    scores = reconstruction_scores(recon, scene)
    assert scores["particle_spacing_m"] == spacing and scores["skipped_steps"] == 3
    assert reconstruction_scores(Reconstruction(points=points), scene)["skipped_steps"] is None
    floor = scores["chamfer_floor_mm2"]
    assert floor == pytest.approx(chamfer_floor_mm2(gt, spacing=spacing))
    one, two = scores["per_object"]["1"], scores["per_object"]["2"]
    assert one["cd_mm2_max"] == pytest.approx(0.0, abs=1e-9) and one["cd_floor_multiple"] == 0
    assert two["cd_mm2_per_frame"][0] == pytest.approx(0.0, abs=1e-9)
    assert two["cd_mm2_max"] == pytest.approx(8.0, rel=1e-4)
    assert two["cd_floor_multiple"] == pytest.approx(8.0 / floor, rel=1e-4)
    assert one["iou_min"] == pytest.approx(0.91) and two["iou_min"] == pytest.approx(0.8)


def test_particle_spacing_of_either_generator():
    assert gt_particle_spacing({"generator_params": {"particle_spacing": 0.008}}) == 0.008
    assert gt_particle_spacing({"generator_params": {"particle_size": 0.01}}) == 0.01
    assert gt_particle_spacing({"generator_params": {}}) is None
    assert gt_particle_spacing({}) is None
