"""Units of the dynamic reconstructor: visual hull, eq. 1 deformation, loss gradients (against
central finite differences), background estimate, densification and pruning, save/load."""

from __future__ import annotations

import mosiv_gauss.train as gauss_train
import pytest
import torch
from mosiv_gauss.dynamic_options import DynamicGaussOptions
from mosiv_gauss.init import carve_labels, hull_init, pixel_lookup, voxel_grid
from mosiv_gauss.model import DynamicGaussians
from mosiv_gauss.options import TorchRasterizerOptions
from mosiv_gauss.rasterizer import rasterize
from mosiv_gauss.reconstructor import (
    load_reconstruction,
    render_silhouettes,
    save_reconstruction,
    to_reconstruction,
)
from mosiv_gauss.step_guard import MAX_SKIPPED_IN_A_ROW
from mosiv_gauss.train import (
    TrainingData,
    coarse_mask_l1,
    densify_and_prune,
    estimate_background,
    hull_loss,
    track_loss,
    train_dynamic,
    view_loss,
)

from mosiv_framework.errors import ConfigError, ReconstructionDiverged
from mosiv_framework.registry import get_registry
from mosiv_framework.scene.cameras import Camera
from mosiv_framework.types import GaussianFrames

LOWER, UPPER = (-0.4, -0.4, 0.0), (0.4, 0.4, 0.6)


def small_model(g: int = 24, *, n_frames: int = 4, seed: int = 0, dtype=torch.float32):
    gen = torch.Generator().manual_seed(seed)
    torch.manual_seed(seed)
    means = torch.tensor([0.0, 0.0, 0.3]) + 0.1 * (torch.rand(g, 3, generator=gen) - 0.5)
    model = DynamicGaussians(
        means=means,
        radii=0.01 + 0.01 * torch.rand(g, generator=gen),
        colors=torch.rand(g, 3, generator=gen),
        opacities=0.3 + 0.5 * torch.rand(g, generator=gen),
        object_ids=torch.arange(g) % 2 + 1,
        n_objects=2,
        n_frames=n_frames,
        lower=LOWER,
        upper=UPPER,
        n_bases=3,
        basis_width=8,
        basis_layers=2,
        coef_width=8,
        coef_layers=2,
        pe_frequencies=2,
    )
    return model.to(dtype)


def random_images(*, n_frames: int, seed: int) -> TrainingData:
    """One camera's random 24 x 24 images over ``n_frames``, no masks, a black background."""
    gen = torch.Generator().manual_seed(seed)
    return TrainingData(
        rgb=torch.rand(n_frames, 1, 24, 24, 3, generator=gen),
        masks=torch.zeros(n_frames, 1, 2, 24, 24),
        cameras=[camera()],
        background=torch.zeros(1, 24, 24, 3),
        voxel_size=0.01,
    )


def camera(size: int = 24) -> Camera:
    return Camera.look_at((0.5, -1.0, 0.7), (0.0, 0.0, 0.3), width=size, height=size, fx=40.0)


def test_visual_hull_contains_the_ground_truth_points(tiny_scene):
    """At least 95% of each object's true frame-0 particles lie in a voxel of its hull."""
    ids = tiny_scene.load_mask_ids(frames=[0])
    grid = voxel_grid(tiny_scene.domain_lower, tiny_scene.domain_upper, resolution=64)
    labels = carve_labels(pixel_lookup(grid.centres, tiny_scene.cameras), ids[0], n_objects=2)
    lower = torch.tensor(tiny_scene.domain_lower)
    upper = torch.tensor(tiny_scene.domain_upper)
    shape = torch.round((upper - lower) / grid.voxel_size).long()
    for k, points in tiny_scene.gt_points().items():
        cell = torch.floor((points[0] - lower) / grid.voxel_size).long()
        flat = (cell[:, 0] * shape[1] + cell[:, 1]) * shape[2] + cell[:, 2]
        inside = (labels[flat] == k).float().mean().item()
        assert inside >= 0.95, f"object {k}: only {inside:.1%} of its points are in its hull"
        # and the hull is a hull of this object, not of the whole scene: under 10x its volume
        hull_volume = (labels == k).sum().item() * grid.voxel_size**3
        true_volume = points.shape[1] * 0.015**3  # particles on a 15 mm lattice
        assert hull_volume < 10 * true_volume


