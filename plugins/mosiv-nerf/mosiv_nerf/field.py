"""The frame-0 radiance field: explicit voxel grids of per-object density and colour (the
Eulerian half of PAC-NeRF's hybrid representation), fitted to every camera's frame-0 image and
masks by differentiable volume rendering.

Density of object k: sigma_k(x) = softplus(D_k(x)) / cell, with D_k the trilinear
interpolation of its raw grid (interpolating before the activation keeps surfaces sharp, as in
DVGO); raw 0 means an opacity of 1/2 over one voxel. Colour: c(x) = sigmoid(C(x)), one colour
grid for all objects (sRGB values, compared with the images as recorded). Rendered pixels are
composited over the camera's static background: I = C + (1 - alpha) B.

The fit minimises, over random batches of frame-0 rays that cross the field's box,

    L = |I - I_rec|^2 + mask_weight sum_k |alpha_k - M_k| + tv_weight TV(D)

starting from the masks' visual hull (raw 0 inside object k's hull, -6 outside).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F

from mosiv_framework.interfaces import RenderOutput
from mosiv_framework.scene.cameras import Camera
from mosiv_nerf.hull import carve
from mosiv_nerf.volume import GridBox, RayImage, march, trilinear

log = logging.getLogger(__name__)
Tensor = torch.Tensor

#: raw density outside the hull at the start: opacity 1 - exp(-softplus(-6)) = 0.25 % per voxel
EMPTY_RAW = -6.0


@dataclass
class VoxelField:
    """Per-object density grids ``density`` [K, Nz, Ny, Nx] (raw) and a colour grid ``color``
    [3, Nz, Ny, Nx] (raw) on ``box``; ``object_ids`` [K] names the object of each channel."""

    box: GridBox
    density: Tensor
    color: Tensor
    object_ids: list[int]

    @property
    def n_objects(self) -> int:
        return len(self.object_ids)

    def sample(self, points: Tensor) -> tuple[Tensor, Tensor]:
        """(sigma [K, ...] in 1/m, rgb [..., 3]) at ``points`` [..., 3]."""
        raw = trilinear(torch.cat([self.density, self.color]), self.box, points)
        sigma = F.softplus(raw[: self.n_objects]) / self.box.cell
        rgb = torch.sigmoid(raw[self.n_objects :]).movedim(0, -1)
        return sigma, rgb

    def state(self) -> dict:
        """Plain tensors and numbers (what a Reconstruction stores in ``extras``)."""
        return {
            "lo": self.box.lo.detach().cpu(),
            "cell": self.box.cell,
            "shape": list(self.box.shape),
            "density": self.density.detach().cpu(),
            "color": self.color.detach().cpu(),
            "object_ids": list(self.object_ids),
        }

    @classmethod
    def from_state(cls, state: dict, device=None) -> VoxelField:
        box = GridBox(state["lo"].to(device), float(state["cell"]), tuple(state["shape"]))
        return cls(
            box,
            state["density"].to(device),
            state["color"].to(device),
            [int(k) for k in state["object_ids"]],
        )


def hull_field(
    box: GridBox, cameras: list[Camera], mask_ids: Tensor, object_ids: list[int]
) -> VoxelField:
    """A field on ``box`` seeded from the visual hull of frame-0 masks ``mask_ids`` [C, H, W]:
    raw density 0 inside object k's hull, EMPTY_RAW elsewhere; grey colour."""
    nodes = box.nodes()  # [Nz, Ny, Nx, 3]
    labels = carve(nodes.reshape(-1, 3), cameras, mask_ids).reshape(nodes.shape[:3])
    density = torch.full((len(object_ids), *nodes.shape[:3]), EMPTY_RAW, device=box.lo.device)
    for i, k in enumerate(object_ids):
        density[i][labels == k] = 0.0
    color = torch.zeros(3, *nodes.shape[:3], device=box.lo.device)
    return VoxelField(box, density, color, list(object_ids))


def render_rays(
    field_sampler,
    box: GridBox,
    origins: Tensor,
    dirs: Tensor,
    *,
    n_objects: int,
    step: float,
    generator=None,
    max_samples: int = 1024,
    chunk: int = 16384,
) -> RayImage:
    """``march`` in chunks of ``chunk`` rays (bounds memory of full-image renders)."""
    parts = [
        march(
            field_sampler,
            box,
            origins[i : i + chunk],
            dirs[i : i + chunk],
            n_objects=n_objects,
            step=step,
            generator=generator,
            max_samples=max_samples,
        )
        for i in range(0, origins.shape[0], chunk)
    ]
    return RayImage(
        *(
            torch.cat([getattr(p, f) for p in parts], dim=-1 if f == "object_alpha" else 0)
            for f in ("rgb", "alpha", "depth", "object_alpha")
        )
    )


