"""The plugin is discovered through its entry point and builds a working renderer."""

from __future__ import annotations

import math

import pytest
import torch

from mosiv_framework.errors import ConfigError
from mosiv_framework.interfaces import Renderer
from mosiv_framework.registry import get_registry
from mosiv_framework.scene.cameras import Camera
from mosiv_framework.types import GaussianFrames


def test_gauss_torch_renderer_is_registered_and_renders():
    registry = get_registry(reload=True)
    component = registry.get("renderer", "gauss-torch")
    assert component.distribution == "mosiv-gauss"
    renderer = registry.create("renderer", "gauss-torch", {"tile_size": 8, "background": [0, 0, 1]})
    assert isinstance(renderer, Renderer)
    cam = Camera.look_at((0.0, -2.0, 0.0), (0.0, 0.0, 0.0), width=16, height=12, fx=20.0)
    gauss = GaussianFrames(
        means=torch.zeros(1, 1, 3),
        radii=torch.full((1, 1), 0.1),
        colors=torch.tensor([[1.0, 0.0, 0.0]]),
        opacities=torch.tensor([0.9]),
        object_ids=torch.tensor([1]),
    )
    out = renderer.render(gauss, cam, frame=0, n_objects=1)
    assert out.rgb.shape == (12, 16, 3) and out.object_alpha.shape == (1, 12, 16)
    # the red Gaussian projects to the image centre (u, v) = (8, 6) with a 1 px std-dev, half a
    # pixel from the centre of pixel (row 6, column 8) along each axis: alpha = 0.9 exp(-0.25);
    # the corners show only the blue background
    assert out.rgb[6, 8, 0].item() == pytest.approx(0.9 * math.exp(-0.25), rel=1e-5)
    assert out.rgb[0, 0].tolist() == [0.0, 0.0, 1.0]


def test_bad_options_are_rejected_with_the_valid_range():
    registry = get_registry()
    with pytest.raises(ConfigError, match="max_alpha"):
        registry.create("renderer", "gauss-torch", {"max_alpha": 1.5})
    with pytest.raises(ConfigError, match="valid options"):
        registry.create("renderer", "gauss-torch", {"tile": 8})
