"""The ``expression`` term in taichi-mpm: its node-local features (mosiv_framework.expression)
added to every grid node's acceleration.

- analytic: on a free body the centroid follows symplectic Euler of the law at the centre of
  mass (quadratic B-splines reproduce linear features, APIC conserves momentum): a constant
  expression is a change of gravity, a = -c v decays the velocity as (1 - c dt)^n, a spring in
  the height and a jerk in time follow their recursion;
- gradients of a rollout loss w.r.t. every kind of coefficient match central differences;
- the other objects' features (warp-mpm's only) and unknown names are refused, naming what is
  valid.
"""

from __future__ import annotations

import pytest
import torch

from mosiv_framework.errors import ConfigError
from mosiv_framework.expression import AXES
from mosiv_framework.testing.physics_cases import central_difference
from mosiv_framework.testing.shapes import block, default_params
from mosiv_framework.types import World

FPS = 24.0
FREE = World((0.0, 0.0, 0.0), (1.0, 1.0, 1.0), gravity=(0.0, 0.0, 0.0), ground_height=None)
#: float32 round-off of centroid positions (m) and velocities (m/s) over a few dozen substeps
POSITION_TOL = 3e-5
VELOCITY_TOL = 3e-5
#: autograd against central differences (steps of 5 % of each coefficient: it enters the node
#: update linearly), relative
FD_TOL = 0.03
FD_STEP = 5e-2


@pytest.fixture(scope="module")
def sim(simulator_factory):
    return simulator_factory(grid=16, substeps=10)


def _block(centre, half=0.05):
    lo, hi = tuple(c - half for c in centre), tuple(c + half for c in centre)
    return block(lo, hi, spacing=0.025, object_id=1)


def _with_expression(particles, values: dict[str, float], velocity):
    params = default_params(particles, velocities={1: velocity})
    params.terms["expression"] = {n: torch.tensor(float(v)) for n, v in values.items()}
    return params


def _centroids(sim, particles, params, world, frames):
    with torch.no_grad():
        traj = sim.rollout(particles, params, world=world, frames=frames)
    return traj, traj.centroids()[1].double()


def test_the_term_is_listed(sim):
    assert "expression" in sim.supported_terms


def test_a_constant_expression_is_a_change_of_gravity(sim):
    """a_z:1 = -2 under g = -9.8: the scheme's free fall under -11.8 m/s^2."""
    world = World((0.0, 0.0, 0.0), (1.0, 1.0, 1.0), gravity=(0.0, 0.0, -9.8), ground_height=None)
    p = _block((0.5, 0.5, 0.6))
    v0 = torch.tensor([0.3, 0.0, 1.0], dtype=torch.float64)
    frames = 6
    _, got = _centroids(sim, p, _with_expression(p, {"a_z:1": -2.0}, (0.3, 0.0, 1.0)), world, 6)
    dt = 1.0 / (FPS * sim.options.substeps)
    n = sim.options.substeps * torch.arange(frames + 1, dtype=torch.float64)[:, None]
    g = torch.tensor([0.0, 0.0, -11.8], dtype=torch.float64)
    expected = p.positions.double().mean(0) + v0 * n * dt + g * dt**2 * n * (n + 1) / 2
    assert (got - expected).abs().max() < POSITION_TOL


def test_linear_drag_expression_decays_the_velocity_geometrically(sim):
    """a = -c v on every axis (c = 2 1/s): each substep multiplies the velocity by 1 - c dt."""
    c = 2.0
    p = _block((0.4, 0.5, 0.5))
    v0 = torch.tensor([1.0, -0.5, 0.5], dtype=torch.float64)
    params = _with_expression(p, {f"a_{a}:v_{a}": -c for a in AXES}, (1.0, -0.5, 0.5))
    traj, _ = _centroids(sim, p, params, FREE, 4)
    dt = 1.0 / (FPS * sim.options.substeps)
    n = sim.options.substeps * torch.arange(5, dtype=torch.float64)
    expected = v0[None] * (1 - c * dt) ** n[:, None]
    assert (traj.velocities.double().mean(dim=1) - expected).abs().max() < VELOCITY_TOL