def test_hull_init_seeds_each_object_with_its_colour(tiny_scene):
    ids = tiny_scene.load_mask_ids()
    rgb = tiny_scene.load_rgb_tensor(frames=[0])[0]
    seeds = hull_init(
        tiny_scene.cameras,
        ids,
        rgb,
        lower=LOWER,
        upper=UPPER,
        n_objects=2,
        resolution=48,
        max_gaussians=200,
        generator=torch.Generator().manual_seed(0),
    )
    assert seeds.tracks.shape == (tiny_scene.n_frames, 2, 3)
    for k in (1, 2):
        mine = seeds.object_ids == k
        assert 0 < mine.sum() <= 100
        # seeds sit near the true object and take its colour (the mean of its masked pixels)
        gt = tiny_scene.gt_points()[k][0]
        assert (seeds.means[mine].mean(0) - gt.mean(0)).norm() < 0.02
        pix = rgb[ids[0] == k]
        assert torch.allclose(seeds.colors[mine].mean(0), pix.mean(0), atol=0.1)


def test_zero_coefficients_give_the_identity_deformation():
    model = small_model()
    means, radii = model.at([0, 1, 2, 3])
    assert torch.equal(means, model.means.detach().expand_as(means))
    assert torch.allclose(radii, model.log_radii.exp().expand_as(radii), rtol=1e-6)


def test_deformation_is_eq1_sum_over_bases():
    model = small_model()
    with torch.no_grad():
        torch.nn.init.normal_(model.coefficients.net[-1].weight)
        frames = torch.tensor([0.0, 2.0])
        psi = model.basis(frames / 3.0)  # [F, B, 4], t normalised by T - 1 = 3
        alpha = model.coefficients(model.means, model.object_ids)  # [G, B]
        means, radii = model.at([0, 2])
    for f in range(2):
        expected = model.means + sum(alpha[:, b : b + 1] * psi[f, b, :3] for b in range(3))
        assert torch.allclose(means[f], expected, atol=1e-6)
        log_r = model.log_radii + sum(alpha[:, b] * psi[f, b, 3] for b in range(3))
        assert torch.allclose(radii[f], log_r.exp(), rtol=1e-5)
    assert not torch.allclose(means[0], means[1])  # the networks really move the Gaussians


def _render_loss(model, cam, target_rgb, target_masks, opts, frame=1):
    means, radii = model.at([frame])
    g = GaussianFrames(means, radii, model.colors(), model.opacities(), model.object_ids)
    out, _ = rasterize(
        g,
        cam,
        n_objects=2,
        options=TorchRasterizerOptions(tile_size=8),
        background=torch.full((3,), 0.2, dtype=means.dtype),
    )
    return (
        view_loss(out.rgb[None], out.object_alpha[None], target_rgb[None], target_masks[None], opts)
        + opts.lambda_radius * radii.mean() / 0.01
    )


def test_loss_gradient_reaches_the_network_weights_and_matches_finite_differences():
    model = small_model(dtype=torch.float64)
    with torch.no_grad():  # leave the identity so every layer of both networks gets gradient
        torch.nn.init.normal_(model.coefficients.net[-1].weight, std=0.3)
    cam = camera()
    target = small_model(seed=1, dtype=torch.float64)
    with torch.no_grad():
        t_means, t_radii = target.at([1])
        g = GaussianFrames(t_means, t_radii, target.colors(), target.opacities(), target.object_ids)
        ref, _ = rasterize(
            g,
            cam,
            n_objects=2,
            options=TorchRasterizerOptions(tile_size=8),
            background=torch.full((3,), 0.2, dtype=torch.float64),
        )
    opts = DynamicGaussOptions()
    loss = _render_loss(model, cam, ref.rgb, ref.object_alpha, opts)
    loss.backward()
    for name, p in [*model.basis.named_parameters(), *model.coefficients.named_parameters()]:
        assert p.grad is not None and p.grad.abs().sum() > 0, f"no gradient reaches {name}"
    # central finite differences on one weight of each network
    for param in (model.basis.net[0].weight, model.coefficients.net[0].weight):
        index = tuple(int(i) for i in torch.nonzero(param.grad.abs() == param.grad.abs().max())[0])
        eps = 1e-6
        with torch.no_grad():
            old = param[index].item()
            param[index] = old + eps
            up = _render_loss(model, cam, ref.rgb, ref.object_alpha, opts).item()
            param[index] = old - eps
            down = _render_loss(model, cam, ref.rgb, ref.object_alpha, opts).item()
            param[index] = old
        numeric = (up - down) / (2 * eps)
        assert param.grad[index].item() == pytest.approx(numeric, rel=1e-4, abs=1e-9)


