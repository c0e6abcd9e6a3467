"""Renderer of generated scenes: object surfaces, a checkered table and a background.

Independent of the reconstruction's Gaussian model. Per view:
1. the object meshes (``surface.particle_surface``) are rasterised with a vectorised z-buffer:
   every triangle covers the pixel centres inside its screen bounding box, barycentric
   coordinates from 2D edge functions decide coverage, depth and normals are interpolated
   perspective-correctly (1/z is affine in screen space);
2. each pixel ray is intersected with the table square (plane z = ground height); what is
   neither object nor table shows the background, a vertical gradient;
3. the nearest hit is shaded Lambertian, c = albedo (ambient + (1 - ambient) max(0, n.l)),
   and encoded to 8-bit sRGB. The instance mask is the object id of the same nearest hit.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from mosiv_framework.scene.cameras import Camera
from mosiv_synth.surface import Surface

# linear-RGB albedo of each shape: one realistic colour per object (paper, section 4.1)
OBJECT_COLORS: dict[str, tuple[float, float, float]] = {
    "egg": (0.78, 0.62, 0.45),
    "pawn": (0.06, 0.06, 0.07),
    "apple": (0.55, 0.04, 0.03),
    "bread": (0.6, 0.33, 0.1),
    "cream": (0.85, 0.82, 0.72),
    "barrel": (0.32, 0.16, 0.06),
    "potato": (0.55, 0.4, 0.2),
    "cushion": (0.12, 0.2, 0.55),
    "banana": (0.8, 0.62, 0.05),
    "mushroom": (0.62, 0.5, 0.38),
}
# table textures: pairs of checker colours (linear RGB) -- wood, slate, linen, green cloth
TABLE_STYLES = (
    ((0.38, 0.2, 0.08), (0.28, 0.14, 0.05)),
    ((0.16, 0.17, 0.18), (0.09, 0.1, 0.11)),
    ((0.7, 0.66, 0.58), (0.55, 0.5, 0.43)),
    ((0.05, 0.22, 0.08), (0.03, 0.15, 0.05)),
    ((0.45, 0.45, 0.45), (0.3, 0.3, 0.3)),
)
# backgrounds: (colour at the horizon, colour overhead), linear RGB
BACKGROUND_STYLES = (
    ((0.55, 0.6, 0.7), (0.2, 0.3, 0.5)),
    ((0.6, 0.55, 0.45), (0.35, 0.3, 0.25)),
    ((0.4, 0.4, 0.42), (0.15, 0.15, 0.17)),
    ((0.5, 0.62, 0.5), (0.2, 0.3, 0.22)),
)
AMBIENT = 0.3


@dataclass
class Style:
    """Appearance of one scene: object albedos (object id -> linear RGB), table checker colours,
    tile size (m), table half-size (m), background gradient, unit light direction (towards the
    light), ground height (m)."""

    object_colors: dict[int, tuple[float, float, float]]
    table_colors: tuple[tuple[float, float, float], tuple[float, float, float]]
    tile: float
    table_half_size: float
    background: tuple[tuple[float, float, float], tuple[float, float, float]]
    light: tuple[float, float, float]
    ground_height: float | None = 0.0


def draw_style(
    shape_names: list[str], rng: np.random.Generator, *, ground_height: float | None = 0.0
) -> Style:
    """A random style: each object's realistic colour jittered by +-8 %, random table and
    background, light from above at a random azimuth."""
    colors = {
        k: tuple(
            float(c) for c in np.clip(np.array(OBJECT_COLORS[n]) * rng.uniform(0.92, 1.08), 0, 1)
        )
        for k, n in enumerate(shape_names, start=1)
    }
    az, el = rng.uniform(0.0, 2.0 * np.pi), np.radians(rng.uniform(45.0, 70.0))
    light = (np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el))
    return Style(
        object_colors=colors,
        table_colors=TABLE_STYLES[rng.integers(len(TABLE_STYLES))],
        tile=float(rng.choice([0.05, 0.075, 0.1])),
        table_half_size=0.6,
        background=BACKGROUND_STYLES[rng.integers(len(BACKGROUND_STYLES))],
        light=tuple(float(x) for x in light),
        ground_height=ground_height,
    )


@dataclass
class Fragments:
    """Per-pixel result of rasterisation: depth [H, W] (m along the optical axis, inf where
    empty), face index [H, W] (-1 where empty) and perspective-correct barycentrics [H, W, 3]."""

    depth: torch.Tensor
    face: torch.Tensor
    bary: torch.Tensor


def rasterize(
    camera: Camera, vertices: torch.Tensor, faces: torch.Tensor, *, near: float = 1e-3
) -> Fragments:
    """Z-buffer rasterisation of triangles (vertices [V, 3] world m, faces [F, 3]) at pixel
    centres; triangles with a vertex closer than ``near`` (m) are skipped."""
    h, w = camera.height, camera.width
    depth = torch.full((h * w,), float("inf"), dtype=torch.float64)
    face_of = torch.full((h * w,), -1, dtype=torch.long)
    bary = torch.zeros((h * w, 3), dtype=torch.float64)
    if faces.shape[0] > 0:
        _fill(camera, vertices.to(torch.float64), faces, near, depth, face_of, bary)
    return Fragments(depth.view(h, w), face_of.view(h, w), bary.view(h, w, 3))


def _fill(camera, vertices, faces, near, depth, face_of, bary) -> None:
    h, w = camera.height, camera.width
    pc = camera.world_to_camera_points(vertices)
    z = pc[:, 2]
    u = camera.fx * pc[:, 0] / z + camera.cx
    v = camera.fy * pc[:, 1] / z + camera.cy
    tz, tu, tv = z[faces], u[faces], v[faces]  # [F, 3]
    # pixel (i, j) has its centre at (i + 0.5, j + 0.5): the columns whose centre the triangle's
    # u-range covers are ceil(umin - 0.5) .. floor(umax - 0.5)
    i0 = torch.ceil(tu.min(1).values - 0.5).clamp(min=0)
    i1 = torch.floor(tu.max(1).values - 0.5).clamp(max=w - 1)
    j0 = torch.ceil(tv.min(1).values - 0.5).clamp(min=0)
    j1 = torch.floor(tv.max(1).values - 0.5).clamp(max=h - 1)
    nx, ny = (i1 - i0 + 1).clamp(min=0), (j1 - j0 + 1).clamp(min=0)
    keep = (tz > near).all(1) & (nx * ny > 0)
    idx = torch.nonzero(keep).squeeze(1)
    if idx.numel() == 0:
        return
    nx, ny = nx[idx].long(), ny[idx].long()
    count = nx * ny
    fid = torch.repeat_interleave(idx, count)  # one fragment per covered bounding-box pixel
    local = torch.arange(int(count.sum())) - torch.repeat_interleave(count.cumsum(0) - count, count)
    slot = torch.repeat_interleave(torch.arange(idx.numel()), count)
    px = i0[idx].long()[slot] + local % nx[slot]
    py = j0[idx].long()[slot] + local // nx[slot]
    pu, pv = px.to(torch.float64) + 0.5, py.to(torch.float64) + 0.5
    au, av = tu[fid], tv[fid]  # [n, 3]
    # 2D edge functions: w_a ~ area of (p, b, c), normalised by the triangle's signed area
    area = (au[:, 1] - au[:, 0]) * (av[:, 2] - av[:, 0]) - (av[:, 1] - av[:, 0]) * (
        au[:, 2] - au[:, 0]
    )

    def edge(i: int, j: int) -> torch.Tensor:
        return (au[:, j] - au[:, i]) * (pv - av[:, i]) - (av[:, j] - av[:, i]) * (pu - au[:, i])

    safe = torch.where(area.abs() > 1e-12, area, torch.ones_like(area))
    b = torch.stack([edge(1, 2), edge(2, 0), edge(0, 1)], dim=1) / safe[:, None]
    inside = (area.abs() > 1e-12) & (b >= -1e-9).all(1)
    b, fid, px, py = b[inside], fid[inside], px[inside], py[inside]
    inv_z = (b / tz[fid]).sum(1)  # 1/z is affine in screen space
    frag_depth = 1.0 / inv_z
    key = py * w + px
    depth.scatter_reduce_(0, key, frag_depth, reduce="amin")
    win = frag_depth <= depth[key]
    order = torch.arange(key.numel())
    winner = torch.full_like(face_of, -1).scatter_reduce_(0, key[win], order[win], reduce="amax")
    hit = winner >= 0
    face_of[hit] = fid[winner[hit]]
    bary[hit] = (b[winner[hit]] / tz[fid[winner[hit]]]) / inv_z[winner[hit], None]


def _srgb(linear: torch.Tensor) -> np.ndarray:
    """Linear [0, 1] -> 8-bit sRGB (IEC 61966-2-1 transfer function)."""
    x = np.clip(linear.numpy(), 0.0, 1.0)
    s = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1.0 / 2.4) - 0.055)
    return (s * 255.0 + 0.5).astype(np.uint8)


@dataclass
class Backdrop:
    """What a camera sees without objects, fixed over a clip: pixel rays (origins, unit
    directions [H, W, 3]), linear colour [H, W, 3] and table depth [H, W] (inf off the table)."""

    origins: torch.Tensor
    dirs: torch.Tensor
    color: torch.Tensor
    table_depth: torch.Tensor


def backdrop(camera: Camera, style: Style) -> Backdrop:
    """Table and background of one camera; compute once per camera and reuse for every frame."""
    origins, dirs = camera.rays(dtype=torch.float64)
    light = torch.tensor(style.light, dtype=torch.float64)
    color, depth = _environment(camera, origins, dirs, style, light)
    return Backdrop(origins, dirs, color, depth)


def render_view(
    camera: Camera, surfaces: dict[int, Surface], style: Style, *, back: Backdrop | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """One view of the object ``surfaces`` (object id -> Surface) on the styled table:
    (rgb uint8 [H, W, 3], instance mask uint8 [H, W], 0 = background/table, k = object k).
    ``back`` is this camera's ``backdrop`` (computed here when not given)."""
    back = backdrop(camera, style) if back is None else back
    verts, faces, normals, face_obj = _concat(surfaces)
    frags = rasterize(camera, verts, faces)
    color = back.color.clone()
    obj = (frags.face >= 0) & (frags.depth < back.table_depth)
    mask = torch.zeros(frags.face.shape, dtype=torch.uint8)
    if obj.any():
        light = torch.tensor(style.light, dtype=torch.float64)
        f = frags.face[obj]
        n = (normals[faces[f]] * frags.bary[obj][..., None]).sum(1)
        n = n / n.norm(dim=-1, keepdim=True).clamp(min=1e-12)
        n = torch.where(((n * back.dirs[obj]).sum(-1) > 0)[:, None], -n, n)  # face the viewer
        ids = face_obj[f]
        palette = torch.zeros((int(ids.max()) + 1, 3), dtype=torch.float64)
        for k, c in style.object_colors.items():
            if k < palette.shape[0]:
                palette[k] = torch.tensor(c, dtype=torch.float64)
        shade = AMBIENT + (1.0 - AMBIENT) * (n @ light).clamp(min=0.0)
        color[obj] = palette[ids] * shade[:, None]
        mask[obj] = ids.to(torch.uint8)
    return _srgb(color), mask.numpy()