def render_image(
    sampler,
    box: GridBox,
    camera: Camera,
    *,
    n_objects: int,
    step: float,
    background: Tensor | None = None,
    max_samples: int = 1024,
) -> RenderOutput:
    """One camera's full image of a field (``sampler``) on ``box``: a RenderOutput whose rgb is
    composited over ``background`` [H, W, 3] when given; depth along the optical axis."""
    device = box.lo.device
    origins, dirs = camera.rays(device=device)
    h, w = camera.height, camera.width
    out = render_rays(
        sampler,
        box,
        origins.reshape(-1, 3),
        dirs.reshape(-1, 3),
        n_objects=n_objects,
        step=step,
        max_samples=max_samples,
    )
    axis = camera.rotation[2].to(dirs)  # optical axis in world coordinates
    depth = out.depth * (dirs.reshape(-1, 3) @ axis)
    rgb = out.rgb.reshape(h, w, 3)
    alpha = out.alpha.reshape(h, w)
    if background is not None:
        rgb = rgb + (1.0 - alpha)[..., None] * background.to(rgb)
    return RenderOutput(rgb, alpha, depth.reshape(h, w), out.object_alpha.reshape(-1, h, w))


@dataclass
class FitData:
    """Frame-0 rays that cross the field's box: origins, dirs [R, 3], recorded rgb [R, 3],
    masks [K, R] and background [R, 3]."""

    origins: Tensor
    dirs: Tensor
    rgb: Tensor
    masks: Tensor
    background: Tensor


def fit_data(scene, box: GridBox, backgrounds: dict[str, Tensor], object_ids: list[int]):
    """The frame-0 rays of every camera (that recorded frame 0) that cross ``box``."""
    from mosiv_nerf.hull import frame_views
    from mosiv_nerf.volume import ray_box

    device = box.lo.device
    parts = []
    for cam, cam_ids in zip(*frame_views(scene, 0)):
        o, d = cam.rays(device=device)
        o, d = o.reshape(-1, 3), d.reshape(-1, 3)
        rgb = torch.from_numpy(scene.rgb(cam.id, 0)).float().reshape(-1, 3).to(device) / 255.0
        masks = torch.stack([(cam_ids == k).reshape(-1) for k in object_ids]).float().to(device)
        bg = backgrounds[cam.id].reshape(-1, 3).to(device)
        keep = ray_box(o, d, box.lo, box.hi)[2]
        parts.append((o[keep], d[keep], rgb[keep], masks[:, keep], bg[keep]))
    cat = [torch.cat([p[i] for p in parts], dim=-1 if i == 3 else 0) for i in range(5)]
    return FitData(*cat)


def total_variation(grid: Tensor) -> Tensor:
    """Mean squared difference of neighbouring voxels of ``grid`` [C, Nz, Ny, Nx]."""
    return sum(grid.diff(dim=d).square().mean() for d in (1, 2, 3))


def fit_field(field: VoxelField, data: FitData, options, generator: torch.Generator) -> list:
    """Optimise ``field`` in place on ``data`` (NerfFieldOptions); returns the loss history."""
    field.density.requires_grad_(True)
    field.color.requires_grad_(True)
    opt = torch.optim.Adam([field.density, field.color], lr=options.lr)
    step = options.step_ratio * field.box.cell
    history = []
    n = data.origins.shape[0]
    for it in range(options.iterations):
        pick = torch.randint(
            n, (min(options.rays_per_step, n),), generator=generator, device=generator.device
        ).to(data.origins.device)
        out = march(
            field.sample,
            field.box,
            data.origins[pick],
            data.dirs[pick],
            n_objects=field.n_objects,
            step=step,
            generator=generator,
        )
        pred = out.rgb + (1.0 - out.alpha)[:, None] * data.background[pick]
        loss = (pred - data.rgb[pick]).square().mean()
        if options.mask_weight > 0:
            mask_l1 = (out.object_alpha - data.masks[:, pick]).abs().mean(dim=1).sum()
            loss = loss + options.mask_weight * mask_l1
        if options.tv_weight > 0:
            loss = loss + options.tv_weight * total_variation(field.density)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        # cosine decay to a tenth of the rate: late steps polish instead of oscillating
        for group in opt.param_groups:
            group["lr"] = options.lr * (
                0.55 + 0.45 * math.cos(math.pi * (it + 1) / options.iterations)
            )
        history.append(float(loss.detach()))
    field.density.requires_grad_(False)
    field.color.requires_grad_(False)
    return history