def test_background_is_the_median_outside_the_masks():
    gen = torch.Generator().manual_seed(0)
    background = torch.rand(2, 6, 5, 3, generator=gen)
    rgb = background.expand(5, -1, -1, -1, -1).clone()
    ids = torch.zeros(5, 2, 6, 5, dtype=torch.long)
    for t in range(5):  # an object walks along row 2, painting its pixels red
        ids[t, :, 2, t] = 1
        rgb[t, :, 2, t] = torch.tensor([1.0, 0.0, 0.0])
    ids[:, 1, 4, 4] = 1  # a pixel of camera 1 covered in every frame
    rgb[:, 1, 4, 4] = torch.tensor([0.0, 1.0, 0.0])
    est = estimate_background(rgb, ids)
    hole = torch.zeros(2, 6, 5, dtype=torch.bool)
    hole[1, 4, 4] = True
    assert torch.equal(est[~hole], background[~hole])
    fill = background[1][~hole[1]].reshape(-1, 3).median(dim=0).values
    assert torch.equal(est[1, 4, 4], fill)


def test_densify_clones_splits_and_prunes_keeping_adam_state():
    model = small_model(g=10)
    opts = DynamicGaussOptions(densify_grad=1e-3, prune_opacity=0.05, max_gaussians=100)
    voxel = 0.01
    with torch.no_grad():
        model.log_radii[:] = torch.log(torch.tensor(0.5 * voxel))
        model.log_radii[1] = torch.log(torch.tensor(2.0 * voxel))  # wide: will be split
        model.opacity_logits[9] = -10.0  # nearly transparent: will be pruned
    optimizer = torch.optim.Adam(
        [{"params": [getattr(model, n)], "name": n, "lr": 1e-3} for n in model.canonical_names]
    )
    model.means.sum().backward()
    optimizer.step()
    grad = torch.zeros(10)
    grad[0] = grad[1] = 1.0  # score = grad * voxel = 0.01 > 1e-3 for Gaussians 0 and 1
    ids_before = model.object_ids.clone()
    moment = optimizer.state[model.means]["exp_avg"].clone()
    densify_and_prune(model, optimizer, grad, voxel_size=voxel, opts=opts)
    # 10 - 1 (pruned) - 1 (split) + 1 (clone) + 2 (split children)
    assert model.n_gaussians == 11
    kept = [0, 2, 3, 4, 5, 6, 7, 8]
    assert torch.equal(model.object_ids, ids_before[[*kept, 0, 1, 1]])
    assert torch.allclose(model.log_radii[-2:].exp(), torch.full((2,), 2.0 * voxel / 1.6))
    state = optimizer.state[model.means]
    assert torch.equal(state["exp_avg"], moment[[*kept, 0, 1, 1]])
    assert optimizer.param_groups[0]["params"][0] is model.means


