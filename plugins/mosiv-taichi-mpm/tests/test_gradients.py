"""Rollout gradients against central finite differences (within 5%).

The shared ``gradient_check`` covers every law parameter, rho, the initial velocity and ground
friction for one object of each law of OWN_CHECK thrown onto the ground; the shared
``collision_gradient_check`` covers multi-field contact between two objects (the same checks as
on warp-mpm); one more check covers contact friction and the body-force term parameters.
"""

import pytest
import torch

from mosiv_framework.testing import physics_cases
from mosiv_framework.testing.shapes import block, combine, default_params
from mosiv_framework.types import World

#: Laws checked against differences here, one per path through this backend's stress adjoint:
#: sand the SVD with a return map (the path of plasticine, non-newtonian, snow and the corotated
#: laws), newtonian no SVD (elastic's path; kernels.py: needs_svd). Every law's gradients, these
#: two included, are held to warp-mpm's by the parity test (tests/test_parity.py), and
#: warp-mpm's to differences law by law (plugins/mosiv-warp-mpm/tests): so each law is checked
#: against differences through the other backend. Each check here compiles its law's kernels
#: and their adjoints (three to four minutes of a CI core with Taichi's cache cold), which is
#: why not every law runs here too.
OWN_CHECK = ("sand", "newtonian")


@pytest.mark.parametrize("family", OWN_CHECK)
def test_shared_gradient_check(family, simulator_factory):
    report = physics_cases.gradient_check(simulator_factory, family)
    print(family, report)
    assert any(abs(ad) > 0 for ad, _fd in report.values())


def test_collision_gradient_check(simulator_factory):
    # per-object fields, contact normals and the Coulomb projection between fields
    report = physics_cases.collision_gradient_check(simulator_factory)
    print("collision", report)
    assert abs(report["obj2.friction"][0]) > 0, "contact friction of ball 2 has no gradient"


def test_a_rollout_between_forward_and_backward_leaves_the_gradients_alone(simulator_factory):
    # rollouts of one layout share the engine's parameter fields; the backward loads its own
    report = physics_cases.interleaved_rollouts_check(simulator_factory)
    print("interleaved", report)


def _central_difference(loss_of, value: torch.Tensor, h: float) -> torch.Tensor:
    out = torch.zeros_like(value).reshape(-1)
    for i in range(value.numel()):
        t = value.detach().clone().reshape(-1)
        t[i] += h
        up = loss_of(t.reshape(value.shape)).item()
        t[i] -= 2 * h
        down = loss_of(t.reshape(value.shape)).item()
        out[i] = (up - down) / (2 * h)
    return out.reshape(value.shape)


def _assert_close(name, ad, fd, loss_scale):
    err = (ad - fd).abs().max().item()
    tol = 0.05 * fd.abs().max().item() + 1e-6 * loss_scale
    assert err <= tol, f"{name}: autograd {ad.tolist()} vs finite difference {fd.tolist()}"


def test_contact_friction_and_term_gradients(simulator_factory):
    """Two blocks pressed together while sliding past each other (friction) and thrown onto the
    table, with drag, wind, material damping and ground restitution on: d loss / d (friction of
    each object, drag coefficients, wind, viscosity, restitution) match differences."""
    sim = simulator_factory(grid=16, substeps=30)
    world = World((0.0, 0.0, 0.0), (0.5, 0.5, 0.5), gravity=(0.0, 0.0, -9.8), ground_height=0.0)
    a = block((0.15, 0.2, 0.02), (0.25, 0.3, 0.1), spacing=1.0 / 48, object_id=1)
    b = block((0.26, 0.2, 0.02), (0.34, 0.3, 0.1), spacing=1.0 / 48, object_id=2)
    p = combine([a, b])
    params = default_params(
        p,
        overrides={1: {"friction": 0.5}, 2: {"friction": 0.3}},
        # thrown down so that they land and bounce: ground restitution acts on arriving speed
        velocities={1: (0.8, 0.6, -0.8), 2: (-0.8, -0.6, -0.8)},
        ground_friction=0.2,
        terms={
            "linear_drag": {"coefficient": 0.5},
            "quadratic_drag": {"coefficient": 0.3},
            "wind": {"acceleration": [0.5, -0.3, 0.0]},
            "material_damping": {"viscosity": 20.0},
            "ground_restitution": {"coefficient": 0.5},
        },
    )
    weights = torch.randn(len(p), 3, generator=torch.Generator().manual_seed(1))
    names = [
        "obj1.friction", "obj2.friction", "term.linear_drag.coefficient",
        "term.quadratic_drag.coefficient", "term.wind.acceleration",
        "term.material_damping.viscosity", "term.ground_restitution.coefficient",
    ]  # fmt: skip
    named = dict(params.named_tensors())

    def loss_with(overrides):
        traj = sim.rollout(p, params.with_tensors(overrides), world=world, frames=3)
        return ((traj.positions[1:] - traj.positions[:1]) * weights).sum(dim=(1, 2)).mean()

    leaves = {n: named[n].detach().clone().requires_grad_(True) for n in names}
    loss = loss_with(leaves)
    grads = torch.autograd.grad(loss, [leaves[n] for n in names])
    # steps: 2e-2 in general; the viscosity (20 Pa s) needs a larger one to lift the loss change
    # above float32 round-off, the restitution a smaller one because the loss bends in e (which
    # nodes bounce changes with it; at 5e-2 the difference is off by 9%)
    steps = {"term.material_damping.viscosity": 0.5, "term.ground_restitution.coefficient": 5e-3}
    for n, g in zip(names, grads):
        with torch.no_grad():
            h = steps.get(n, 2e-2)
            fd = _central_difference(lambda t, n=n: loss_with({n: t}), named[n], h=h)
        _assert_close(n, g, fd, abs(loss.item()))
    assert grads[0].abs().item() > 0 and grads[1].abs().item() > 0, "contact friction inactive"
    assert grads[-2].abs().item() > 0 and grads[-1].abs().item() > 0, "new terms inactive"
