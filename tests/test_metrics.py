"""Evaluation metrics against values computed by hand (units: mm^2, mm, dB)."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest
import torch

from mosiv_framework.metrics import (
    chamfer_mm2,
    emd_mm,
    frame_metrics,
    geometry_metrics,
    image_metrics,
    nearest_distances,
    psnr,
    region_psnr,
    ssim,
)
from mosiv_framework.types import GeometryFrames

MM = 1e-3  # one millimetre in metres


def test_chamfer_hand_computed_two_tiny_sets():
    # a = {(0,0,0), (2,0,0)} mm, b = {(0,1,0)} mm
    a = np.array([[0.0, 0.0, 0.0], [2.0, 0.0, 0.0]]) * MM
    b = np.array([[0.0, 1.0, 0.0]]) * MM
    # a -> b: |(0,-1,0)|^2 = 1, |(2,-1,0)|^2 = 4 + 1 = 5; mean = 3 mm^2
    # b -> a: nearest is (0,0,0) at distance 1 -> 1 mm^2
    expected = (1.0 + 5.0) / 2 + 1.0
    assert chamfer_mm2(a, b) == pytest.approx(expected, rel=1e-9)
    assert chamfer_mm2(b, a) == pytest.approx(expected, rel=1e-9)


def test_chamfer_one_millimetre_offset_gives_two_square_millimetres():
    rng = np.random.default_rng(0)
    # points on a 1 cm lattice, so a 1 mm shift keeps each point's nearest neighbour its twin
    grid = np.stack(np.meshgrid(*[np.arange(5)] * 3, indexing="ij"), -1).reshape(-1, 3) * 0.01
    a = grid + rng.normal(scale=1e-4, size=grid.shape)
    b = a + np.array([0.0, 0.0, 1.0]) * MM
    # each direction contributes mean(1 mm^2) = 1 mm^2
    assert chamfer_mm2(a, b) == pytest.approx(1.0 + 1.0, rel=1e-9)
    # torch input in float32 gives the same value up to float32 rounding of metre coordinates
    assert chamfer_mm2(torch.tensor(a, dtype=torch.float32), torch.tensor(b)) == pytest.approx(
        2.0, rel=1e-3
    )


def test_chamfer_identical_sets_is_zero_and_rejects_bad_shapes():
    a = np.random.default_rng(1).random((50, 3))
    assert chamfer_mm2(a, a[::-1]) == 0.0
    with pytest.raises(ValueError, match=r"\[N, 3\]"):
        chamfer_mm2(a[:, :2], a)
    with pytest.raises(ValueError, match="empty"):
        chamfer_mm2(np.zeros((0, 3)), a)


def _brute_force_nearest(query: torch.Tensor, reference: torch.Tensor, rows: int) -> torch.Tensor:
    """Nearest distances by exhaustive search in row chunks (float64)."""
    out = [
        torch.cdist(query[i : i + rows], reference).min(dim=1).values
        for i in range(0, len(query), rows)
    ]
    return torch.cat(out)


def test_chamfer_100k_points_fast_and_matches_brute_force():
    rng = np.random.default_rng(2)
    a = rng.random((100_000, 3)) * 0.3  # a 30 cm box, like a tabletop scene
    b = rng.random((100_000, 3)) * 0.3
    start = time.perf_counter()
    value = chamfer_mm2(a, b)
    elapsed = time.perf_counter() - start
    # about 0.3 s on two idle cores; the bound leaves room for a busy CI machine
    assert elapsed < 10.0, f"100k x 100k Chamfer took {elapsed:.1f} s"

    # brute force over every reference point for a random subsample of query points
    picks = rng.choice(len(a), size=1000, replace=False)
    ta, tb = torch.from_numpy(a), torch.from_numpy(b)
    brute_ab = _brute_force_nearest(ta[picks], tb, rows=250).numpy()
    brute_ba = _brute_force_nearest(tb[picks], ta, rows=250).numpy()
    np.testing.assert_allclose(nearest_distances(a[picks], b), brute_ab, rtol=1e-9, atol=0)
    np.testing.assert_allclose(nearest_distances(b[picks], a), brute_ba, rtol=1e-9, atol=0)
    # the full value agrees with the subsample estimate of both means (within sampling error)
    estimate = np.mean((brute_ab / MM) ** 2) + np.mean((brute_ba / MM) ** 2)
    assert value == pytest.approx(estimate, rel=0.1)


def test_emd_translate_by_d_equals_d():
    rng = np.random.default_rng(3)
    a = rng.random((300, 3)) * 0.1
    d = np.array([3.0, 0.0, 4.0]) * MM  # |d| = 5 mm
    # any matching costs sum |a_i + d - a_s(i)| >= |sum (a_i + d - a_s(i))| = N |d|, so the
    # identity matching, of mean length |d|, is optimal
    assert emd_mm(a, a + d) == pytest.approx(5.0, rel=1e-9)


def test_emd_of_permuted_identical_sets_is_zero():
    a = np.random.default_rng(4).random((500, 3))
    perm = np.random.default_rng(5).permutation(500)
    assert emd_mm(a, a[perm]) == pytest.approx(0.0, abs=1e-12)


def test_emd_hand_computed_matching_and_seeded_subsampling():
    # a = {(0,0,0), (10,0,0)} mm, b = {(1,0,0), (10,2,0)} mm: matching the near pairs costs
    # 1 + 2 = 3 (mean 1.5 mm); crossing costs 10.198 + 9 (worse)
    a = np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0]]) * MM
    b = np.array([[10.0, 2.0, 0.0], [1.0, 0.0, 0.0]]) * MM
    assert emd_mm(a, b) == pytest.approx(1.5, rel=1e-9)

    rng = np.random.default_rng(6)
    big_a, big_b = rng.random((3000, 3)), rng.random((2500, 3))
    first = emd_mm(big_a, big_b, n_samples=256, seed=7)
    assert emd_mm(big_a, big_b, n_samples=256, seed=7) == first  # same seed, same subsample
    assert emd_mm(big_a, big_b, n_samples=256, seed=8) != first
    with pytest.raises(ValueError, match="n_samples"):
        emd_mm(big_a, big_b, n_samples=0)


def test_psnr_of_known_mse():
    target = torch.full((16, 16, 3), 0.5, dtype=torch.float64)
    pred = target.clone()
    pred[::2] += 0.1  # half the pixels off by 0.1: MSE = 0.5 * 0.01 = 0.005
    expected = 10 * math.log10(1.0 / 0.005)
    assert psnr(pred, target) == pytest.approx(expected, rel=1e-9)
    # with a peak value of 2 the same error is 10 log10(4) dB better
    assert psnr(pred, target, max_value=2.0) == pytest.approx(
        expected + 10 * math.log10(4), rel=1e-9
    )
    # a batch averages per-image PSNRs: MSEs 0.01 and 0.0025 -> 20 and 26.02 dB
    batch_t = torch.full((2, 3, 8, 8), 0.5)
    batch_p = batch_t + torch.tensor([0.1, 0.05]).view(2, 1, 1, 1)
    assert psnr(batch_p, batch_t) == pytest.approx(
        (10 * math.log10(100) + 10 * math.log10(400)) / 2, rel=1e-5
    )


def test_ssim_identical_is_one_and_decreases_with_noise():
    rng = np.random.default_rng(9)
    image = rng.random((32, 32, 3))
    assert ssim(image, image) == pytest.approx(1.0, abs=1e-9)
    low = np.clip(image + rng.normal(scale=0.05, size=image.shape), 0, 1)
    high = np.clip(image + rng.normal(scale=0.2, size=image.shape), 0, 1)
    s_low, s_high = ssim(low, image), ssim(high, image)
    assert 1.0 > s_low > s_high
    with pytest.raises(ValueError, match="window"):
        ssim(image, image, window=4)
    with pytest.raises(ValueError, match="differ in shape"):
        ssim(image, image[:16])


def test_frame_metrics_per_object_and_scene():
    rng = np.random.default_rng(10)
    # object 1: 40 points of a 1 cm lattice, 3 frames; object 2: random points 1 m away
    lattice = np.stack(np.meshgrid(*[np.arange(4)] * 3, indexing="ij"), -1).reshape(-1, 3) * 0.01
    target = {1: np.stack([lattice[:40]] * 3), 2: rng.random((3, 30, 3)) * 0.1 + 1.0}
    # object 1 shifted by 2 mm in every frame, object 2 exact
    shift = np.array([2.0, 0.0, 0.0]) * MM
    predicted = {1: target[1] + shift, 2: target[2].copy()}
    out = geometry_metrics(predicted, target)
    # object 1: every point 2 mm from its twin, the lattice spacing (10 mm) is far larger
    assert out["per_object"][1]["cd_mm2"] == pytest.approx(4.0 + 4.0, rel=1e-9)
    assert out["per_object"][1]["emd_mm"] == pytest.approx(2.0, rel=1e-9)
    assert out["per_object"][2] == {"cd_mm2": 0.0, "emd_mm": 0.0}
    # the scene union (objects 1 m apart): 40 of 70 points contribute 4 mm^2 each way
    assert out["cd_mm2"] == pytest.approx(2 * 4.0 * 40 / 70, rel=1e-9)

    # GeometryFrames input and a frame selection give the same per-frame values
    frames = GeometryFrames(
        frames=[0, 1, 2],
        points={k: [torch.tensor(v[t]) for t in range(3)] for k, v in predicted.items()},
    )
    sub = geometry_metrics(frames, target, frames=[1])
    assert sub["per_object"][1]["cd_mm2"] == pytest.approx(8.0, rel=1e-6)

    img_t = [rng.random((8, 8, 3)) for _ in range(2)]
    img_p = [np.clip(i + 0.1, 0, 1) for i in img_t]
    full = frame_metrics(predicted, target, predicted_images=img_p, target_images=img_t)
    assert set(full) == {"cd_mm2", "emd_mm", "psnr", "ssim", "psnr_objects", "per_object"}
    assert full["psnr_objects"] is None  # no regions given
    assert full["psnr"] == pytest.approx(image_metrics(img_p, img_t)["psnr"])
    assert full["psnr"] == pytest.approx(
        np.mean([psnr(p, t) for p, t in zip(img_p, img_t, strict=True)])
    )
    assert frame_metrics(predicted, target)["psnr"] is None

    # the region PSNR sees only its pixels: an error of 0.2 inside a 2x2 region and none
    # outside gives 10 log10(1 / 0.04) there, whatever the rest of the image holds
    clean = rng.random((8, 8, 3)) * 0.5
    damaged = clean.copy()
    damaged[2:4, 2:4] += 0.2
    region = np.zeros((8, 8), dtype=bool)
    region[2:4, 2:4] = True
    expected = 10 * np.log10(1 / 0.04)
    assert region_psnr(damaged, clean, region) == pytest.approx(expected, rel=1e-5)
    assert psnr(damaged, clean) == pytest.approx(expected + 10 * np.log10(64 / 4), rel=1e-5)
    assert region_psnr(damaged, clean, np.zeros((8, 8), dtype=bool)) is None
    block = frame_metrics(
        predicted,
        target,
        predicted_images=[damaged, damaged],
        target_images=[clean, clean],
        image_regions=[region, region],
    )
    assert block["psnr_objects"] == pytest.approx(expected, rel=1e-5)
    with pytest.raises(ValueError, match="one \\[H, W\\] mask per image"):
        region_psnr(damaged, clean, np.stack([region, region]))

    with pytest.raises(ValueError, match="differ from target objects"):
        geometry_metrics({1: predicted[1]}, target)
    with pytest.raises(ValueError, match="not in 0..2"):
        geometry_metrics(predicted, target, frames=[5])


def test_chamfer_against_a_particle_lattice_has_a_floor_of_a_quarter_spacing_squared():
    # The generator places each body's particles on a lattice of spacing h at a random phase.
    # Points that fill the body without knowing that phase sit, per axis, uniformly within
    # +-h/2 of the nearest lattice plane, so their mean squared distance to the particles is
    # 3 * h^2 / 12 = h^2 / 4 (16 mm^2 at the benchmark's 8 mm), one direction of the Chamfer
    # alone; a reconstruction scored against the particles cannot go below it.
    rng = np.random.default_rng(3)
    h = 0.008
    axis = np.arange(13) * h
    lattice = np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3)
    lattice = lattice + rng.uniform(0.0, h, size=3)
    dense = rng.uniform(2 * h, 11 * h, size=(20000, 3))  # inside, away from the edges
    one_way = float(np.mean((nearest_distances(dense, lattice) * 1000.0) ** 2))
    assert one_way == pytest.approx(h**2 / 4 * 1e6, rel=0.03)
    assert chamfer_mm2(dense, lattice) > 16.0
