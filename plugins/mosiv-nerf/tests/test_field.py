"""The frame-0 field fit, the particles sampled from it and their grid renders."""

from __future__ import annotations

import torch
from mosiv_nerf.hull import carve
from mosiv_nerf.lifter import NerfParticlesLifter
from mosiv_nerf.reconstructor import psnr
from mosiv_nerf.renderer import NerfGridRenderer

#: frame-0 PSNR (dB) over the object pixels of the tiny fit; measured 34.5 dB (all pixels 46.8)
MIN_OBJECT_PSNR_DB = 30.0
#: the grid render of the lifted particles (B-spline splat), object pixels; measured 28.3 dB
MIN_GRID_OBJECT_PSNR_DB = 25.0


def test_field_fit_reproduces_frame0_images(tiny_reconstruction):
    report = tiny_reconstruction.extras["nerf_fit"]
    print("nerf-field tiny fit:", report)
    assert report["loss_last"] < 0.5 * report["loss_first"]
    assert report["object_psnr_db"] > MIN_OBJECT_PSNR_DB
    # every frame has hull points for every object (identification's targets)
    for pts in tiny_reconstruction.points.values():
        assert pts.shape == (6, 200, 3)


def test_particles_lie_in_the_visual_hull(tiny_scene, tiny_reconstruction):
    particles = NerfParticlesLifter().lift(tiny_reconstruction, tiny_scene)
    ids0 = tiny_scene.load_mask_ids(frames=[0])[0]
    labels = carve(particles.positions, tiny_scene.cameras, ids0, min_views=1)
    agree = (labels == particles.object_ids).float().mean()
    print(f"particles: {len(particles)}, share inside their object's hull {float(agree):.3f}")
    assert float(agree) > 0.9
    # every particle is within one spacing of its object's hull (jitter and voxel size)
    spacing = particles.appearance.report["spacing_m"]
    offsets = (
        torch.tensor(
            [[dx, dy, dz] for dx in (-1, 0, 1) for dy in (-1, 0, 1) for dz in (-1, 0, 1)],
            dtype=torch.float32,
        )
        * spacing
    )
    near = torch.zeros(len(particles), dtype=torch.bool)
    for off in offsets:
        near |= carve(particles.positions + off, tiny_scene.cameras, ids0, min_views=1) == (
            particles.object_ids
        )
    assert bool(near.all())


def test_grid_render_of_the_particles_matches_frame0(tiny_scene, tiny_reconstruction):
    particles = NerfParticlesLifter().lift(tiny_reconstruction, tiny_scene)
    frames = particles.appearance.binding.gaussian_frames(particles.positions)
    renderer = NerfGridRenderer()
    preds, recs, masks = [], [], []
    for cam in tiny_scene.cameras:
        out = renderer.render(
            frames, cam, n_objects=2, background=particles.appearance.background[cam.id]
        )
        assert out.object_alpha.shape == (2, cam.height, cam.width)
        preds.append(out.rgb.clamp(0, 1))
        recs.append(torch.from_numpy(tiny_scene.rgb(cam.id, 0)).float() / 255.0)
        masks.append(torch.from_numpy(tiny_scene.mask(cam.id, 0) > 0))
    pred, rec, mask = torch.stack(preds), torch.stack(recs), torch.stack(masks)
    value = psnr(pred[mask], rec[mask])
    print(f"grid render of the lifted particles: object PSNR {value:.2f} dB")
    assert value > MIN_GRID_OBJECT_PSNR_DB


def test_a_camera_that_missed_frame_0_is_left_out_of_the_field(tiny_scene, field_options, tmp_path):
    """cam_02 starts at frame 2 (a rig's late start): the frame-0 field is carved, fitted and
    scored on the three cameras that recorded frame 0, and every frame still has hull points."""
    from mosiv_nerf.reconstructor import NerfFieldReconstructor

    from mosiv_framework.scene import read_scene
    from mosiv_framework.testing.views import with_recorded_frames

    late = read_scene(with_recorded_frames(tiny_scene.root, tmp_path / "late", {"cam_02": (2, 5)}))
    recon = NerfFieldReconstructor(**field_options).fit(late)
    report = recon.extras["nerf_fit"]
    assert report["object_psnr_db"] > MIN_OBJECT_PSNR_DB
    for pts in recon.points.values():
        assert pts.shape == (6, 200, 3)
    assert set(recon.background) == set(late.camera_ids)