def test_track_anchor_is_the_squared_centroid_excess_in_voxels_where_the_hull_exists():
    # two objects, two frames; object 2's hull is empty at frame 1, so it is left out there
    ids = torch.tensor([1, 1, 2, 2])
    means = torch.zeros(2, 4, 3)
    means[:, :2] = torch.tensor([[0.1, 0.0, 0.3], [0.3, 0.0, 0.3]])  # object 1 centroid x=0.2
    means[:, 2:] = torch.tensor([[0.0, 0.5, 0.2], [0.0, 0.7, 0.2]])  # object 2 centroid y=0.6
    tracks = torch.tensor([[[0.2, 0.0, 0.3], [0.0, 0.6, 0.2]], [[0.23, 0.0, 0.3], [9.0, 9.0, 9.0]]])
    valid = torch.tensor([[True, True], [True, False]])
    voxel = 0.01
    data = TrainingData(
        rgb=torch.zeros(2, 1, 4, 4, 3),
        masks=torch.zeros(2, 1, 2, 4, 4),
        cameras=[],
        background=torch.zeros(1, 4, 4, 3),
        voxel_size=voxel,
        tracks=tracks,
        track_valid=valid,
    )
    assert float(track_loss(means[:1], [0], ids, data, tolerance=0.0)) == pytest.approx(
        0.0, abs=1e-9
    )
    # frame 1: object 1 is 3 voxels off along x, object 2 is skipped -> mean over one term
    assert float(track_loss(means[1:], [1], ids, data, tolerance=0.0)) == pytest.approx(
        9.0, rel=1e-4
    )
    # within the tolerance nothing pulls; beyond it only the excess counts: (3 - 2)^2
    assert float(track_loss(means[1:], [1], ids, data, tolerance=3.5)) == 0.0
    assert float(track_loss(means[1:], [1], ids, data, tolerance=2.0)) == pytest.approx(
        1.0, rel=1e-3
    )
    # both frames: (0 + 0 + 9) / 3 terms
    assert float(track_loss(means, [0, 1], ids, data, tolerance=0.0)) == pytest.approx(
        3.0, rel=1e-4
    )
    # the anchor's gradient moves every Gaussian of the object by the same amount
    moved = means.clone().requires_grad_(True)
    track_loss(moved[1:], [1], ids, data, tolerance=2.0).backward()
    grad = moved.grad[1]
    assert (
        torch.allclose(grad[0], grad[1])
        and float(grad[0, 0]) < 0
        and float(grad[2:].abs().sum()) == 0
    )


def test_hull_term_is_a_chamfer_in_voxels_with_the_first_voxel_free():
    voxel = 0.01
    ids = torch.tensor([1, 1, 2])
    hull1 = torch.tensor([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0]])
    hulls = [[hull1, torch.zeros(0, 3)]]  # object 2's hull is empty: left out
    on = torch.stack([hull1[0], hull1[1], torch.tensor([5.0, 5.0, 5.0])])[None]
    assert float(hull_loss(on, [0], ids, hulls, voxel_size=voxel)) == 0.0
    half = on + torch.tensor([0.005, 0.0, 0.0])  # half a voxel off: still free
    assert float(hull_loss(half, [0], ids, hulls, voxel_size=voxel)) == 0.0
    # both Gaussians 4 voxels up: each way every distance is 4, minus the free voxel -> 9 + 9
    up = (on + torch.tensor([0.0, 0.0, 0.04])).requires_grad_(True)
    value = hull_loss(up, [0], ids, hulls, voxel_size=voxel)
    assert float(value.detach()) == pytest.approx(18.0, rel=1e-4)
    value.backward()  # descent moves both down onto the hull; object 2 feels nothing
    assert float(up.grad[0, :2, 2].min()) > 0 and float(up.grad[0, 2].abs().sum()) == 0


def test_training_with_the_hull_term_pulls_each_object_onto_its_hull():
    # no photometric signal (black images, no masks): only the hull term can move the
    # Gaussians, and it moves each object's centres onto its hull, 5 cm away
    def fit(lambda_hull: float):
        model = small_model(n_frames=2)
        hulls = []
        for t in range(2):
            means = model.at([t])[0][0].detach()
            shift = torch.tensor([0.05, 0.0, 0.0])
            hulls.append([means[model.object_ids == k] + shift for k in (1, 2)])
        data = TrainingData(
            rgb=torch.zeros(2, 1, 24, 24, 3),
            masks=torch.zeros(2, 1, 2, 24, 24),
            cameras=[camera()],
            background=torch.zeros(1, 24, 24, 3),
            voxel_size=0.01,
            hulls=hulls,
        )
        options = DynamicGaussOptions(
            iterations=60,
            lambda_hull=lambda_hull,
            lambda_radius=0.0,
            densify_from=10**6,
            progress=False,
        )
        with torch.no_grad():
            before = float(
                hull_loss(model.at([0, 1])[0], [0, 1], model.object_ids, hulls, voxel_size=0.01)
            )
        train_dynamic(model, data, options, generator=torch.Generator().manual_seed(0))
        with torch.no_grad():
            after = hull_loss(model.at([0, 1])[0], [0, 1], model.object_ids, hulls, voxel_size=0.01)
        return before, float(after)

    before, with_term = fit(1.0)
    _, without = fit(0.0)
    assert before > 5.0
    assert with_term < 0.25 * before and without > 0.9 * before


