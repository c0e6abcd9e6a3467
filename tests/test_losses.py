"""Identification losses: hand-computed values, object vs scene identity, gradients vs finite
differences (float64)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from mosiv_framework.errors import ConfigError
from mosiv_framework.losses import (
    BUILTIN_LOSSES,
    ObjectChamferLoss,
    ObjectSilhouetteLoss,
    SceneChamferLoss,
    SceneSilhouetteLoss,
    WeightedSum,
    chamfer_m2,
    union_silhouette,
)
from mosiv_framework.metrics import chamfer_mm2
from mosiv_framework.types import GeometryFrames

D = torch.float64


def _pts(*rows: tuple[float, float, float]) -> torch.Tensor:
    return torch.tensor(rows, dtype=D)


def _frames(points: dict[int, list[torch.Tensor]], silhouettes=None) -> GeometryFrames:
    n = len(next(iter(points.values())))
    return GeometryFrames(frames=list(range(n)), points=points, silhouettes=silhouettes)


def test_object_chamfer_hand_computed():
    # frame 0, object 1: pred {(0,0,0)}, target {(0,0,0), (1,0,0)}
    #   pred -> target: 0; target -> pred: (0 + 1) / 2 = 0.5          => 0.5 m^2
    # frame 0, object 2: pred {(0,0,0), (0,2,0)}, target {(0,0,1)}
    #   pred -> target: (1 + (4 + 1)) / 2 = 3; target -> pred: 1       => 4 m^2
    # frame 1: both objects exact                                       => 0
    # loss = mean over frames of the sum over objects = (0.5 + 4 + 0) / 2 = 2.25
    pred = _frames(
        {
            1: [_pts((0, 0, 0)), _pts((5, 5, 5))],
            2: [_pts((0, 0, 0), (0, 2, 0)), _pts((7, 7, 7))],
        }
    )
    target = _frames(
        {
            1: [_pts((0, 0, 0), (1, 0, 0)), _pts((5, 5, 5))],
            2: [_pts((0, 0, 1)), _pts((7, 7, 7))],
        }
    )
    assert ObjectChamferLoss()(pred, target).item() == pytest.approx(2.25, rel=1e-12)
    # scene-wise at frame 0: union pred {(0,0,0) x2, (0,2,0)}, union target {(0,0,0), (1,0,0),
    # (0,0,1)}; pred -> target: (0 + 0 + 4) / 3 = 4/3 (the nearest of (0,2,0) is (0,0,0));
    # target -> pred: (0 + 1 + 1) / 3 = 2/3  => 2; frame 1 (5,5,5),(7,7,7) exact => 0
    assert SceneChamferLoss()(pred, target).item() == pytest.approx((4 / 3 + 2 / 3) / 2, rel=1e-12)


@pytest.mark.parametrize("search", ["kdtree", "brute"])
def test_chamfer_matches_metric_in_metres_squared(search):
    rng = np.random.default_rng(0)
    a, b = rng.random((3000, 3)) * 0.2, rng.random((2500, 3)) * 0.2
    # max_pairs=100_000 makes the brute search work in chunks of 40 and 33 rows
    value = chamfer_m2(torch.tensor(a), torch.tensor(b), max_pairs=100_000, search=search)
    assert value.item() * 1e6 == pytest.approx(chamfer_mm2(a, b), rel=1e-10)
    # float32 points 0.5 m from the origin, 1 mm apart: centring keeps the brute search exact
    near = torch.tensor(a, dtype=torch.float32) + 0.5
    far = near + torch.tensor([1e-3, 0.0, 0.0])
    assert chamfer_m2(near, far, search=search).item() == pytest.approx(2e-6, rel=1e-3)


def test_identical_inputs_give_zero_loss():
    rng = torch.Generator().manual_seed(1)
    points = {k: [torch.rand(50, 3, generator=rng, dtype=D) for _ in range(2)] for k in (1, 2)}
    alpha = {k: torch.rand(2, 3, 8, 8, generator=rng, dtype=D) for k in (1, 2)}
    geo = _frames(points, alpha)
    for name, cls, _, _ in BUILTIN_LOSSES:
        assert cls()(geo, geo).item() == 0.0, name


def _two_objects_swapped():
    """Two well-separated objects; the prediction swaps their identities."""
    a = torch.rand(30, 3, generator=torch.Generator().manual_seed(2), dtype=D) * 0.1
    b = a + torch.tensor([1.0, 0.0, 0.0], dtype=D)
    mask_a = torch.zeros(1, 2, 6, 6, dtype=D)
    mask_a[..., :3] = 1.0  # object 1 covers the left half of each view
    mask_b = 1.0 - mask_a  # object 2 the right half
    target = _frames({1: [a], 2: [b]}, {1: mask_a, 2: mask_b})
    swapped = _frames({1: [b], 2: [a]}, {1: mask_b, 2: mask_a})
    return swapped, target


def test_object_wise_penalises_identity_swap_scene_wise_does_not():
    swapped, target = _two_objects_swapped()
    assert SceneChamferLoss()(swapped, target).item() == pytest.approx(0.0, abs=1e-15)
    assert SceneSilhouetteLoss()(swapped, target).item() == 0.0
    assert SceneSilhouetteLoss(union="clamp-sum")(swapped, target).item() == 0.0
    # object-wise: every point is ~1 m from the other object's points, so the Chamfer of each
    # object is at least 2 * (1 - 0.1)^2; every pixel of each object's alpha is wrong, L1 = 1
    assert ObjectChamferLoss()(swapped, target).item() > 2 * 2 * 0.9**2
    assert ObjectSilhouetteLoss()(swapped, target).item() == pytest.approx(2.0)


def test_silhouette_hand_computed():
    # one frame, one camera, 2 x 2 pixels, two objects
    pred = {
        1: torch.tensor([[[[1.0, 0.5], [0.0, 0.0]]]], dtype=D),
        2: torch.tensor([[[[0.0, 0.5], [1.0, 0.0]]]], dtype=D),
    }
    targ = {
        1: torch.tensor([[[[1.0, 0.0], [0.0, 0.0]]]], dtype=D),
        2: torch.tensor([[[[0.0, 1.0], [0.0, 0.0]]]], dtype=D),
    }
    points = {1: [_pts((0, 0, 0))], 2: [_pts((1, 0, 0))]}
    p, t = _frames(points, pred), _frames(points, targ)
    # object 1: |0.5 - 0| = 0.5 over 4 pixels -> 0.125; object 2: 0.5 + 1 = 1.5 -> 0.375
    assert ObjectSilhouetteLoss()(p, t).item() == pytest.approx(0.125 + 0.375)
    # soft-or union: pred [[1, 1 - 0.5 * 0.5], [1, 0]] = [[1, 0.75], [1, 0]];
    # target [[1, 1], [0, 0]]; |diff| = 0.25 + 1 over 4 pixels
    assert SceneSilhouetteLoss()(p, t).item() == pytest.approx(1.25 / 4)
    # clamp-sum union: pred [[1, 1], [1, 0]] -> |diff| = 1 over 4 pixels
    assert SceneSilhouetteLoss(union="clamp-sum")(p, t).item() == pytest.approx(0.25)


def _geometry_from(x: torch.Tensor, template: GeometryFrames) -> GeometryFrames:
    """Rebuild GeometryFrames whose object-1 frame-0 points are ``x``."""
    points = {k: list(v) for k, v in template.points.items()}
    points[1][0] = x
    return GeometryFrames(template.frames, points, template.silhouettes)


@pytest.mark.parametrize("search", ["kdtree", "brute"])
@pytest.mark.parametrize("loss_cls", [ObjectChamferLoss, SceneChamferLoss])
def test_chamfer_gradient_matches_central_differences(loss_cls, search):
    gen = torch.Generator().manual_seed(3)
    pred = _frames({k: [torch.rand(12, 3, generator=gen, dtype=D) + k] for k in (1, 2)})
    target = _frames({k: [torch.rand(9, 3, generator=gen, dtype=D) + k] for k in (1, 2)})
    loss = loss_cls(max_points=0, search=search)
    x = pred.points[1][0].clone().requires_grad_(True)
    (grad,) = torch.autograd.grad(loss(_geometry_from(x, pred), target), x)

    eps = 1e-6  # small enough that no nearest neighbour changes within +-eps
    numeric = torch.zeros_like(x)
    for idx in np.ndindex(*x.shape):
        plus, minus = x.detach().clone(), x.detach().clone()
        plus[idx] += eps
        minus[idx] -= eps
        numeric[idx] = (
            loss(_geometry_from(plus, pred), target) - loss(_geometry_from(minus, pred), target)
        ) / (2 * eps)
    torch.testing.assert_close(grad, numeric, rtol=1e-6, atol=1e-8)
    assert grad.abs().sum() > 0


@pytest.mark.parametrize("loss_cls", [ObjectSilhouetteLoss, SceneSilhouetteLoss])
def test_silhouette_gradient_matches_central_differences(loss_cls):
    gen = torch.Generator().manual_seed(4)
    alphas = {k: torch.rand(2, 2, 3, 3, generator=gen, dtype=D) for k in (1, 2)}
    targets = {k: torch.rand(2, 2, 3, 3, generator=gen, dtype=D) for k in (1, 2)}
    points = {k: [_pts((0, 0, k))] * 2 for k in (1, 2)}
    target = _frames(points, targets)

    def f(a1: torch.Tensor) -> torch.Tensor:
        return loss_cls()(_frames(points, {1: a1, 2: alphas[2]}), target)

    # gradcheck compares the analytic Jacobian with central differences in float64
    assert torch.autograd.gradcheck(f, (alphas[1].clone().requires_grad_(True),), eps=1e-6)


def test_subsampling_is_seeded_and_bounded():
    gen = torch.Generator().manual_seed(5)
    pred = _frames({1: [torch.rand(500, 3, generator=gen, dtype=D)]})
    target = _frames({1: [torch.rand(400, 3, generator=gen, dtype=D)]})
    first = [ObjectChamferLoss(max_points=64, seed=9)(pred, target).item() for _ in range(2)]
    loss = ObjectChamferLoss(max_points=64, seed=9)
    again = [loss(pred, target).item(), loss(pred, target).item()]
    assert first[0] == first[1] == again[0]  # same seed, same first subset
    assert again[1] != again[0]  # successive calls draw new subsets
    full = ObjectChamferLoss(max_points=0)(pred, target).item()
    assert again[0] > full  # sparser sets are farther apart on average


def test_weighted_sum_uses_recipe_weights():
    swapped, target = _two_objects_swapped()
    cd = ObjectChamferLoss(weight=2.0)
    sil = ObjectSilhouetteLoss()
    objective = WeightedSum({"chamfer": cd, "silhouette": sil}, weights={"silhouette": 0.5})
    total, values = objective.evaluate(swapped, target)
    expected = 2.0 * cd(swapped, target) + 0.5 * sil(swapped, target)
    assert total.item() == pytest.approx(expected.item())
    assert values["silhouette"] == pytest.approx(2.0)
    assert objective(swapped, target).item() == pytest.approx(total.item())
    with pytest.raises(ConfigError, match="unknown loss terms"):
        WeightedSum({"chamfer": cd}, weights={"chamfr": 1.0})


def test_bad_options_and_inputs_are_named():
    with pytest.raises(ConfigError, match=r"valid options: \['weight', 'max_points'"):
        ObjectChamferLoss(max_point=10)
    with pytest.raises(ConfigError, match="kdtree"):
        SceneChamferLoss(search="octree")
    with pytest.raises(ConfigError, match="soft-or"):
        SceneSilhouetteLoss(union="max")
    with pytest.raises(ConfigError, match="weight"):
        ObjectSilhouetteLoss(weight=-1.0)
    swapped, target = _two_objects_swapped()
    no_alpha = GeometryFrames(swapped.frames, swapped.points, None)
    with pytest.raises(ValueError, match="no silhouettes"):
        ObjectSilhouetteLoss()(no_alpha, target)
    shifted = GeometryFrames([5], swapped.points, swapped.silhouettes)
    with pytest.raises(ValueError, match="frames"):
        ObjectChamferLoss()(shifted, target)
    assert union_silhouette([torch.ones(2), torch.zeros(2)]).tolist() == [1.0, 1.0]
