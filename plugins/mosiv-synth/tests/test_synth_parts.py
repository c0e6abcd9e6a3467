"""Unit tests of the generator's parts that need no simulator: shapes, particles, materials,
layout, cameras, surface extraction, renderer, concealment specs and options."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from mosiv_synth.layout import first_contact_distance, plan_collision
from mosiv_synth.materials import MATERIAL_RANGES, sample_params
from mosiv_synth.options import SynthOptions
from mosiv_synth.render import Style, rasterize, render_view
from mosiv_synth.sampling import random_rotation, sample_inside
from mosiv_synth.shapes import SHAPE_NAMES, SIZE_LIMITS, make_shape
from mosiv_synth.surface import Surface, particle_surface

from mosiv_framework.conceal import parse_conceal
from mosiv_framework.errors import ConfigError
from mosiv_framework.laws import get_law
from mosiv_framework.scene.cameras import Camera
from mosiv_framework.scene.protocol import (
    ELEVATION_MAX,
    ELEVATION_MIN,
    LOOK_AT,
    hemisphere_cameras,
)


def _ball(radius: float, spacing: float, centre=(0.0, 0.0, 0.0)) -> np.ndarray:
    import trimesh

    mesh = trimesh.creation.icosphere(subdivisions=4, radius=radius)
    return sample_inside(mesh, spacing) + np.asarray(centre)


def _winding_number(points: np.ndarray, mesh) -> np.ndarray:
    """Sum of signed solid angles of the triangles / 4 pi (Van Oosterom & Strackee 1983)."""
    rel = mesh.vertices[mesh.faces][None] - points[:, None, None, :]  # [P, F, 3, 3]
    a, b, c = rel[..., 0, :], rel[..., 1, :], rel[..., 2, :]
    la, lb, lc = (np.linalg.norm(x, axis=-1) for x in (a, b, c))
    det = np.einsum("pfk,pfk->pf", a, np.cross(b, c))
    dot = lambda x, y: np.einsum("pfk,pfk->pf", x, y)  # noqa: E731
    den = la * lb * lc + dot(a, b) * lc + dot(b, c) * la + dot(c, a) * lb
    return (2.0 * np.arctan2(det, den)).sum(-1) / (4.0 * np.pi)


# --------------------------------------------------------------------------------- shapes
@pytest.mark.parametrize("name", SHAPE_NAMES)
def test_shape_is_watertight_centred_and_sized(name):
    rng = np.random.default_rng(1)
    mesh = make_shape(name, rng)
    assert mesh.is_watertight and mesh.is_winding_consistent and mesh.volume > 0
    assert SIZE_LIMITS[0] - 1e-9 <= max(mesh.extents) <= SIZE_LIMITS[1] + 1e-9
    assert np.allclose(mesh.center_mass, 0.0, atol=1e-9)


def test_unknown_shape_lists_valid_names():
    with pytest.raises(ValueError, match="valid shapes: egg"):
        make_shape("teapot", np.random.default_rng(0))


# ------------------------------------------------------------------------------ particles
@pytest.mark.parametrize("name", ["pawn", "banana", "cushion", "mushroom"])
def test_particles_inside_mesh_and_volume_matches(name):
    rng = np.random.default_rng(2)
    mesh = make_shape(name, rng)
    mesh.vertices = mesh.vertices @ random_rotation(rng).T
    spacing = 0.004
    points = sample_inside(mesh, spacing, offset=rng.uniform(0, 1, 3))
    # independent inside test: the generalised winding number is ~1 inside, ~0 outside
    wn = _winding_number(points[rng.choice(len(points), 200, replace=False)], mesh)
    assert np.all(wn > 0.5)
    outside = mesh.bounds[1] + spacing  # a point beyond the bounding box
    assert _winding_number(outside[None], mesh)[0] < 0.5
    # lattice volume converges to the mesh volume: error ~ surface area * spacing / 2 at most
    assert abs(len(points) * spacing**3 - mesh.volume) / mesh.volume < 0.05


def test_rotation_is_proper_orthogonal():
    r = random_rotation(np.random.default_rng(3))
    assert np.allclose(r @ r.T, np.eye(3), atol=1e-12) and np.isclose(np.linalg.det(r), 1.0)


# ------------------------------------------------------------------------------ materials
@pytest.mark.parametrize("family", list(MATERIAL_RANGES))
def test_sampled_parameters_within_law_bounds(family):
    law = get_law(family)
    rng = np.random.default_rng(4)
    for _ in range(50):
        values = sample_params(family, rng)
        assert set(values) == set(law.param_names())
        for spec in law.all_params:
            assert spec.lower <= values[spec.name] <= spec.upper
            lo, hi, _ = MATERIAL_RANGES[family][spec.name]
            assert lo <= values[spec.name] <= hi


def test_paper_ranges_for_e_nu_rho():
    for family, ranges in MATERIAL_RANGES.items():
        if "E" in ranges:
            assert ranges["E"][:2] == (4.75e4, 5.25e4), family
            assert ranges["nu"][:2] == (0.2, 0.3), family
        assert ranges["rho"][:2] == (800.0, 1200.0), family


# --------------------------------------------------------------------------------- layout
def test_first_contact_distance_of_two_balls():
    # two balls of radius r approaching along x first come within c when their centres are
    # 2 r + c apart, up to the lattice's surface roughness (one spacing)
    r, s = 0.04, 0.004
    a, b = _ball(r, s), _ball(r, s)
    d = first_contact_distance(a, b, np.array([1.0, 0.0, 0.0]), s)
    outer = np.linalg.norm(a, axis=1).max()  # outermost particle centre
    assert 2 * outer < d <= 2 * outer + s + 1e-12


@pytest.mark.parametrize("k", [2, 3])
def test_layout_objects_touch_at_collision_time(k):
    rng = np.random.default_rng(5)
    spacing = 0.01
    clouds = []
    for name in ["apple", "banana", "pawn"][:k]:
        mesh = make_shape(name, rng)
        mesh.vertices = mesh.vertices @ random_rotation(rng).T
        pts = sample_inside(mesh, spacing)
        clouds.append(pts - pts.mean(axis=0))
    g = np.array([0.0, 0.0, -9.8])
    t_c = 6 / 24
    layout = plan_collision(
        clouds,
        collision_time=t_c,
        acceleration=g,
        contact=spacing,
        domain_lower=(-0.4, -0.4, 0.0),
        domain_upper=(0.4, 0.4, 0.6),
        ground_height=0.0,
        rng=rng,
    )
    # analytic ballistic centroids x0 + v0 t + g t^2 / 2 reach the planned targets at t_c
    c_tc = layout.starts + layout.velocities * t_c + 0.5 * g * t_c**2
    assert np.allclose(c_tc, layout.targets, atol=1e-12)

    def gap(t):
        c = layout.centroid_at(t, g)
        return np.linalg.norm((clouds[0] + c[0])[:, None] - (clouds[1] + c[1])[None], axis=-1).min()

    # objects 1 and 2 are exactly at contact distance at t_c and apart at every earlier time
    assert gap(t_c) == pytest.approx(spacing, abs=1e-9)
    for t in np.linspace(0.0, t_c, 12)[:-1]:
        assert gap(t) > spacing
    assert gap(t_c + 0.02) < spacing  # and they keep approaching: a real collision
    if k == 3:
        c = layout.centroid_at(t_c, g)
        pair = np.concatenate([clouds[0] + c[0], clouds[1] + c[1]])
        third = clouds[2] + c[2]
        assert np.linalg.norm(pair[:, None] - third[None], axis=-1).min() == pytest.approx(
            spacing, abs=1e-9
        )
    # centroids stay above the table until the collision
    for t in np.linspace(0.0, t_c, 10):
        assert np.all(layout.centroid_at(t, g)[:, 2] > 0.05)


# -------------------------------------------------------------------------------- cameras
def test_cameras_on_upper_hemisphere_looking_at_centre():
    cams = hemisphere_cameras(11, resolution=64)
    target = torch.tensor(LOOK_AT, dtype=torch.float64)
    centres = torch.stack([c.camera_center for c in cams])
    radius = (centres - target).norm(dim=1)
    assert torch.allclose(radius, radius[0].expand_as(radius), atol=1e-9)
    elevation = torch.asin((centres[:, 2] - target[2]) / radius)
    assert torch.all(elevation >= ELEVATION_MIN - 1e-9) and torch.all(
        elevation <= ELEVATION_MAX + 1e-9
    )
    for cam in cams:
        assert cam.is_rigid
        uv, z = cam.project(target[None])
        assert z[0] > 0 and torch.allclose(
            uv[0], torch.tensor([32.0, 32.0], dtype=uv.dtype), atol=1e-6
        )
    # evenly spread: nearest-neighbour distances differ by less than a factor 2
    d = (centres[:, None] - centres[None]).norm(dim=-1) + torch.eye(11) * 10
    nearest = d.min(dim=1).values
    assert nearest.max() / nearest.min() < 2.0


# ---------------------------------------------------------------------- surface + render
def _plain_style(ground: float | None = None) -> Style:
    return Style(
        object_colors={1: (0.8, 0.1, 0.1), 2: (0.1, 0.1, 0.8)},
        table_colors=((0.5, 0.5, 0.5), (0.3, 0.3, 0.3)),
        tile=0.05,
        table_half_size=0.6,
        background=((0.6, 0.6, 0.6), (0.2, 0.3, 0.5)),
        light=(0.0, 0.0, 1.0),
        ground_height=ground,
    )


def test_particle_surface_preserves_ball_radius():
    r, s = 0.05, 0.005
    surf = particle_surface(_ball(r, s), s)
    dist = np.linalg.norm(surf.vertices, axis=1)
    # iso-surface radius within a quarter spacing of the ball's
    assert abs(dist.mean() - r) < 0.25 * s and dist.std() < 0.25 * s


def test_sphere_silhouette_area_matches_pinhole_projection():
    # a ball of radius r at distance z on the optical axis subtends a cone of half-angle
    # asin(r/z): its image is a disc of radius f tan(asin(r/z)) = f r / sqrt(z^2 - r^2)
    r, s, z = 0.06, 0.005, 0.7
    surf = particle_surface(_ball(r, s, (0.0, 0.0, 0.3)), s)
    cam = Camera.look_at(
        (0.0, 0.0, 0.3 + z), (0.0, 0.0, 0.3), (0.0, 1.0, 0.0), width=128, height=128, fov_deg=30
    )
    rgb, mask = render_view(cam, {1: surf}, _plain_style())
    expected = math.pi * cam.fx**2 * r**2 / (z * z - r * r)
    assert (mask == 1).sum() == pytest.approx(expected, rel=0.03)
    # nothing but the ball and the empty background (no ground in this style)
    assert set(np.unique(mask)) == {0, 1}


def test_mask_agrees_with_rgb_foreground_and_depth_order():
    s = 0.005
    near = _ball(0.04, s, (0.0, 0.0, 0.35))
    far = _ball(0.05, s, (0.03, 0.0, 0.2))
    cam = Camera.look_at(
        (0.0, 0.0, 1.0), (0.0, 0.0, 0.2), (0.0, 1.0, 0.0), width=96, height=96, fov_deg=30
    )
    style = _plain_style(ground=0.0)
    rgb, mask = render_view(cam, {1: particle_surface(near, s), 2: particle_surface(far, s)}, style)
    empty, _ = render_view(cam, {}, style)
    # foreground in rgb (differs from the empty scene) is exactly where the mask is non-zero
    changed = np.any(rgb != empty, axis=-1)
    assert np.array_equal(changed, mask > 0)
    # the nearer ball (1) hides the far one where they overlap: centre pixel belongs to 1
    assert mask[48, 48] == 1 and (mask == 2).sum() > 0
    # object pixels carry the object's hue: red channel dominates for 1, blue for 2
    assert np.all(rgb[mask == 1][:, 0] > rgb[mask == 1][:, 2])
    assert np.all(rgb[mask == 2][:, 2] > rgb[mask == 2][:, 0])


def test_rasterizer_covers_a_square_exactly():
    # a square of side a at depth z facing the camera covers (f a / z)^2 pixel centres
    cam = Camera.look_at(
        (0.0, 0.0, 1.0), (0.0, 0.0, 0.0), (0.0, 1.0, 0.0), width=64, height=64, fx=64.0
    )
    a = 0.5
    v = torch.tensor(
        [[-a / 2, -a / 2, 0.0], [a / 2, -a / 2, 0.0], [a / 2, a / 2, 0.0], [-a / 2, a / 2, 0.0]]
    )
    f = torch.tensor([[0, 1, 2], [0, 2, 3]])
    frags = rasterize(cam, v, f)
    assert int((frags.face >= 0).sum()) == round((64.0 * a / 1.0) ** 2)
    assert torch.allclose(frags.depth[frags.face >= 0], torch.tensor(1.0, dtype=torch.float64))
    assert torch.allclose(
        frags.bary[frags.face >= 0].sum(-1), torch.tensor(1.0, dtype=torch.float64)
    )


def test_empty_surface_renders_environment_only():
    cam = hemisphere_cameras(1, resolution=32)[0]
    empty = Surface(np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64), np.zeros((0, 3)))
    rgb, mask = render_view(cam, {1: empty}, _plain_style(ground=0.0))
    assert rgb.shape == (32, 32, 3) and rgb.dtype == np.uint8 and not mask.any()


# ---------------------------------------------------------------------- conceal + options
def test_conceal_spec_parsing():
    effects = parse_conceal("quadratic_drag:coefficient=0.6;wind:acceleration=1.5,0,0")
    assert [e.kind for e in effects] == ["quadratic_drag", "wind"]
    assert effects[0].params == {"coefficient": 0.6}
    assert effects[1].params == {"acceleration": (1.5, 0.0, 0.0)}
    assert parse_conceal(["gravity"])[0].params["acceleration"] == (0.0, 0.0, -12.0)
    assert parse_conceal([e.spec() for e in effects]) == effects
    assert parse_conceal(None) == [] and parse_conceal("") == []
    for bad, msg in [
        ("fog", "valid kinds"),
        ("wind:acceleration=1,2", "3 numbers"),
        ("linear_drag:coef=1", "valid: coefficient"),
        ("linear_drag:coefficient=-1", ">= 0"),
        ("wind;wind", "more than once"),
    ]:
        with pytest.raises(ValueError, match=msg):
            parse_conceal(bad)


def test_options_validation_lists_every_problem():
    with pytest.raises(ConfigError) as err:
        SynthOptions(n_objects=4, shapes="egg,teapot", observed_frames=40, conceal="fog")
    text = str(err.value)
    for part in ["n_objects=4", "'teapot'", "observed_frames=40", "conceal"]:
        assert part in text
    opts = SynthOptions(shapes="egg, apple", materials=["sand", "snow"])
    assert opts.shapes == ["egg", "apple"] and opts.materials == ["sand", "snow"]


def test_plugin_registers_synth_without_heavy_imports():
    import subprocess
    import sys

    code = (
        "import sys, mosiv_synth.plugin as p;"
        "heavy = [m for m in ('trimesh', 'skimage', 'warp', 'taichi') if m in sys.modules];"
        "print(heavy)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"
    from mosiv_framework.registry import get_registry

    component = get_registry().get("scene_source", "synth")
    assert component.options is SynthOptions
