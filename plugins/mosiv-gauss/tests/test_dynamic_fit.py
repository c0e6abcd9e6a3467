"""End to end on CPU: the tiny generated two-object scene (48x48, 4 cameras, 6 frames, collision
at frame 3) is reconstructed by ``gauss-dynamic`` within loose, stated thresholds.

Measured on 2 CPU threads of an otherwise idle 16-core machine (2026-11-21, options
``conftest.TINY_FIT``, torch seeds 0 and 1, about 15 s for the fit): training PSNR 45.5-45.8 dB,
per-object mask IoU >= 0.70 in every frame (the worst is object 1 in the last frame), per-object
Chamfer of the Gaussian centres to the true particles 87-286 mm^2 per frame. The floor of that Chamfer is
about s^2 / 4 = 56 mm^2 for the true particles' lattice spacing s = 15 mm (a dense, perfect
reconstruction is on average s/2 per axis from the nearest lattice point). Thresholds leave a
margin for other CPUs and seeds of torch.
"""

from __future__ import annotations

import torch
from mosiv_gauss.dynamic_options import DynamicGaussOptions
from mosiv_gauss.evaluate import chamfer_per_frame, mask_iou
from mosiv_gauss.reconstructor import load_reconstruction, render_silhouettes

from mosiv_framework.types import Reconstruction

#: training-view PSNR, mean over all images (dB)
MIN_PSNR_DB = 35.0
#: per-object mask IoU, every frame (48x48 images: an object covers 5-40 pixels per view)
MIN_IOU = 0.6
#: per-object Chamfer distance (mm^2) of the Gaussian centres to the true points, every frame
MAX_CHAMFER_MM2 = 500.0
#: the options the session's fit was made with, for a second fit that differs in one option
TINY_FIT_FIELDS = DynamicGaussOptions.__dataclass_fields__


def assert_each_object_follows_its_own_points(recon, scene) -> None:
    """Each object's Gaussian centres are within MAX_CHAMFER_MM2 of its true points in every
    frame, and nearer its own points than the other object's (no identity swap), the
    collision frame 3 and after included."""
    gt = scene.gt_points()
    own = chamfer_per_frame(recon.points, gt)
    swapped = chamfer_per_frame({1: recon.points[2], 2: recon.points[1]}, gt)
    for k in (1, 2):
        assert max(own[k]) <= MAX_CHAMFER_MM2, (k, own[k])
        for t in range(scene.n_frames):
            assert own[k][t] < swapped[k][t], (k, t, own[k][t], swapped[k][t])


def test_fit_returns_object_aware_dynamic_gaussians(tiny_scene, tiny_fit):
    _, recon, _ = tiny_fit
    assert isinstance(recon, Reconstruction)
    assert recon.object_list == [1, 2]
    g = recon.gaussians
    n_frames = tiny_scene.n_frames
    assert g.means.shape[0] == n_frames and g.radii.shape == g.means.shape[:2]
    assert torch.isfinite(g.means).all() and (g.radii > 0).all()
    assert ((g.opacities >= 0) & (g.opacities <= 1)).all()
    for k in (1, 2):
        assert recon.points[k].shape[0] == n_frames and recon.points[k].shape[1] > 0
        assert torch.equal(recon.points[k], g.means[:, g.object_ids == k])
    assert set(recon.background) == set(tiny_scene.camera_ids)


def test_training_views_are_reproduced(tiny_fit):
    _, recon, _ = tiny_fit
    scores = recon.extras["training"]
    assert scores["psnr_mean"] >= MIN_PSNR_DB, scores
    for k, per_frame in scores["iou"].items():
        assert all(v is not None and v >= MIN_IOU for v in per_frame), (k, per_frame)


def test_gaussian_centres_follow_each_object_through_the_collision(tiny_scene, tiny_fit):
    _, recon, _ = tiny_fit
    assert_each_object_follows_its_own_points(recon, tiny_scene)


def test_run_folder_reloads_and_silhouettes_match_the_masks(tiny_scene, tiny_fit):
    reconstructor, recon, run_dir = tiny_fit
    back = load_reconstruction(run_dir / reconstructor.options.save_dir)
    for k in (1, 2):
        assert torch.equal(back.points[k], recon.points[k])
    assert back.extras["training"] == recon.extras["training"]
    silhouettes = render_silhouettes(back, tiny_scene.cameras, tile_size=8)
    alpha = torch.stack([silhouettes[1], silhouettes[2]], dim=2)  # [F, C, K, H, W]
    iou = mask_iou(alpha, tiny_scene.load_mask_ids())
    assert (iou >= MIN_IOU).all(), iou


def test_per_frame_refinement_sharpens_every_frame_without_swapping_identity(tiny_scene, tiny_fit):
    """The same fit with ``refine_iterations``: on the development CPU (2026-11-23) 100 steps
    raised the worst IoU from 0.69 to 0.95 and the PSNR from 44.0 to 49.4 dB. With 4 cameras
    the weak default neighbour term lets hidden parts wander (object 2's mean Chamfer 112 ->
    125 mm^2), so only the silhouettes are held to a tighter bound here; the 3D error keeps
    the plain fit's threshold."""
    from mosiv_framework.registry import get_registry

    reconstructor, plain, _ = tiny_fit
    same = {name: getattr(reconstructor.options, name) for name in TINY_FIT_FIELDS}
    options = {**same, "refine_iterations": 100, "save_dir": ""}
    refined = get_registry().create("reconstructor", "gauss-dynamic", options).fit(tiny_scene)
    before, after = plain.extras["training"], refined.extras["training"]
    assert after["iou_min"] >= before["iou_min"] + 0.1, (before["iou_min"], after["iou_min"])
    assert after["iou_min"] >= 0.85, after["iou"]
    assert after["psnr_mean"] >= before["psnr_mean"] + 2.0
    assert_each_object_follows_its_own_points(refined, tiny_scene)


def test_a_camera_that_started_late_is_fitted_from_the_views_it_has(tiny_scene, tiny_fit, tmp_path):
    """The tiny scene with camera cam_01 missing frames 0 and 1 (a rig's late start): the fit
    trains on the views that exist, seeds frame 0 from the other three cameras, and follows
    each object within the full scene's bounds; the scores cover only recorded views."""
    from mosiv_framework.registry import get_registry
    from mosiv_framework.scene import read_scene
    from mosiv_framework.testing.views import with_recorded_frames

    late_dir = with_recorded_frames(tiny_scene.root, tmp_path / "late", {"cam_01": (2, 5)})
    late = read_scene(late_dir)
    reconstructor = tiny_fit[0]
    same = {name: getattr(reconstructor.options, name) for name in TINY_FIT_FIELDS}
    options = {**same, "save_dir": ""}
    recon = get_registry().create("reconstructor", "gauss-dynamic", options).fit(late)
    scores = recon.extras["training"]
    assert scores["psnr_mean"] >= MIN_PSNR_DB, scores
    for k, per_frame in scores["iou"].items():
        assert all(v is not None and v >= MIN_IOU for v in per_frame), (k, per_frame)
    assert_each_object_follows_its_own_points(recon, late)
