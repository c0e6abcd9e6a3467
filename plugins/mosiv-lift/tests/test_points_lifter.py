"""The gt-points lifter: frame-0 points as particles, and each point split into a finer lattice
for a simulator grid finer than the points."""

from __future__ import annotations

import pytest
import torch
from mosiv_lift.points import PointsLifter, PointsLifterOptions, occupied_volume, split_points

from mosiv_framework.scene.io import SceneObject
from mosiv_framework.types import Reconstruction


def cube_points(n: int, spacing: float, origin=(0.0, 0.0, 0.0)) -> torch.Tensor:
    """An n x n x n lattice of points ``spacing`` apart: a cube of side n * spacing."""
    axis = torch.arange(n, dtype=torch.float32) * spacing
    grid = torch.stack(torch.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3)
    return grid + torch.tensor(origin)


def test_split_points_fills_each_points_cell_with_a_finer_lattice():
    """A lattice of pitch s split by 2 is the lattice of pitch s / 2 over the same cube (the
    same centroid, the same extent grown by nothing but the half-cells at the faces)."""
    s = 0.01
    points = cube_points(4, s)
    volume = points.shape[0] * s**3
    split = split_points(points, 2, volume)
    assert split.shape == (8 * 64, 3)
    torch.testing.assert_close(split.mean(0), points.mean(0), rtol=0, atol=1e-7)
    finer = cube_points(8, s / 2, origin=(-s / 4, -s / 4, -s / 4))
    got = sorted(map(tuple, split.round(decimals=6).tolist()))
    want = sorted(map(tuple, finer.round(decimals=6).tolist()))
    assert got == want
    assert split_points(points, 1, volume) is points


def test_lifter_split_keeps_each_bodys_volume_and_id():
    s = 0.01
    points = {1: cube_points(4, s)[None], 2: cube_points(3, s, origin=(0.2, 0, 0))[None]}
    reconstruction = Reconstruction(points=points)
    scene = type(
        "Scene", (), {"objects": [SceneObject(1, "a", "elastic"), SceneObject(2, "b", "sand")]}
    )
    plain = PointsLifter(voxel_size=s).lift(reconstruction, scene)
    fine = PointsLifter(voxel_size=s, split=3).lift(reconstruction, scene)
    for k in (1, 2):
        body = plain.object_ids == k
        split_body = fine.object_ids == k
        assert int(split_body.sum()) == 27 * int(body.sum())
        total = float(fine.volumes[split_body].sum())
        assert total == pytest.approx(float(plain.volumes[body].sum()), rel=1e-5)
        assert total == pytest.approx(occupied_volume(points[k][0], s), rel=1e-5)


@pytest.mark.parametrize("split", [0, 1.5, True])
def test_split_must_be_a_whole_number_of_at_least_one(split):
    with pytest.raises(ValueError, match="split must be a whole number >= 1"):
        PointsLifterOptions(split=split)