def test_area_ratio_tells_a_fat_silhouette_from_a_thin_one():
    from mosiv_gauss.evaluate import drawn_area_ratio, mask_iou

    # one frame, one camera, two objects: object 1 recorded as a 4x4 square, object 2 absent
    masks = torch.zeros(1, 1, 8, 8, dtype=torch.int64)
    masks[0, 0, 2:6, 2:6] = 1
    fat = torch.zeros(1, 1, 2, 8, 8)
    fat[0, 0, 0, 1:7, 1:7] = 1.0  # 6x6 drawn over the 4x4: IoU 16/36 and area 36/16
    thin = torch.zeros(1, 1, 2, 8, 8)
    thin[0, 0, 0, 3:5, 2:6] = 1.0  # 2x4 inside it: IoU 8/16 and area 8/16
    assert float(mask_iou(fat, masks)[0, 0]) == pytest.approx(16 / 36)
    assert float(drawn_area_ratio(fat, masks)[0, 0]) == pytest.approx(36 / 16)
    assert float(drawn_area_ratio(thin, masks)[0, 0]) == pytest.approx(0.5)
    assert torch.isnan(drawn_area_ratio(thin, masks)[0, 1])  # object 2 is in no mask


def test_more_time_octaves_let_the_bases_follow_an_abrupt_change():
    # an impact: a residual that jumps at frame 15 of 30. With one octave of time encoding the
    # basis network is too smooth to follow it; with six it fits the step far more closely.
    from mosiv_gauss.model import BasisNetwork

    t = torch.arange(30, dtype=torch.float32) / 29
    target = (t > 0.5).float()

    def fit_error(octaves: int) -> float:
        torch.manual_seed(0)
        basis = BasisNetwork(n_bases=1, width=32, layers=2, scale=1.0, time_frequencies=octaves)
        optimiser = torch.optim.Adam(basis.parameters(), lr=1e-2)
        for _ in range(400):
            optimiser.zero_grad()
            loss = ((basis(t)[:, 0, 0] - target) ** 2).mean()
            loss.backward()
            optimiser.step()
        return float(loss.detach())

    assert fit_error(6) < 0.2 * fit_error(1)
    with pytest.raises(ConfigError, match="time_frequencies"):
        get_registry().create("reconstructor", "gauss-dynamic", {"time_frequencies": -1})


def test_block_mean_mask_term_asks_for_the_density_of_scattered_dots():
    """A body drawn as dots on a quarter of the pixels of an 8 x 8 region: the per-pixel mask
    L1 of a uniform cover of alpha a is lowest with nothing drawn (a = 0), the 4 x 4 block-mean
    L1 at the dots' density (a = 0.25), where it is zero; on a solid mask both vanish at a = 1."""
    dots = torch.zeros(1, 1, 16, 16)
    dots[0, 0, 4:12:2, 4:12:2] = 1.0
    region = torch.zeros(1, 1, 16, 16)
    region[0, 0, 4:12, 4:12] = 1.0
    levels = torch.linspace(0.0, 1.0, 21)
    per_pixel = torch.stack([(a * region - dots).abs().mean() for a in levels])
    blocks = torch.stack([coarse_mask_l1(a * region, dots, 4) for a in levels])
    assert float(levels[per_pixel.argmin()]) == 0.0
    assert float(levels[blocks.argmin()]) == pytest.approx(0.25)
    assert float(blocks.min()) == pytest.approx(0.0, abs=1e-7)
    assert float(coarse_mask_l1(region, region, 4)) == 0.0
    # in view_loss the term is added with its weight, and nothing changes when it is off
    rgb = torch.zeros(1, 16, 16, 3)
    alpha = 0.25 * region
    off = DynamicGaussOptions(lambda_mask_coarse=0.0)
    on = DynamicGaussOptions(lambda_mask_coarse=2.0, mask_pool=4)
    gap = view_loss(rgb, alpha, rgb, dots, on) - view_loss(rgb, alpha, rgb, dots, off)
    assert float(gap) == pytest.approx(2.0 * float(coarse_mask_l1(alpha, dots, 4)), abs=1e-7)
    # a partial block at the border is the mean of the pixels it has: a full cover of a
    # 15 x 15 image against an empty mask differs by 1 in every block
    full, empty = torch.ones(1, 1, 15, 15), torch.zeros(1, 1, 15, 15)
    assert float(coarse_mask_l1(full, empty, 4)) == pytest.approx(1.0)


