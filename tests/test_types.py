"""Core data types refuse input that would only fail later, naming what is wrong."""

from __future__ import annotations

import pytest
import torch

from mosiv_framework.types import ParticleSet


def particles(positions: torch.Tensor, volumes: torch.Tensor) -> ParticleSet:
    ids = torch.tensor([1, 1, 2, 2])
    return ParticleSet(positions, volumes, ids, {1: "elastic", 2: "sand"})


def test_valid_particles_are_accepted():
    p = particles(torch.rand(4, 3), torch.full((4,), 1e-6))
    assert len(p) == 4 and p.object_list == [1, 2]


@pytest.mark.parametrize("bad", [float("nan"), float("inf")])
def test_a_non_finite_position_is_refused_with_its_object(bad):
    pos = torch.rand(4, 3)
    pos[2, 1] = bad
    with pytest.raises(ValueError, match=r"positions: 1 of 4 .* object 2"):
        particles(pos, torch.full((4,), 1e-6))


@pytest.mark.parametrize("bad", [0.0, -1e-6, float("nan")])
def test_a_volume_that_is_not_positive_is_refused(bad):
    vol = torch.full((4,), 1e-6)
    vol[1] = bad
    with pytest.raises(ValueError, match=r"volumes: 1 of 4 .* object 1"):
        particles(torch.rand(4, 3), vol)
