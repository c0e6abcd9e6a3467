"""Options of the object-aware dynamic Gaussian reconstructor (reconstructor ``gauss-dynamic``).

One frozen dataclass, validated in ``__post_init__`` so that a recipe with a bad value fails
before any training starts, with a message naming the option and its valid range.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from mosiv_framework.errors import ConfigError
from mosiv_gauss.options import RASTER_BACKENDS

#: how the static per-camera background is obtained (see ``train.estimate_background``)
BACKGROUND_MODES = ("median", "learned")


def _is_int(value: object) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _is_number(value: object) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


@dataclass(frozen=True)
class DynamicGaussOptions:
    """Initialisation, model size and training schedule of the dynamic Gaussians.

    Initialisation (``init.py``):
        hull_resolution: voxels along the longest side of the scene domain for the visual hull
            (voxel size = domain extent / hull_resolution, m).
        max_init_gaussians: at most this many hull voxels seed Gaussians (random subsample,
            split evenly between objects).
    Model (paper eq. 1, ``model.py``):
        n_bases: B, number of temporal bases; basis_width, basis_layers: hidden width and number
            of hidden layers of the basis network of time; coef_width, coef_layers: the same for
            the coefficient network of canonical position; pe_frequencies: octaves of the
            positional encoding of canonical positions; time_frequencies: octaves of the
            encoding of normalised time fed to the basis network (the highest has a period of
            2^(2-L) of the clip, so more octaves let the motion change faster, e.g. at impact).
    Training (paper eq. 2, ``train.py``):
        iterations: optimisation steps; views_per_step: (frame, camera) images per step;
        motion_init_iterations: steps fitting the deformation to per-object visual-hull centroid
            tracks before the photometric training (0 disables it);
        lambda_ssim: weight of (1 - SSIM); lambda_radius: weight of the mean radius in voxel
            units (eq. 2's |r_t|_1 made dimensionless); lambda_mask: weight of the per-object
            silhouette L1 against the instance masks; lambda_mask_coarse: weight of the same
            L1 between mask_pool x mask_pool block means (0: off; ``train.coarse_mask_l1``), for
            bodies whose masks are scattered dots; lambda_track: weight of the squared
            excess (voxels^2) over ``track_tolerance`` voxels of the distance between each
            object's mean Gaussian centre and its visual-hull centroid at the trained frames,
            where that hull is non-empty (a guard: an object a few pixels wide gives the
            photometric loss almost no gradient, and Adam's scale-free steps then let the
            deformation drift off every view, never to return); track_tolerance (voxels): the
            distance left free, above the hull centroid's own bias; lambda_hull: weight of
            a symmetric Chamfer (voxels^2, the first voxel free) between each object's Gaussian
            centres and its visual hull at the trained frames, the motion prior's hull term
            kept through training: a shape guide where the photometric and mask losses give
            the deformation no long-range pull, e.g. a body flattening on the ground. Off (0)
            by default: the hull is larger than the body where few cameras carve it, and the
            term pulls Gaussians out to fill it (a lift from 6 cameras grew by 30 %); with 11
            cameras, 0.01 keeps a flattening body's Gaussians on it (docs/BENCHMARKS.md "The
            hull term at the acceptance settings", which also chose lambda_radius's default);
        lr_position (m per step scale), lr_radius, lr_color, lr_opacity, lr_network,
            lr_background: Adam learning rates (log-radius, logits and weights are unitless);
        network_warmup: steps over which the networks' learning rate ramps up linearly from
            lr_network / network_warmup (0: no ramp; None: iterations // 15, 100 of 1500
            steps, so short fits keep most of their schedule at full rate). The photometric
            training starts a fresh Adam on networks the motion prior has just fitted, and
            Adam's first steps have the full learning rate whatever the gradient: at 1e-3 one
            step moved a banana's frame 2 from 1 to 12 hull voxels off its hull, and the drift
            guard then pulled the whole body, frame 0 too, 2 cm off;
        densify_every, densify_from, densify_until: densification/pruning schedule (steps);
        densify_grad: clone/split a Gaussian when its mean positional gradient times the voxel
            size exceeds this; prune_opacity: drop Gaussians whose opacity falls below this;
        max_gaussians: cap on the number of Gaussians after densification;
    Per-frame refinement (``refine.py``), after training:
        refine_iterations: steps fitting a free centre and log-radius offset per Gaussian and
            frame, networks, colours and opacities frozen (0: off, the plain eq. 1 model). With
            11 cameras, 2000 steps took the acceptance scene's worst collision-frame IoU from 0.67 to 0.99
            and cut the Chamfer (docs/BENCHMARKS.md "Per-frame refinement"); off by default
            because with few cameras the free offsets fit the views better than the 3D shape;
        lr_refine_position: Adam learning rate of the centre offsets, in hull voxels per step;
        lr_refine_radius: Adam learning rate of the log-radius offsets;
        lambda_refine_smooth: weight of the squared difference (voxels^2) between a Gaussian's
            offsets and those of its ``refine_neighbours`` nearest canonical neighbours of the
            same object, so each body moves as a body and hidden Gaussians follow (the default
            is the best of the sweep with 11 cameras; raise it when few cameras see a body);
    Rendering and run:
        background: "median" (per-pixel median of the frames outside the masks, fixed) or
            "learned" (that median refined as a parameter);
        tile_size: tile side of the torch rasterizer (pixels); raster_checkpoint: let the
            rasterizer recompute per-pixel values in the backward pass (less memory, slower);
            raster_backend: "auto" (default), "torch" or "warp", where the rasterizer
            composites (``TorchRasterizerOptions.backend``);
        device: torch device ("cpu", "cuda", "cuda:1"); seed: random seed; progress: tqdm bar;
        save_dir: sub-folder of the run folder the reconstruction is saved in ("" = no saving).
    """

    hull_resolution: int = 64
    max_init_gaussians: int = 4000
    n_bases: int = 10
    basis_width: int = 64
    basis_layers: int = 4
    coef_width: int = 64
    coef_layers: int = 4
    pe_frequencies: int = 4
    time_frequencies: int = 4
    iterations: int = 3000
    views_per_step: int = 2
    motion_init_iterations: int = 400
    lambda_ssim: float = 0.2
    lambda_radius: float = 0.001
    lambda_mask: float = 0.5
    lambda_mask_coarse: float = 0.0
    mask_pool: int = 4
    lambda_track: float = 0.01
    track_tolerance: float = 5.0
    lambda_hull: float = 0.0
    lr_position: float = 1e-3
    lr_radius: float = 5e-3
    lr_color: float = 2e-2
    lr_opacity: float = 3e-2
    lr_network: float = 1e-3
    lr_background: float = 1e-2
    network_warmup: int | None = None
    refine_iterations: int = 0
    lr_refine_position: float = 0.5
    lr_refine_radius: float = 0.02
    lambda_refine_smooth: float = 0.001
    refine_neighbours: int = 8
    densify_every: int = 100
    densify_from: int = 200
    densify_until: int = 2000
    densify_grad: float = 2e-4
    prune_opacity: float = 0.02
    max_gaussians: int = 20000
    background: str = "median"
    tile_size: int = 16
    raster_checkpoint: bool = False
    raster_backend: str = "auto"
    device: str = "cpu"
    seed: int = 0
    progress: bool = True
    save_dir: str = "gauss-dynamic"

    def __post_init__(self) -> None:
        problems: list[str] = []
        ints = {
            "hull_resolution": (8, 512),
            "max_init_gaussians": (2, 10_000_000),
            "n_bases": (1, 64),
            "basis_width": (4, 4096),
            "basis_layers": (1, 16),
            "coef_width": (4, 4096),
            "coef_layers": (1, 16),
            "pe_frequencies": (0, 16),
            "time_frequencies": (0, 16),
            "iterations": (0, 10_000_000),
            "views_per_step": (1, 1024),
            "motion_init_iterations": (0, 1_000_000),
            "densify_every": (1, 1_000_000),
            "densify_from": (0, 10_000_000),
            "densify_until": (0, 10_000_000),
            "max_gaussians": (2, 100_000_000),
            "refine_iterations": (0, 10_000_000),
            "refine_neighbours": (1, 64),
            "mask_pool": (1, 64),
            "tile_size": (1, 256),
            "seed": (0, 2**63 - 1),
        }
        if self.network_warmup is not None:
            ints["network_warmup"] = (0, 1_000_000)
        for name, (lo, hi) in ints.items():
            value = getattr(self, name)
            if not _is_int(value) or not lo <= value <= hi:
                problems.append(f"{name}={value!r}: must be an integer in [{lo}, {hi}]")
        non_negative = ("lambda_ssim", "lambda_radius", "lambda_mask", "lambda_track")
        non_negative += ("lambda_mask_coarse",)
        non_negative += ("lambda_hull", "lambda_refine_smooth")
        non_negative += ("track_tolerance", "densify_grad")
        for name in non_negative:
            value = getattr(self, name)
            if not _is_number(value) or value < 0:
                problems.append(f"{name}={value!r}: must be a finite number >= 0")
        rates = ("lr_position", "lr_radius", "lr_color", "lr_opacity", "lr_network")
        for name in (*rates, "lr_background", "lr_refine_position", "lr_refine_radius"):
            value = getattr(self, name)
            if not _is_number(value) or not 0 < value <= 1:
                problems.append(f"{name}={value!r}: must be a learning rate in (0, 1]")
        if not _is_number(self.prune_opacity) or not 0 <= self.prune_opacity < 1:
            problems.append(f"prune_opacity={self.prune_opacity!r}: must be a number in [0, 1)")
        if self.raster_backend not in RASTER_BACKENDS:
            problems.append(
                f"raster_backend={self.raster_backend!r}: must be one of "
                f"{', '.join(RASTER_BACKENDS)}"
            )
        if self.background not in BACKGROUND_MODES:
            problems.append(
                f"background={self.background!r}: must be one of {', '.join(BACKGROUND_MODES)}"
            )
        if not isinstance(self.device, str) or self.device.split(":")[0] not in ("cpu", "cuda"):
            problems.append(f"device={self.device!r}: must be 'cpu', 'cuda' or 'cuda:N'")
        for name in ("progress", "raster_checkpoint"):
            if not isinstance(getattr(self, name), bool):
                problems.append(f"{name}={getattr(self, name)!r}: must be true or false")
        if not isinstance(self.save_dir, str) or ".." in self.save_dir.split("/"):
            problems.append(
                f"save_dir={self.save_dir!r}: must be a folder name inside the run folder "
                "('' for no saving)"
            )
        if problems:
            raise ConfigError([f"reconstructor gauss-dynamic: {p}" for p in problems])
