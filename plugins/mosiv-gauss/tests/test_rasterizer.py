"""The torch Gaussian rasterizer against an independent per-pixel loop, finite differences,
hand-computed renders, and its own memory bound."""

from __future__ import annotations

import math

import pytest
import torch
from mosiv_gauss.options import TorchRasterizerOptions
from mosiv_gauss.rasterizer import TorchRasterizer, rasterize

from mosiv_framework.scene.cameras import Camera
from mosiv_framework.types import GaussianFrames


def random_scene(g: int, k: int, *, seed: int, dtype=torch.float64, radius=(0.05, 0.15)):
    """``g`` Gaussians of ``k`` objects scattered around the origin (one frame)."""
    gen = torch.Generator().manual_seed(seed)
    means = (torch.rand(1, g, 3, generator=gen, dtype=dtype) - 0.5) * 0.8
    radii = radius[0] + (radius[1] - radius[0]) * torch.rand(1, g, generator=gen, dtype=dtype)
    colors = torch.rand(g, 3, generator=gen, dtype=dtype)
    opacities = 0.3 + 0.6 * torch.rand(g, generator=gen, dtype=dtype)
    object_ids = torch.arange(g) % k + 1  # every object present
    return GaussianFrames(means, radii, colors, opacities, object_ids)


def oblique_camera(width: int, height: int) -> Camera:
    # fx != fy so the two footprint axes are exercised separately
    return Camera.look_at(
        (0.6, -2.0, 0.9),
        (0.0, 0.0, 0.0),
        width=width,
        height=height,
        fx=1.1 * width,
        fy=0.9 * width,
    )


def brute_force(gauss: GaussianFrames, cam: Camera, k: int, opts: TorchRasterizerOptions):
    """Every pixel walks every Gaussian in depth order: plain Python floats, no tiling."""
    rot = cam.world_to_camera[:3, :3].tolist()
    trans = cam.world_to_camera[:3, 3].tolist()
    splats = []
    for g in range(gauss.means.shape[1]):
        x = gauss.means[0, g].tolist()
        xc = [sum(rot[i][j] * x[j] for j in range(3)) + trans[i] for i in range(3)]
        r = float(gauss.radii[0, g])
        if xc[2] < opts.near or r <= 0:
            continue
        splats.append(
            (
                xc[2],
                cam.fx * xc[0] / xc[2] + cam.cx,
                cam.fy * xc[1] / xc[2] + cam.cy,
                r * cam.fx / xc[2],
                r * cam.fy / xc[2],
                float(gauss.opacities[g]),
                gauss.colors[g].tolist(),
                int(gauss.object_ids[g]),
            )
        )
    splats.sort(key=lambda s: s[0])
    rgb = torch.zeros(cam.height, cam.width, 3, dtype=torch.float64)
    alpha = torch.zeros(cam.height, cam.width, dtype=torch.float64)
    depth = torch.zeros_like(alpha)
    obj = torch.zeros(k, cam.height, cam.width, dtype=torch.float64)
    for row in range(cam.height):
        for col in range(cam.width):
            pu, pv, transmit = col + 0.5, row + 0.5, 1.0
            for z, u, v, su, sv, o, c, oid in splats:
                q = ((pu - u) / su) ** 2 + ((pv - v) / sv) ** 2
                if q > opts.cutoff_sigma**2:
                    continue
                a = min(o * math.exp(-0.5 * q), opts.max_alpha)
                w = a * transmit
                for ch in range(3):
                    rgb[row, col, ch] += w * c[ch]
                alpha[row, col] += w
                depth[row, col] += w * z
                obj[oid - 1, row, col] += w
                transmit *= 1.0 - a
    return rgb, alpha, depth, obj


@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-10), (torch.float32, 1e-5)])
def test_matches_brute_force_per_pixel_loop(dtype, tol):
    k = 3
    gauss = random_scene(14, k, seed=1)
    cam = oblique_camera(20, 14)
    opts = TorchRasterizerOptions(tile_size=4, pixel_chunk=32, pair_chunk=64)
    expected = brute_force(gauss, cam, k, opts)
    cast = GaussianFrames(
        gauss.means.to(dtype),
        gauss.radii.to(dtype),
        gauss.colors.to(dtype),
        gauss.opacities.to(dtype),
        gauss.object_ids,
    )
    out, stats = rasterize(cast, cam, n_objects=k, options=opts)
    assert stats.n_visible > 8  # most Gaussians are on screen, so the comparison means something
    assert expected[1].max() > 0.5
    for got, want in zip((out.rgb, out.alpha, out.depth, out.object_alpha), expected):
        assert got.dtype == dtype
        assert got.shape == want.shape
        torch.testing.assert_close(got.double(), want, atol=tol, rtol=0)


