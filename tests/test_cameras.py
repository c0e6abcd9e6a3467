"""Camera geometry in the OpenCV convention of docs/SCENE_FORMAT.md, against hand-computed pixels."""

import json
import math

import numpy as np
import pytest
import torch

from mosiv_framework.scene import Camera, is_rigid, rigidity_problems

# A camera turned 90 degrees about the world x axis: it looks along world +y with world +z up.
# Rows of R are the camera axes in world coordinates: x_cam = world x, y_cam (down) = -world z,
# z_cam (forward) = world y.
R90 = [[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]]
T = [0.1, 0.2, 2.0]


def simple_camera() -> Camera:
    m = np.eye(4)
    m[:3, :3] = R90
    m[:3, 3] = T
    return Camera(
        "cam_00", width=64, height=48, fx=100.0, fy=120.0, cx=32.0, cy=24.0, world_to_camera=m
    )


def test_projection_matches_hand_computed_pixels():
    cam = simple_camera()
    points = torch.tensor([[0.5, 1.0, 0.3], [-0.4, 0.5, -0.2]], dtype=torch.float64)
    uv, depth = cam.project(points)
    # point 1: R x = (0.5, -0.3, 1.0); + t = (0.6, -0.1, 3.0)
    #   u = 100 * 0.6 / 3.0 + 32 = 52.0,  v = 120 * -0.1 / 3.0 + 24 = 20.0,  depth 3.0
    # point 2: R x = (-0.4, 0.2, 0.5); + t = (-0.3, 0.4, 2.5)
    #   u = 100 * -0.3 / 2.5 + 32 = 20.0, v = 120 * 0.4 / 2.5 + 24 = 43.2,  depth 2.5
    expected_uv = torch.tensor([[52.0, 20.0], [20.0, 43.2]], dtype=torch.float64)
    torch.testing.assert_close(uv, expected_uv, rtol=0, atol=1e-12)
    torch.testing.assert_close(depth, torch.tensor([3.0, 2.5], dtype=torch.float64))


def test_camera_center_and_inverse():
    cam = simple_camera()
    # c = -R^T t; R^T t = (0.1, 2.0, -0.2)
    torch.testing.assert_close(
        cam.camera_center, torch.tensor([-0.1, -2.0, 0.2], dtype=torch.float64)
    )
    torch.testing.assert_close(
        cam.camera_to_world @ cam.world_to_camera, torch.eye(4, dtype=torch.float64)
    )


def test_unproject_inverts_project():
    cam = simple_camera()
    gen = torch.Generator().manual_seed(0)
    # points in front of the camera: world y > -2 + 0.5 keeps depth > 0.5
    pts = torch.rand(100, 3, generator=gen, dtype=torch.float64) * 2.0 - 1.0
    uv, depth = cam.project(pts)
    assert bool((depth > 0).all())
    torch.testing.assert_close(cam.unproject(uv, depth), pts, rtol=0, atol=1e-12)


def test_project_is_differentiable_against_finite_differences():
    cam = simple_camera()
    pts = torch.tensor(
        [[0.5, 1.0, 0.3], [-0.4, 0.5, -0.2]], dtype=torch.float64, requires_grad=True
    )
    assert torch.autograd.gradcheck(lambda p: cam.project(p)[0], (pts,))
    assert torch.autograd.gradcheck(lambda p: cam.project(p)[1], (pts,))


def test_rays_pass_through_pixel_centres():
    cam = simple_camera()
    origins, dirs = cam.rays(dtype=torch.float64)
    assert origins.shape == dirs.shape == (48, 64, 3)
    torch.testing.assert_close(dirs.norm(dim=-1), torch.ones(48, 64, dtype=torch.float64))
    torch.testing.assert_close(origins[7, 11], cam.camera_center)
    # a point 1.7 m along the ray of row 7, column 11 lands on that pixel's centre (11.5, 7.5)
    uv, depth = cam.project((origins[7, 11] + 1.7 * dirs[7, 11])[None])
    torch.testing.assert_close(uv[0], torch.tensor([11.5, 7.5], dtype=torch.float64))
    assert float(depth[0]) > 0