def test_height_and_time_features_follow_the_centroid_recursion(sim):
    """a_z = -30 h (a spring towards the plane z = 0, here the height without a ground) and
    a_x = 4 t (a jerk): U += dt a(C, t); C += dt U, substep by substep, frames included."""
    k, jerk = 30.0, 4.0
    p = _block((0.3, 0.5, 0.55))
    params = _with_expression(p, {"a_z:h": -k, "a_x:t": jerk}, (0.2, 0.0, 0.0))
    frames, substeps = 6, sim.options.substeps
    dt = 1.0 / (FPS * substeps)
    _, got = _centroids(sim, p, params, FREE, frames)
    c = p.positions.double().mean(0)
    u = torch.tensor([0.2, 0.0, 0.0], dtype=torch.float64)
    expected = [c.clone()]
    for i in range(substeps * frames):
        u = u + dt * torch.tensor([jerk * i * dt, 0.0, -k * float(c[2])], dtype=torch.float64)
        c = c + dt * u
        if (i + 1) % substeps == 0:
            expected.append(c.clone())
    assert (got - torch.stack(expected)).abs().max() < POSITION_TOL


def _loss(sim, particles, params, world, frames, weights):
    traj = sim.rollout(particles, params, world=world, frames=frames)
    return ((traj.positions[1:] - traj.positions[:1]) * weights).sum(dim=(1, 2)).mean()


def test_gradients_of_every_node_feature_match_finite_differences(sim):
    """A block thrown onto a table with friction under an expression of every kind of
    node-local feature: d loss / d coefficient, per coefficient."""
    world = World((0.0, 0.0, 0.0), (0.5, 0.5, 0.5), gravity=(0.0, 0.0, -9.8), ground_height=0.0)
    p = block((0.2, 0.2, 0.04), (0.3, 0.28, 0.1), spacing=1.0 / 48, object_id=1)
    values = {"a_x:1": 0.5, "a_y:v_y": -1.0, "a_z:|v|v_z": -0.3, "a_x:h": -2.0}
    values.update({"a_y:t": 1.0, "a_z:x": 0.5})
    params = default_params(p, velocities={1: (1.0, 0.3, -1.0)}, ground_friction=0.4)
    params.terms["expression"] = {n: torch.tensor(v) for n, v in values.items()}
    names = [f"term.expression.{n}" for n in values]
    weights = torch.randn(len(p), 3, generator=torch.Generator().manual_seed(0))
    named = dict(params.named_tensors())
    leaves = {n: named[n].detach().clone().requires_grad_(True) for n in names}
    loss = _loss(sim, p, params.with_tensors(leaves), world, 3, weights)
    grads = torch.autograd.grad(loss, [leaves[n] for n in names])
    bad = []
    for n, grad in zip(names, grads, strict=True):
        base = named[n].detach()

        def loss_of(t, n=n):
            return _loss(sim, p, params.with_tensors({n: t}), world, 3, weights)

        fd = central_difference(loss_of, base, 0, FD_STEP * abs(float(base)))
        ad = float(grad)
        assert fd != 0, n
        if abs(ad - fd) > FD_TOL * abs(fd) + 1e-6 * abs(float(loss.detach())):
            bad.append(f"{n}: autograd {ad:.5g} vs finite difference {fd:.5g}")
    assert not bad, "expression gradients disagree with central differences:\n" + "\n".join(bad)


@pytest.mark.parametrize(
    ("name", "message"),
    [
        ("a_x:dp_x", "the other objects' features .* warp-mpm simulator only"),
        ("a_x:speed", "unknown feature 'speed'; valid features"),
    ],
)
def test_what_taichi_cannot_apply_is_refused_by_name(sim, name, message):
    p = _block((0.5, 0.5, 0.5))
    params = _with_expression(p, {name: -1.0}, (0.0, 0.0, 0.0))
    with pytest.raises(ConfigError, match=message):
        sim.rollout(p, params, world=FREE, frames=1)