def test_background_colour_is_composited_behind():
    gauss = random_scene(6, 2, seed=2)
    cam = oblique_camera(12, 10)
    bg = (0.2, 0.5, 0.9)
    plain = rasterize(gauss, cam, n_objects=2)[0]
    with_bg = rasterize(gauss, cam, n_objects=2, options=TorchRasterizerOptions(background=bg))[0]
    want = plain.rgb + (1 - plain.alpha).unsqueeze(-1) * torch.tensor(bg, dtype=torch.float64)
    torch.testing.assert_close(with_bg.rgb, want)
    image = torch.rand(10, 12, 3, dtype=torch.float64)
    per_call = TorchRasterizer().render(gauss, cam, n_objects=2, background=image)
    torch.testing.assert_close(per_call.rgb, plain.rgb + (1 - plain.alpha).unsqueeze(-1) * image)


def test_gradients_match_central_finite_differences():
    k = 2
    gauss = random_scene(5, k, seed=3, radius=(0.08, 0.2))
    cam = oblique_camera(12, 10)
    gen = torch.Generator().manual_seed(4)
    weights = [
        torch.randn(10, 12, 3, generator=gen, dtype=torch.float64),
        torch.randn(10, 12, generator=gen, dtype=torch.float64),
        torch.randn(10, 12, generator=gen, dtype=torch.float64),
        torch.randn(k, 10, 12, generator=gen, dtype=torch.float64),
    ]
    opts = TorchRasterizerOptions(tile_size=4, pixel_chunk=32, pair_chunk=48)

    def loss(means, radii, colors, opacities, options=opts):
        g = GaussianFrames(means, radii, colors, opacities, gauss.object_ids)
        out = rasterize(g, cam, n_objects=k, options=options)[0]
        images = (out.rgb, out.alpha, out.depth, out.object_alpha)
        return sum((w * im).sum() for w, im in zip(weights, images))

    inputs = [gauss.means, gauss.radii, gauss.colors, gauss.opacities]
    leaves = [t.clone().requires_grad_(True) for t in inputs]
    grads = torch.autograd.grad(loss(*leaves), leaves)
    # the same gradients without checkpointing (stored instead of recomputed activations)
    plain = TorchRasterizerOptions(tile_size=4, pixel_chunk=32, pair_chunk=48, checkpoint=False)
    leaves2 = [t.clone().requires_grad_(True) for t in inputs]
    for a, b in zip(grads, torch.autograd.grad(loss(*leaves2, options=plain), leaves2)):
        torch.testing.assert_close(a, b, atol=1e-12, rtol=0)

    eps = 1e-6
    for which, (tensor, grad) in enumerate(zip(inputs, grads)):
        assert grad.abs().max() > 1e-3  # every input really drives the image
        fd = torch.zeros_like(tensor)
        for i in range(tensor.numel()):
            args = [t.clone() for t in inputs]
            args[which].view(-1)[i] += eps
            up = loss(*args).item()
            args[which].view(-1)[i] -= 2 * eps
            down = loss(*args).item()
            fd.view(-1)[i] = (up - down) / (2 * eps)
        torch.testing.assert_close(grad, fd, atol=1e-6, rtol=1e-5)


def test_tiling_and_chunking_do_not_change_the_image():
    gauss = random_scene(40, 3, seed=5, radius=(0.02, 0.1))
    cam = oblique_camera(37, 29)  # sizes no tile divides
    settings = [
        TorchRasterizerOptions(),
        TorchRasterizerOptions(tile_size=1, pixel_chunk=7, pair_chunk=5),
        TorchRasterizerOptions(tile_size=3, pixel_chunk=9, pair_chunk=20),
        TorchRasterizerOptions(tile_size=8, pixel_chunk=256, pair_chunk=64, checkpoint=False),
        TorchRasterizerOptions(tile_size=32, pixel_chunk=1024, pair_chunk=10_000),
    ]
    results = [rasterize(gauss, cam, n_objects=3, options=o) for o in settings]
    steps = {stats.n_steps for _, stats in results}
    assert len(steps) > 2  # the settings really split the work differently
    ref = results[0][0]
    for out, _ in results[1:]:
        for got, want in zip(
            (out.rgb, out.alpha, out.depth, out.object_alpha),
            (ref.rgb, ref.alpha, ref.depth, ref.object_alpha),
        ):
            torch.testing.assert_close(got, want, atol=1e-12, rtol=0)


def test_object_alpha_sums_to_alpha_and_separates_objects():
    gauss = random_scene(30, 4, seed=6)
    cam = oblique_camera(24, 20)
    out = rasterize(gauss, cam, n_objects=4)[0]
    assert out.object_alpha.shape == (4, 20, 24)
    torch.testing.assert_close(out.object_alpha.sum(0), out.alpha, atol=1e-12, rtol=0)
    assert (out.alpha <= 1).all() and (out.object_alpha >= 0).all()
    # removing object 2 (opacity 0) empties its channel and leaves the others drawn
    gauss.opacities = torch.where(gauss.object_ids == 2, 0.0, gauss.opacities)
    out = rasterize(gauss, cam, n_objects=4)[0]
    assert out.object_alpha[1].abs().max() == 0
    assert all(out.object_alpha[i].max() > 0.1 for i in (0, 2, 3))


def head_on_camera() -> Camera:
    # at the world origin looking along +z (camera axes = world axes)
    return Camera("front", 9, 7, fx=10.0, fy=8.0, cx=4.5, cy=3.5, world_to_camera=torch.eye(4))


