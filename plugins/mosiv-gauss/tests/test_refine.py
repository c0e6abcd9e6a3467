"""Per-frame refinement (``mosiv_gauss.refine``): neighbourhoods stay inside an object, the
offsets recover a displacement the model lacks, and frames outside a batch do not move."""

from __future__ import annotations

import torch
from mosiv_gauss.dynamic_options import DynamicGaussOptions
from mosiv_gauss.options import TorchRasterizerOptions
from mosiv_gauss.rasterizer import rasterize
from mosiv_gauss.refine import object_neighbours, refine_frames, smoothness
from mosiv_gauss.train import TrainingData

from mosiv_framework.scene.cameras import Camera
from mosiv_framework.types import GaussianFrames

#: hull voxel of the synthetic setup (m)
VOXEL = 0.01


def test_neighbours_are_the_nearest_points_of_the_same_object():
    gen = torch.Generator().manual_seed(0)
    means = torch.rand(60, 3, generator=gen)
    ids = torch.tensor([1] * 30 + [2] * 30)
    # object 2 sits right on top of object 1: the nearest point overall is often the other's
    means[30:] = means[:30] + 1e-4
    nbrs = object_neighbours(means, ids, 4)
    assert nbrs.shape == (60, 4)
    assert torch.equal(ids[nbrs], ids[:, None].expand(-1, 4))
    for g in (0, 17, 45):
        mine = torch.nonzero(ids == ids[g]).squeeze(1)
        d = (means[mine] - means[g]).norm(dim=1)
        d[mine == g] = float("inf")
        assert set(nbrs[g].tolist()) == set(mine[d.argsort()[:4]].tolist())


def test_neighbours_do_not_depend_on_the_block_size(monkeypatch):
    import mosiv_gauss.refine as refine

    gen = torch.Generator().manual_seed(1)
    means = torch.rand(300, 3, generator=gen)
    ids = (torch.rand(300, generator=gen) < 0.5).long() + 1
    whole = object_neighbours(means, ids, 5)
    monkeypatch.setattr(refine, "NEIGHBOUR_BLOCK", 7)
    assert torch.equal(object_neighbours(means, ids, 5), whole)


def test_smoothness_is_zero_for_a_rigid_translation_and_counts_differences():
    nbrs = object_neighbours(torch.rand(10, 3), torch.ones(10, dtype=torch.long), 3)
    same = torch.tensor([0.5, -1.0, 2.0]).expand(2, 10, 3)
    assert smoothness(same, torch.zeros(2, 10), nbrs).item() == 0.0
    bumped = same.clone()
    bumped[1, 4, 0] += 1.0
    assert smoothness(bumped, torch.zeros(2, 10), nbrs).item() > 0.0


def _blob(n: int = 40, seed: int = 0) -> GaussianFrames:
    """A ball of n Gaussians of one object about (0, 0, 0.3), the same at two frames."""
    gen = torch.Generator().manual_seed(seed)
    centre = torch.tensor([0.0, 0.0, 0.3])
    means = centre + 0.03 * (torch.rand(n, 3, generator=gen) - 0.5)
    return GaussianFrames(
        means=means.expand(2, n, 3).clone(),
        radii=torch.full((2, n), 0.008),
        colors=torch.rand(n, 3, generator=gen) * 0.5 + 0.3,
        opacities=torch.full((n,), 0.9),
        object_ids=torch.ones(n, dtype=torch.long),
    )


def _views(gaussians: GaussianFrames, cameras, background):
    rgb, masks = [], []
    opts = TorchRasterizerOptions(tile_size=8)
    for t in range(gaussians.n_frames):
        row_rgb, row_mask = [], []
        for c, cam in enumerate(cameras):
            out, _ = rasterize(
                gaussians, cam, frame=t, n_objects=1, options=opts, background=background[c]
            )
            row_rgb.append(out.rgb)
            row_mask.append((out.object_alpha > 0.5).float())
        rgb.append(torch.stack(row_rgb))
        masks.append(torch.stack(row_mask))
    return torch.stack(rgb), torch.stack(masks)


def test_refinement_recovers_a_per_frame_shift_the_model_lacks():
    cameras = [
        Camera.look_at(eye, (0.0, 0.0, 0.3), width=32, height=32, fx=160.0)
        for eye in ((0.6, 0.0, 0.3), (0.0, -0.6, 0.35), (0.0, 0.1, 0.9))
    ]
    background = torch.full((3, 32, 32, 3), 0.1)
    model = _blob()
    truth = _blob()
    shift = torch.tensor([1.0, -0.5, 0.7]) * VOXEL  # frame 1 only
    truth.means[1] += shift
    rgb, masks = _views(truth, cameras, background)
    data = TrainingData(
        rgb=rgb, masks=masks, cameras=cameras, background=background, voxel_size=VOXEL
    )
    opts = DynamicGaussOptions(
        refine_iterations=150,
        views_per_step=3,
        tile_size=8,
        lambda_refine_smooth=0.1,
        lr_refine_position=0.05,
        progress=False,
    )
    refined, history = refine_frames(
        model, data, background, opts, generator=torch.Generator().manual_seed(0)
    )
    moved = (refined.means - model.means).mean(dim=1)  # [2, 3] mean offset per frame
    # frame 1 follows the shift to within a fifth of a voxel per axis; frame 0 stays put
    assert (moved[1] - shift).abs().max() < 0.2 * VOXEL, (moved[1] / VOXEL, shift / VOXEL)
    assert moved[0].abs().max() < 0.2 * VOXEL, moved[0] / VOXEL
    assert history[-1] < history[0]
    assert torch.equal(refined.colors, model.colors)
    assert torch.equal(refined.object_ids, model.object_ids)


def test_a_frame_outside_the_batch_does_not_move_on_stale_momentum(monkeypatch):
    import mosiv_gauss.refine as refine

    monkeypatch.setattr(refine, "FINAL_LR_FRACTION", 1.0)  # same step sizes in both runs
    cameras = [Camera.look_at((0.6, 0.0, 0.3), (0.0, 0.0, 0.3), width=24, height=24, fx=120.0)]
    background = torch.full((1, 24, 24, 3), 0.1)
    model = _blob(20)
    truth = _blob(20)
    truth.means += 0.5 * VOXEL
    rgb, masks = _views(truth, cameras, background)
    data = TrainingData(
        rgb=rgb, masks=masks, cameras=cameras, background=background, voxel_size=VOXEL
    )

    def run(steps: int) -> torch.Tensor:
        # one view per step over two frames: steps 1 and 2 train one frame each, step 3 one
        # of them again; the other must keep exactly its position after step 2
        opts = DynamicGaussOptions(
            refine_iterations=steps, views_per_step=1, tile_size=8, progress=False
        )
        refined, _ = refine_frames(
            model, data, background, opts, generator=torch.Generator().manual_seed(0)
        )
        return refined.means

    two, three = run(2), run(3)
    changed = [not torch.equal(two[t], three[t]) for t in range(2)]
    assert sorted(changed) == [False, True], changed
    assert not torch.equal(two[0], model.means[0]) and not torch.equal(two[1], model.means[1])
