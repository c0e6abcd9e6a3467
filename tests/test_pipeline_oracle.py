"""The oracle reconstructor's relative noise follows the paper's protocol:
std = alpha * (xyz_max - xyz_min) per axis, i.i.d. per point or shared per object and frame."""

from __future__ import annotations

import pytest
import torch

from mosiv_framework.oracle import OracleReconstructor


class FakeScene:
    def __init__(self, pts):
        self.pts = pts

    def gt_points(self):
        return {1: self.pts}


def test_relative_noise_levels_and_kinds():
    gen = torch.Generator().manual_seed(0)
    extent = torch.tensor([0.1, 0.2, 0.4])
    pts = torch.rand(3, 20000, 3, generator=gen) * extent  # 3 frames
    alpha = 0.02
    iid = OracleReconstructor(noise_iid_rel=alpha, max_points=0).fit(FakeScene(pts)).points[1]
    diff = iid - pts
    measured = diff.reshape(-1, 3).std(dim=0)
    true_extent = pts[0].max(0).values - pts[0].min(0).values
    assert torch.allclose(measured, alpha * true_extent, rtol=0.03)
    shared = OracleReconstructor(noise_shared_rel=alpha, max_points=0).fit(FakeScene(pts))
    d = shared.points[1] - pts
    # one offset per frame: every point of a frame moved alike
    assert torch.allclose(d, d[:, :1].expand_as(d), atol=1e-6)
    assert float(d[:, 0].abs().max()) > 0


def test_negative_noise_is_rejected_by_name():
    with pytest.raises(ValueError, match="noise_shared_rel"):
        OracleReconstructor(noise_shared_rel=-1.0)