def single(mean, radius, *, opacity=0.95, color=(0.2, 0.6, 1.0)):
    return GaussianFrames(
        torch.tensor([[mean]], dtype=torch.float64),
        torch.tensor([[radius]], dtype=torch.float64),
        torch.tensor([color], dtype=torch.float64),
        torch.tensor([opacity], dtype=torch.float64),
        torch.tensor([1]),
    )


def test_single_gaussian_head_on_lands_on_its_pixel():
    # centre (0.4, -0.25, 2): u = 10 * 0.4 / 2 + 4.5 = 6.5, v = 8 * -0.25 / 2 + 3.5 = 2.5,
    # the centre of column 6, row 2; footprint std-devs s_u = 0.1 * 10 / 2 = 0.5 px, s_v = 0.4 px
    out = rasterize(single((0.4, -0.25, 2.0), 0.1), head_on_camera(), n_objects=1)[0]
    row, col = divmod(int(out.alpha.argmax()), 9)
    assert (row, col) == (2, 6)
    assert out.alpha[2, 6].item() == pytest.approx(0.95, abs=1e-12)
    assert out.rgb[2, 6].tolist() == pytest.approx([0.19, 0.57, 0.95], abs=1e-12)
    assert out.depth[2, 6].item() == pytest.approx(0.95 * 2.0, abs=1e-12)
    # one pixel right: q = (1 / 0.5)^2 = 4; one pixel down: q = (1 / 0.4)^2 = 6.25
    assert out.alpha[2, 7].item() == pytest.approx(0.95 * math.exp(-2.0), abs=1e-12)
    assert out.alpha[3, 6].item() == pytest.approx(0.95 * math.exp(-3.125), abs=1e-12)
    # two pixels right: q = 16 > 3^2, past the cut-off
    assert out.alpha[2, 8].item() == 0.0
    # an opacity above max_alpha is clamped
    out = rasterize(single((0.4, -0.25, 2.0), 0.1, opacity=1.0), head_on_camera(), n_objects=1)[0]
    assert out.alpha.max().item() == pytest.approx(0.99, abs=1e-12)


def test_gaussians_behind_the_camera_or_near_plane_are_ignored():
    cam = head_on_camera()
    front = single((0.0, 0.0, 2.0), 0.2)
    # mirrored through the camera centre it would project onto the same pixels if not culled
    for z in (-2.0, 0.005):  # behind the camera; in front but closer than near = 0.01 m
        gauss = single((0.0, 0.0, z), 0.2)
        gauss.means.requires_grad_(True)
        out = rasterize(gauss, cam, n_objects=1)[0]
        assert out.alpha.abs().max() == 0 and out.rgb.abs().max() == 0
        both = GaussianFrames(
            torch.cat([front.means, gauss.means], dim=1),
            torch.cat([front.radii, gauss.radii], dim=1),
            torch.cat([front.colors, gauss.colors]),
            torch.cat([front.opacities, gauss.opacities]),
            torch.tensor([1, 1]),
        )
        out = rasterize(both, cam, n_objects=1)[0]
        alone = rasterize(front, cam, n_objects=1)[0]
        torch.testing.assert_close(out.rgb, alone.rgb, atol=0, rtol=0)
        (grad,) = torch.autograd.grad(out.rgb.sum(), gauss.means)
        assert torch.isfinite(grad).all() and grad.abs().max() == 0


def test_many_gaussians_render_in_bounded_steps():
    g, size, pair_chunk = 20_000, 128, 32_768
    gauss = random_scene(g, 3, seed=7, dtype=torch.float32, radius=(0.002, 0.01))
    cam = oblique_camera(size, size)
    opts = TorchRasterizerOptions(tile_size=16, pixel_chunk=1024, pair_chunk=pair_chunk)
    with torch.no_grad():
        out, stats = rasterize(gauss, cam, n_objects=3, options=opts)
    assert stats.n_visible > 0.9 * g
    # no slice evaluates more than pair_chunk (pixel, Gaussian) pairs ...
    assert 0 < stats.max_step_pairs <= pair_chunk
    assert stats.n_steps > 10
    # ... culling keeps the total far below every pixel against every Gaussian, and grouping
    # tiles of similar load keeps padding small against the (tile, Gaussian) overlaps
    assert stats.n_evaluated < 0.05 * size * size * g
    assert stats.n_evaluated < 1.1 * stats.n_tile_pairs * 16 * 16
    assert out.alpha.max() > 0.5 and out.alpha.min() >= 0 and out.alpha.max() <= 1


def test_bad_inputs_are_named():
    gauss = random_scene(4, 2, seed=8)
    cam = oblique_camera(8, 8)
    with pytest.raises(ValueError, match="frame=1"):
        rasterize(gauss, cam, frame=1, n_objects=2)
    with pytest.raises(ValueError, match="object_ids span 1..2"):
        rasterize(gauss, cam, n_objects=1)
    gauss.radii = gauss.radii[0]
    with pytest.raises(ValueError, match="radii"):
        rasterize(gauss, cam, n_objects=2)
