"""The parity suite catches a backend that gets one law wrong, and passes a correct one.

The tiny test backend delegates to the installed warp-mpm but treats plasticine's yield stress
three times too high, in its law kernels and in its rollouts alike: a realistic bug (a unit or
factor slip in one law) that a third-party author could make.
"""

from __future__ import annotations

import pytest

from mosiv_framework.interfaces import Simulator
from mosiv_framework.laws import FAMILIES
from mosiv_framework.registry import get_registry
from mosiv_framework.testing import check_backend
from mosiv_framework.types import ObjectParams

pytest.importorskip("mosiv_warp_mpm", reason="the parity demonstration wraps warp-mpm")


class YieldStressSlip(Simulator):
    """warp-mpm with plasticine's yield stress scaled by 3 (the deliberate bug)."""

    def __init__(self, **options):
        self.inner = get_registry().create("simulator", "warp-mpm", options)
        self.supported_laws = self.inner.supported_laws

    @staticmethod
    def _slip(family, values):
        if family != "plasticine":
            return values
        return {**values, "yield_stress": values["yield_stress"] * 3.0}

    def evaluate_law(self, family, F, values, **kwargs):
        return self.inner.evaluate_law(family, F, self._slip(family, values), **kwargs)

    def rollout(self, particles, params, *, world, frames):
        objects = {
            k: ObjectParams(p.family, self._slip(p.family, p.values))
            for k, p in params.objects.items()
        }
        slipped = type(params)(
            objects, params.initial_velocity, params.ground_friction, params.terms
        )
        return self.inner.rollout(particles, slipped, world=world, frames=frames)


def test_one_line_check_catches_the_wrong_law():
    report = check_backend(
        YieldStressSlip(grid=32, substeps=40), laws=("elastic", "plasticine"), gradients=False
    )
    failed = {(r.law, r.check) for r in report.failures}
    assert ("plasticine", "law-return") in failed, report.table()
    assert any(law == "plasticine" and check.startswith("forward") for law, check in failed)
    assert not any(law == "elastic" for law, _ in failed), report.table()


def test_a_correct_backend_passes_its_own_reference():
    report = check_backend("warp-mpm", reference=None, laws=("elastic", "sand"))
    assert report.passed, report.table()


def test_warp_and_taichi_agree_on_every_law():
    """The two independently written backends, forward: laws vs reference, positions and
    centroids after 1 and 10 frames of every standard scene, within TOLERANCES."""
    pytest.importorskip("mosiv_taichi_mpm", reason="needs both MPM backends")
    from mosiv_framework.testing.parity import run_parity

    registry = get_registry()
    report = run_parity(
        {
            name: (
                lambda name=name, **o: registry.create("simulator", name, {**o, "device": "cpu"})
            )
            for name in ("warp-mpm", "taichi-mpm")
        },
        gradients=False,
    )
    assert report.passed, report.table()
    # every law (stress and return map, each backend) and every scene (one per law and the
    # collision; four checks each) was run
    assert len(report.results) == len(FAMILIES) * 2 * 2 + (len(FAMILIES) + 1) * 4


@pytest.mark.parametrize("scene", [*FAMILIES, "collision"])
def test_warp_and_taichi_gradients_agree(scene, parity_pair):
    """The two backends' gradients of one rollout loss w.r.t. every parameter (law
    parameters, initial velocities, frictions), per scene, within TOLERANCES."""
    from mosiv_framework.testing.parity import check_gradients

    (result,) = check_gradients(parity_pair, scene)
    assert result.passed, result


@pytest.fixture(scope="module")
def parity_pair():
    pytest.importorskip("mosiv_taichi_mpm", reason="needs both MPM backends")
    from mosiv_framework.testing.parity import SCENE_OPTIONS

    registry = get_registry()
    return {
        name: registry.create("simulator", name, {**SCENE_OPTIONS, "device": "cpu"})
        for name in ("warp-mpm", "taichi-mpm")
    }


def test_warp_and_taichi_apply_the_same_expression(parity_pair):
    """The expression term's node-local features on the collision scene: both backends'
    positions after 1 and 4 frames within TOLERANCES, and their gradients w.r.t. every
    coefficient within the gradient tolerance."""
    import torch

    from mosiv_framework.testing.parity import TOLERANCES, WORLD, standard_scenes
    from mosiv_framework.testing.shapes import default_params

    particles, velocities = standard_scenes()["collision"]
    values = {"a_x:1": 0.8, "a_y:v_y": -1.5, "a_z:|v|v_z": -0.4, "a_x:h": -3.0}
    values.update({"a_y:t": 2.0, "a_z:x": 1.0})
    weights = torch.linspace(0.5, 1.5, len(particles))
    positions, grads = {}, {}
    for name, sim in parity_pair.items():
        params = default_params(particles, velocities=velocities)
        params.terms["expression"] = {
            n: torch.tensor(v, requires_grad=True) for n, v in values.items()
        }
        traj = sim.rollout(particles, params, world=WORLD, frames=4)
        loss = sum(((traj.positions[f] - 0.5) ** 2).sum(1).mul(weights).mean() for f in (1, 4))
        loss.backward()
        positions[name] = traj.positions.detach()
        grads[name] = torch.stack([params.terms["expression"][n].grad for n in values])
    warp, taichi = positions["warp-mpm"], positions["taichi-mpm"]
    for f in (1, 4):
        gap = float((warp[f] - taichi[f]).norm(dim=1).max()) / WORLD.extent
        assert gap <= TOLERANCES["positions_frac"], (f, gap)
    a, b = grads["warp-mpm"], grads["taichi-mpm"]
    assert (a.abs() > 0).all(), a
    rel = ((a - b).abs() / torch.maximum(a.abs(), b.abs())).max()
    assert rel <= TOLERANCES["gradient_rel"], (a, b)