def test_bad_options_name_the_option_and_its_range():
    with pytest.raises(ConfigError, match="lambda_mask"):
        get_registry().create("reconstructor", "gauss-dynamic", {"lambda_mask": -1.0})
    with pytest.raises(ConfigError, match="lambda_mask_coarse"):
        get_registry().create("reconstructor", "gauss-dynamic", {"lambda_mask_coarse": -1.0})
    with pytest.raises(ConfigError, match="mask_pool"):
        get_registry().create("reconstructor", "gauss-dynamic", {"mask_pool": 0})
    with pytest.raises(ConfigError, match="lambda_track"):
        get_registry().create("reconstructor", "gauss-dynamic", {"lambda_track": -0.1})
    with pytest.raises(ConfigError, match="lambda_hull"):
        get_registry().create("reconstructor", "gauss-dynamic", {"lambda_hull": -1.0})
    with pytest.raises(ConfigError, match="background"):
        get_registry().create("reconstructor", "gauss-dynamic", {"background": "green"})
    with pytest.raises(ConfigError, match="valid options"):
        get_registry().create("reconstructor", "gauss-dynamic", {"iters": 3})


def test_save_load_round_trip_and_silhouettes(tmp_path):
    model = small_model()
    with torch.no_grad():
        torch.nn.init.normal_(model.coefficients.net[-1].weight, std=0.3)
        gaussians = model.frames()
    background = torch.rand(2, 24, 24, 3)
    recon = to_reconstruction(
        gaussians,
        background,
        camera_ids=["a", "b"],
        extras={"note": "round trip", "values": [1.5, None]},
    )
    save_reconstruction(recon, tmp_path / "saved")
    back = load_reconstruction(tmp_path / "saved")
    assert back.object_list == recon.object_list == [1, 2]
    for k in recon.points:
        assert torch.equal(back.points[k], recon.points[k])
        assert back.points[k].shape == (4, 12, 3)
    for name in ("means", "radii", "colors", "opacities", "object_ids"):
        assert torch.equal(getattr(back.gaussians, name), getattr(recon.gaussians, name))
    assert set(back.background) == {"a", "b"}
    assert torch.equal(back.background["b"], background[1])
    assert back.extras == {"note": "round trip", "values": [1.5, None]}
    sil_a = render_silhouettes(recon, [camera()], frames=[0, 3])
    sil_b = render_silhouettes(back, [camera()], frames=[0, 3])
    assert sorted(sil_a) == [1, 2] and sil_a[1].shape == (2, 1, 24, 24)
    assert all(torch.equal(sil_a[k], sil_b[k]) for k in (1, 2))
    assert sil_a[1].max() > 0.1 and sil_a[2].max() > 0.1
    with pytest.raises(ValueError, match="reconstruction.json"):
        load_reconstruction(tmp_path / "missing")


def test_network_warmup_keeps_the_fitted_deformation_through_adams_first_steps():
    # Adam's first steps move every weight by about the learning rate whatever the gradient,
    # so a fresh optimiser on fitted networks throws the deformation off at once; the ramp
    # makes those steps network_warmup times smaller
    def deformation_change(warmup: int) -> float:
        model = small_model(n_frames=3)
        with torch.no_grad():  # a fitted-looking deformation: non-zero coefficients
            model.coefficients.net[-1].weight.normal_(0.0, 0.1)
            before = model.residuals([0, 1, 2])[..., :3].clone()
        data = random_images(n_frames=3, seed=1)
        options = DynamicGaussOptions(
            iterations=3,
            views_per_step=3,
            network_warmup=warmup,
            densify_from=10**6,
            progress=False,
        )
        train_dynamic(model, data, options, generator=torch.Generator().manual_seed(0))
        with torch.no_grad():
            after = model.residuals([0, 1, 2])[..., :3]
        return float((after - before).norm(dim=-1).mean())

    free, ramped = deformation_change(0), deformation_change(100)
    assert free > 1e-4  # metres: the unramped steps do move the fitted deformation
    assert ramped < 0.1 * free, (ramped, free)