def test_look_at_reproduces_the_hand_built_camera():
    cam = simple_camera()
    eye = cam.camera_center.tolist()
    target = [eye[0], eye[1] + 1.0, eye[2]]
    built = Camera.look_at(eye, target, (0.0, 0.0, 1.0), width=64, height=48, fx=100.0, fy=120.0)
    torch.testing.assert_close(built.world_to_camera, cam.world_to_camera, rtol=0, atol=1e-12)
    assert (built.cx, built.cy) == (32.0, 24.0)


def test_look_at_properties():
    eye, target = (1.3, -0.7, 0.9), (0.1, 0.2, 0.3)
    cam = Camera.look_at(eye, target, width=40, height=30, fov_deg=60.0)
    assert cam.is_rigid and is_rigid(cam.world_to_camera, atol=1e-12)
    assert float(torch.linalg.det(cam.rotation)) == pytest.approx(1.0, abs=1e-12)
    torch.testing.assert_close(cam.camera_center, torch.tensor(eye, dtype=torch.float64))
    # horizontal field of view: fx = (W / 2) / tan(fov / 2)
    assert cam.fx == pytest.approx(20.0 / math.tan(math.radians(30.0)))
    # the target projects to the principal point at its distance
    uv, depth = cam.project(torch.tensor([target], dtype=torch.float64))
    torch.testing.assert_close(uv[0], torch.tensor([20.0, 15.0], dtype=torch.float64))
    assert float(depth[0]) == pytest.approx(float(np.linalg.norm(np.subtract(target, eye))))
    # world up points up in the image (smaller v)
    above = torch.tensor([[target[0], target[1], target[2] + 0.1]], dtype=torch.float64)
    assert float(cam.project(above)[0][0, 1]) < 15.0
    # right of the view = forward x up, which lands at larger u
    forward = np.subtract(target, eye)
    right = np.cross(forward, (0.0, 0.0, 1.0))
    beside = torch.from_numpy(np.add(target, 0.1 * right / np.linalg.norm(right))[None])
    assert float(cam.project(beside)[0][0, 0]) > 20.0


def test_look_at_rejects_degenerate_input():
    with pytest.raises(ValueError, match="parallel"):
        Camera.look_at((0, 0, 2), (0, 0, 0), width=8, height=8, fov_deg=40)
    with pytest.raises(ValueError, match="coincide"):
        Camera.look_at((1, 1, 1), (1, 1, 1), width=8, height=8, fov_deg=40)
    with pytest.raises(ValueError, match="exactly one"):
        Camera.look_at((1, 0, 0), (0, 0, 0), width=8, height=8)


def test_dict_round_trip_is_json():
    cam = simple_camera()
    data = json.loads(json.dumps(cam.to_dict()))
    back = Camera.from_dict(data)
    assert back.to_dict() == cam.to_dict()
    with pytest.raises(ValueError, match="fx"):
        Camera.from_dict({k: v for k, v in data.items() if k != "fx"})


def test_rigidity_check():
    rigid = simple_camera().world_to_camera.numpy()
    assert rigidity_problems(rigid) == []
    scaled = rigid.copy()
    scaled[:3, :3] *= 1.1
    assert any("orthonormal" in r for r in rigidity_problems(scaled))
    reflected = rigid.copy()
    reflected[0, :3] *= -1.0
    assert any("determinant" in r for r in rigidity_problems(reflected))
    bad_row = rigid.copy()
    bad_row[3] = [0.0, 0.0, 0.5, 1.0]
    assert any("last row" in r for r in rigidity_problems(bad_row))
    assert "shape" in rigidity_problems(np.eye(3))[0]
    nan = rigid.copy()
    nan[0, 3] = np.nan
    assert "non-finite" in rigidity_problems(nan)[0]
    assert "numbers" in rigidity_problems([["a"] * 4] * 4)[0]
    # a rotation rounded to 6 digits, as a hand-written cameras.json would have, is still rigid
    assert is_rigid(
        np.round(
            Camera.look_at((1, 2, 1), (0, 0, 0), width=8, height=8, fx=10).world_to_camera.numpy(),
            6,
        )
    )