def _concat(surfaces: dict[int, Surface]):
    verts, faces, normals, owner, offset = [], [], [], [], 0
    for k in sorted(surfaces):
        s = surfaces[k]
        verts.append(torch.as_tensor(s.vertices, dtype=torch.float64))
        normals.append(torch.as_tensor(s.normals, dtype=torch.float64))
        faces.append(torch.as_tensor(s.faces, dtype=torch.long) + offset)
        owner.append(torch.full((len(s.faces),), k, dtype=torch.long))
        offset += len(s.vertices)
    if not verts:
        empty = torch.zeros((0, 3), dtype=torch.float64)
        return empty, torch.zeros((0, 3), dtype=torch.long), empty, torch.zeros(0, dtype=torch.long)
    return torch.cat(verts), torch.cat(faces), torch.cat(normals), torch.cat(owner)


def _environment(camera, origins, dirs, style: Style, light):
    """Colour [H, W, 3] (linear) of table and background, and the table's depth [H, W] (m along
    the optical axis; inf where a ray misses the table)."""
    up = dirs[..., 2].clamp(0.0, 1.0)[..., None]
    horizon, overhead = (torch.tensor(c, dtype=torch.float64) for c in style.background)
    color = horizon + (overhead - horizon) * up.sqrt()
    depth = torch.full(dirs.shape[:2], float("inf"), dtype=torch.float64)
    if style.ground_height is None:
        return color, depth
    # ray-plane: o_z + t d_z = height, hit from above only
    t = (style.ground_height - origins[..., 2]) / dirs[..., 2].clamp(max=-1e-12)
    hit_pt = origins + t[..., None] * dirs
    on_table = (
        (dirs[..., 2] < 0) & (t > 0) & (hit_pt[..., :2].abs() <= style.table_half_size).all(-1)
    )
    cell = torch.floor(hit_pt[..., 0] / style.tile) + torch.floor(hit_pt[..., 1] / style.tile)
    odd = (cell.remainder(2) == 1)[..., None]
    c0, c1 = (torch.tensor(c, dtype=torch.float64) for c in style.table_colors)
    table = torch.where(odd, c1, c0) * (AMBIENT + (1.0 - AMBIENT) * light[2].clamp(min=0.0))
    color = torch.where(on_table[..., None], table, color)
    forward = camera.rotation[2].to(torch.float64)  # optical axis in world coordinates
    depth = torch.where(on_table, t * (dirs @ forward), depth)
    return color, depth
