"""A small, genuine ``mosiv-scene/1`` scene for tests and plugin authors.

Two spheres fly on analytic ballistic paths x(t) = x0 + v0 t + g t^2 / 2 (rigid, no contact; the
lanes never cross) above a grey square table (the ground plane over the domain's footprint) and a darker grey
background. Every camera image is ray-traced exactly: each
pixel-centre ray is intersected with the spheres and the plane, the nearest hit is shaded
Lambertian (ambient + diffuse) and encoded to 8-bit sRGB; the instance mask comes from the same
hit. gt/points.npz holds points sampled uniformly inside each sphere, carried along its path.
The gt parameters are labels only: the motion is free flight, so no material law acts.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch

from mosiv_framework.scene.cameras import Camera
from mosiv_framework.scene.io import SceneObject, SceneWriter

DOMAIN_LOWER = (-0.5, -0.5, 0.0)
DOMAIN_UPPER = (0.5, 0.5, 1.0)
GRAVITY = (0.0, 0.0, -9.8)
GROUND_HEIGHT = 0.0
# Longest clip (s) whose arcs stay inside the 1 m box: apex rise |g| T^2 / 8 stays below 0.31 m.
MAX_DURATION_S = 0.5
POINTS_PER_OBJECT = 256

_LIGHT = np.array([0.3, -0.4, 1.0]) / np.linalg.norm([0.3, -0.4, 1.0])
_AMBIENT = 0.25
_GROUND_ALBEDO = (0.5, 0.5, 0.5)
_BACKGROUND = (0.2, 0.2, 0.2)

# (name, material, radius m, lane x m, start y m, direction of travel along y, linear albedo, gt)
_SPHERES = (
    (
        "red_ball",
        "elastic",
        0.12,
        -0.2,
        -0.15,
        1.0,
        (0.8, 0.15, 0.1),
        {"E": 5.0e4, "nu": 0.3, "rho": 1000.0, "friction": 0.3},
    ),
    (
        "blue_clay",
        "plasticine",
        0.09,
        0.2,
        0.15,
        -1.0,
        (0.1, 0.25, 0.8),
        {"E": 2.0e5, "nu": 0.35, "yield_stress": 5.0e3, "rho": 1500.0, "friction": 0.5},
    ),
)


def _srgb_encode(linear: torch.Tensor) -> torch.Tensor:
    """Linear [0, 1] -> sRGB transfer function (IEC 61966-2-1)."""
    linear = linear.clamp(0.0, 1.0)
    return torch.where(linear <= 0.0031308, 12.92 * linear, 1.055 * linear.pow(1.0 / 2.4) - 0.055)


def _render(
    o: torch.Tensor,
    d: torch.Tensor,
    centres: torch.Tensor,
    radii: torch.Tensor,
    albedos: torch.Tensor,
) -> tuple[np.ndarray, np.ndarray]:
    """Ray-trace one view from pixel rays (origins ``o``, unit directions ``d``, [H, W, 3]):
    uint8 sRGB [H, W, 3] and uint8 instance mask [H, W] (0 = no object)."""
    # ray-sphere: |o + t d - c|^2 = r^2  ->  t = -b - sqrt(b^2 - (|o - c|^2 - r^2)), b = d.(o - c)
    oc = o[:, :, None, :] - centres  # [H, W, K, 3]
    b = (d[:, :, None, :] * oc).sum(-1)
    disc = b * b - ((oc * oc).sum(-1) - radii**2)
    t_sphere = -b - disc.clamp(min=0.0).sqrt()
    t_sphere = torch.where((disc > 0) & (t_sphere > 0), t_sphere, torch.inf)
    # ray-plane z = h for rays going down, kept where the hit lies on the table (the domain's
    # footprint), so the background shows beyond its edges
    dz = d[..., 2]
    t_ground = (GROUND_HEIGHT - o[..., 2]) / dz.clamp(max=-1e-12)
    xy = o[..., :2] + t_ground[..., None] * d[..., :2]
    on_table = (xy >= xy.new_tensor(DOMAIN_LOWER[:2])).all(-1) & (
        xy <= xy.new_tensor(DOMAIN_UPPER[:2])
    ).all(-1)
    t_ground = torch.where((dz < 0) & on_table, t_ground, torch.inf)
    t_all = torch.cat([t_sphere, t_ground[..., None]], dim=-1)  # [H, W, K + 1]
    t_hit, which = t_all.min(dim=-1)
    k = centres.shape[0]
    hit_sphere = torch.isfinite(t_hit) & (which < k)
    hit_ground = torch.isfinite(t_hit) & (which == k)

    point = o + t_hit.clamp(max=1e6)[..., None] * d
    sphere_idx = which.clamp(max=k - 1)
    normal = (point - centres[sphere_idx]) / radii[sphere_idx][..., None]
    normal = torch.where(hit_ground[..., None], torch.tensor([0.0, 0.0, 1.0]).to(normal), normal)
    # Lambert: radiance = albedo (ambient + (1 - ambient) max(0, n.l))
    lambert = _AMBIENT + (1.0 - _AMBIENT) * (normal @ torch.as_tensor(_LIGHT)).clamp(min=0.0)
    albedo = torch.where(
        hit_sphere[..., None],
        albedos[sphere_idx],
        torch.tensor(_GROUND_ALBEDO, dtype=torch.float64),
    )
    colour = albedo * lambert[..., None]
    background = torch.tensor(_BACKGROUND, dtype=torch.float64)
    colour = torch.where((hit_sphere | hit_ground)[..., None], colour, background)
    rgb = (_srgb_encode(colour) * 255.0).round().to(torch.uint8).numpy()
    mask = torch.where(hit_sphere, which + 1, 0).to(torch.uint8).numpy()
    return rgb, mask


def example_cameras(*, n_cameras: int, size: int) -> list[Camera]:
    """``n_cameras`` views evenly spaced in azimuth at 30 degrees elevation, 1.6 m from the
    domain centre, all looking at it with a 40 degree field of view."""
    centre = np.add(DOMAIN_LOWER, DOMAIN_UPPER) / 2.0
    elevation, distance = math.radians(30.0), 1.6
    cameras = []
    for i in range(n_cameras):
        azimuth = 2.0 * math.pi * i / n_cameras + math.pi / 4.0
        offset = distance * np.array(
            [
                math.cos(elevation) * math.cos(azimuth),
                math.cos(elevation) * math.sin(azimuth),
                math.sin(elevation),
            ]
        )
        cameras.append(
            Camera.look_at(
                centre + offset, centre, id=f"cam_{i:02d}", width=size, height=size, fov_deg=40.0
            )
        )
    return cameras


def write_example_scene(
    out_dir: str | Path, *, n_frames: int = 4, n_cameras: int = 4, size: int = 32, seed: int = 0
) -> Path:
    """Write the two-sphere example scene into ``out_dir`` (must be absent or empty).

    ``fps`` is 24 unless the clip would last longer than MAX_DURATION_S, in which case it rises
    so the clip spans exactly that long (the arcs must stay inside the domain). ``seed`` varies
    start positions and throw velocities.
    """
    if n_frames < 1 or n_cameras < 1 or size < 1:
        raise ValueError(
            f"n_frames, n_cameras and size must be >= 1, got {n_frames}, {n_cameras}, {size}"
        )
    out = Path(out_dir)
    if out.exists() and any(out.iterdir()):
        raise FileExistsError(f"{out} is not empty; write the example scene into a new folder")
    rng = np.random.default_rng(seed)
    fps = 24.0 if (n_frames - 1) / 24.0 <= MAX_DURATION_S else (n_frames - 1) / MAX_DURATION_S
    times = np.arange(n_frames) / fps
    duration = max(times[-1], 1.0 / fps)
    g = np.asarray(GRAVITY)

    objects, radii, albedos, paths, v0s, gt_objects, gt_points = [], [], [], [], [], [], {}
    for k, (name, material, radius, lane_x, y0, direction, albedo, params) in enumerate(
        _SPHERES, start=1
    ):
        x0 = np.array([lane_x + rng.uniform(-0.02, 0.02), y0, 0.35])
        # vertical throw: a fraction u of the speed that would return to the start height at T
        vz = 0.5 * abs(g[2]) * duration * rng.uniform(0.85, 1.0)
        v0 = np.array([0.0, direction * rng.uniform(0.2, 0.4), vz])
        path = x0 + v0 * times[:, None] + 0.5 * g * times[:, None] ** 2  # [T, 3]
        lo, hi = path.min(0) - radius, path.max(0) + radius
        if np.any(lo < DOMAIN_LOWER) or np.any(hi > DOMAIN_UPPER) or lo[2] < GROUND_HEIGHT:
            raise AssertionError(f"example sphere {name} leaves the domain: {lo}..{hi}")
        # uniform in the ball: isotropic direction, radius r u^(1/3)
        dirs = rng.normal(size=(POINTS_PER_OBJECT, 3))
        dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
        local = dirs * radius * rng.uniform(size=(POINTS_PER_OBJECT, 1)) ** (1.0 / 3.0)
        gt_points[k] = (path[:, None, :] + local[None]).astype(np.float32)
        objects.append(SceneObject(k, name, material))
        radii.append(radius)
        albedos.append(albedo)
        paths.append(path)
        v0s.append(v0)
        gt_objects.append(
            {"id": k, "material": material, "params": params, "initial_velocity": v0.tolist()}
        )

    cameras = example_cameras(n_cameras=n_cameras, size=size)
    writer = SceneWriter(
        out,
        name=f"example-two-spheres-{seed:04d}",
        fps=fps,
        n_frames=n_frames,
        observed_frames=(n_frames + 1) // 2,
        objects=objects,
        cameras=cameras,
        domain_lower=DOMAIN_LOWER,
        domain_upper=DOMAIN_UPPER,
        gravity=GRAVITY,
        ground_height=GROUND_HEIGHT,
    )
    centres_t = torch.as_tensor(np.stack(paths, axis=1))  # [T, K, 3]
    radii_t = torch.tensor(radii, dtype=torch.float64)
    albedos_t = torch.tensor(albedos, dtype=torch.float64)
    for cam in cameras:
        origins, directions = cam.rays(dtype=torch.float64)
        for t in range(n_frames):
            rgb, mask = _render(origins, directions, centres_t[t], radii_t, albedos_t)
            writer.write_frame(cam.id, t, rgb=rgb, mask=mask)
    writer.write_gt(
        points=gt_points,
        params={
            "generator": "mosiv_framework.scene.example (analytic ballistic spheres)",
            "objects": gt_objects,
        },
    )
    return writer.finish()