def test_a_camera_that_missed_the_frame_neither_carves_nor_votes(tiny_scene):
    """A missing view loads as an empty mask; marked absent, it must not carve the hull away:
    the labels equal those of carving with the other cameras alone."""
    ids = tiny_scene.load_mask_ids(frames=[0])[0].clone()
    grid = voxel_grid(tiny_scene.domain_lower, tiny_scene.domain_upper, resolution=48)
    lookup = pixel_lookup(grid.centres, tiny_scene.cameras)
    ids[1] = 0  # what load_mask_ids(missing="zeros") gives for a view not recorded
    views = torch.tensor([True, False, True, True])
    labels = carve_labels(lookup, ids, n_objects=2, views=views)
    others = [0, 2, 3]
    expected = carve_labels(lookup[others], ids[others], n_objects=2)
    assert torch.equal(labels, expected)
    assert (labels == 1).any() and (labels == 2).any()
    assert not (carve_labels(lookup, ids, n_objects=2) > 0).any()  # unmarked, it carves all


def test_views_not_recorded_are_never_sampled_and_give_no_background():
    from mosiv_gauss.train import sample_views

    gen = torch.Generator().manual_seed(0)
    background = torch.rand(2, 4, 4, 3, generator=gen)
    rgb = background.expand(3, -1, -1, -1, -1).clone()
    views = torch.ones(3, 2, dtype=torch.bool)
    views[0, 1] = False
    rgb[0, 1] = 0.0  # the black image of the missing view
    ids = torch.zeros(3, 2, 4, 4, dtype=torch.long)
    est = estimate_background(rgb, ids, views)
    assert torch.equal(est, background)
    data = TrainingData(
        rgb=rgb,
        masks=torch.zeros(3, 2, 1, 4, 4),
        cameras=[camera(4), camera(4)],
        background=est,
        voxel_size=0.01,
        views=views,
    )
    order: list[int] = []
    epoch = sample_views(data, 5, order, gen)
    assert sorted(epoch) == [(0, 0), (1, 0), (1, 1), (2, 0), (2, 1)]
    assert all(views[t, c] for t, c in sample_views(data, 20, order, gen))


def _nan_on_steps(monkeypatch, bad_steps) -> None:
    """Make the training loss NaN on the steps in ``bad_steps`` (call order)."""
    real = gauss_train._training_loss
    calls = []

    def loss(*args, **kwargs):
        value = real(*args, **kwargs)
        calls.append(len(calls))
        return value * float("nan") if bad_steps(calls[-1]) else value

    monkeypatch.setattr(gauss_train, "_training_loss", loss)


def _tiny_training(iterations: int):
    model = small_model(n_frames=2)
    data = random_images(n_frames=2, seed=2)
    options = DynamicGaussOptions(iterations=iterations, densify_from=10**6, progress=False)
    return model, data, options


def test_a_step_with_a_non_finite_loss_is_skipped_and_the_parameters_stay_finite(monkeypatch):
    _nan_on_steps(monkeypatch, lambda step: step == 2)
    model, data, options = _tiny_training(6)
    history = train_dynamic(model, data, options, generator=torch.Generator().manual_seed(0))
    assert history.skipped_steps == [2]
    assert len(history.loss) == 5
    for param in [*model.canonical_parameters(), *model.network_parameters()]:
        assert torch.isfinite(param).all()


def test_training_that_never_gives_a_finite_loss_stops_naming_the_step(monkeypatch):
    _nan_on_steps(monkeypatch, lambda step: step >= 1)
    model, data, options = _tiny_training(MAX_SKIPPED_IN_A_ROW + 10)
    with pytest.raises(ReconstructionDiverged) as caught:
        train_dynamic(model, data, options, generator=torch.Generator().manual_seed(0))
    assert caught.value.step == MAX_SKIPPED_IN_A_ROW  # steps 1..25 skipped
    assert "Gaussian training" in str(caught.value) and "non-finite loss" in str(caught.value)
