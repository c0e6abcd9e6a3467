"""The oracle reconstructor: ground-truth points in place of Stage I, with optional noise.

It stands in for the Gaussian reconstruction in ablations, sensitivity studies (the paper's
i.i.d. and shared noise levels) and tests, so identification can be studied without
reconstruction error. It is the one reconstructor allowed to read ``gt/points.npz``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import torch

from mosiv_framework.interfaces import Reconstructor
from mosiv_framework.types import Reconstruction


@dataclass
class OracleOptions:
    """noise_iid (m): std of independent Gaussian noise per point and frame; noise_shared (m):
    std of one offset per object and frame shared by all its points (a rigid jitter);
    noise_iid_rel / noise_shared_rel: the same noises with std alpha * (xyz_max - xyz_min) per
    axis of the object at frame 0, the paper's sensitivity protocol (appendix, alpha = 0.005,
    0.02, 0.05); both kinds add up when both are given;
    max_points: random subsample per object (0 keeps all); seed: noise and subsampling seed."""

    noise_iid: float = 0.0
    noise_shared: float = 0.0
    noise_iid_rel: float = 0.0
    noise_shared_rel: float = 0.0
    max_points: int = 4000
    seed: int = 0

    def __post_init__(self) -> None:
        for name in ("noise_iid", "noise_shared", "noise_iid_rel", "noise_shared_rel"):
            if not getattr(self, name) >= 0:
                raise ValueError(
                    f"{name}={getattr(self, name)!r}: a standard deviation must be >= 0 "
                    "(metres, or a fraction of the object's extent for *_rel)"
                )
        if self.max_points < 0:
            raise ValueError(f"max_points must be >= 0 (0 keeps all), got {self.max_points}")


class OracleReconstructor(Reconstructor):
    def __init__(self, **options):
        self.options = OracleOptions(**options)

    def fit(self, scene, *, run_dir: Path | None = None) -> Reconstruction:
        opts = self.options
        generator = torch.Generator().manual_seed(opts.seed)
        points = {}
        for k, pts in scene.gt_points().items():
            if opts.max_points and pts.shape[1] > opts.max_points:
                keep = torch.randperm(pts.shape[1], generator=generator)[: opts.max_points]
                pts = pts[:, keep.sort().values]
            extent = pts[0].max(dim=0).values - pts[0].min(dim=0).values  # [3] m
            sigma_iid = opts.noise_iid + opts.noise_iid_rel * extent
            sigma_shared = opts.noise_shared + opts.noise_shared_rel * extent
            noise = sigma_iid * torch.randn(pts.shape, generator=generator)
            shared = sigma_shared * torch.randn((pts.shape[0], 1, 3), generator=generator)
            points[k] = pts + noise + shared
        return Reconstruction(points=points, extras={"reconstructor": "oracle"})
