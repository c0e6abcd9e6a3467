"""The ``expression`` term in warp-mpm (mosiv_framework.expression): a sum of feature times
coefficient added to every grid node's acceleration.

- the node kernel equals the torch reference for every (axis, feature) pair;
- analytic: on a free body the scheme's centroid follows symplectic Euler of the law at the
  centre of mass exactly (quadratic B-splines reproduce linear features, APIC conserves
  momentum), so a constant expression is a change of gravity, a = -c v decays the velocity as
  (1 - c dt)^n (within 0.3 % of e^(-c t)), a spring in the height and a jerk in time follow
  their recursion, and two bodies pulled by the other's centre (dp) oscillate about each other;
- gradients of a rollout loss w.r.t. every coefficient, and through the other body's centre
  w.r.t. its initial velocity, match central finite differences;
- batched members with different expressions equal their single rollouts;
- bad input (an unknown feature, the other objects' features in single-field mode) is refused
  naming the parameter and what is valid.
"""

from __future__ import annotations

import pytest
import torch

from mosiv_framework.errors import ConfigError
from mosiv_framework.expression import AXES, FEATURES, acceleration, node_features
from mosiv_framework.testing.physics_cases import central_difference
from mosiv_framework.testing.shapes import block, combine, default_params
from mosiv_framework.types import World

FPS = 24.0
FREE = World((0.0, 0.0, 0.0), (1.0, 1.0, 1.0), gravity=(0.0, 0.0, 0.0), ground_height=None)
#: float32 round-off of positions (m) and velocities (m/s) over a few dozen substeps
POSITION_TOL = 2e-5
VELOCITY_TOL = 2e-5
#: autograd against central differences, relative, per quantity: the coefficients enter the
#: node update linearly, so the differences take steps of 5 % of the value (at 1 %, float32
#: round-off of these small effects reached 4 %); largest error measured 0.5 %. An initial
#: velocity (1 % steps, as physics_cases) also reaches the other body through its centre
#: (measured 2.0 % on its smallest component)
FD_TOL = {"coefficient": 0.02, "v0": 0.03}
FD_STEP = {"coefficient": 5e-2, "v0": 1e-2}


def _block(centre, object_id=1, half=0.05):
    lo = tuple(c - half for c in centre)
    hi = tuple(c + half for c in centre)
    return block(lo, hi, spacing=0.025, object_id=object_id)


def _terms(values: dict[str, float], requires_grad=False) -> dict:
    return {
        "expression": {
            n: torch.tensor(float(v), requires_grad=requires_grad) for n, v in values.items()
        }
    }


def _rollout(sim, particles, params, world=FREE, frames=4):
    with torch.no_grad():
        return sim.rollout(particles, params, world=world, frames=frames)


@pytest.fixture(scope="module")
def sim(make_warp_simulator):
    return make_warp_simulator(grid=16, substeps=10)


def test_node_kernel_matches_the_torch_reference():
    """Every feature, with random coefficients on all 54 pairs, at random nodes."""
    import warp as wp
    from mosiv_warp_mpm import expression_kernels as XK
    from mosiv_warp_mpm.simulator import init_warp

    init_warp()
    gen = torch.Generator().manual_seed(0)
    n = 64
    x, v = torch.rand(n, 3, generator=gen), torch.randn(n, 3, generator=gen)
    t = torch.rand(n, generator=gen)
    others_p, others_v = torch.rand(n, 2, 3, generator=gen), torch.randn(n, 2, 3, generator=gen)
    up, ground = torch.tensor([0.0, 0.6, 0.8]), 0.1
    coef = torch.randn(len(FEATURES), 3, generator=gen)
    values = {f"a_{a}:{f}": coef[i, j] for i, f in enumerate(FEATURES) for j, a in enumerate(AXES)}
    features = node_features(
        x, v, t, up=up, ground_height=ground, others_position=others_p, others_velocity=others_v
    )
    expected = acceleration(values, features)

    def arr(a, dtype):
        return wp.array(a.float().numpy(), dtype=dtype, device="cpu")

    out = wp.zeros(n, dtype=wp.vec3, device="cpu")
    wp.launch(
        XK.evaluate_expression,
        dim=n,
        inputs=[arr(coef, wp.vec3), arr(x, wp.vec3), arr(v, wp.vec3), arr(t, float)]
        + [wp.vec3(*up.tolist()), ground, arr(others_p.sum(1), wp.vec3)]
        + [arr(others_v.sum(1), wp.vec3), arr(torch.full((n,), 2.0), float)],
        outputs=[out],
        device="cpu",
    )
    got = torch.from_numpy(out.numpy())
    assert torch.allclose(got, expected, rtol=1e-5, atol=1e-5 * float(expected.abs().max()))


def test_a_constant_expression_is_a_change_of_gravity(sim):
    """a_z:1 = -2 under g = -9.8: the scheme's free fall (symplectic Euler, exact for a
    uniform field, see physics_cases.free_fall) under -11.8 m/s^2."""
    world = World((0.0, 0.0, 0.0), (1.0, 1.0, 1.0), gravity=(0.0, 0.0, -9.8), ground_height=None)
    p = _block((0.5, 0.5, 0.6))
    v0 = torch.tensor([0.3, 0.0, 1.0], dtype=torch.float64)
    params = default_params(p, velocities={1: tuple(v0.tolist())})
    params.terms.update(_terms({"a_z:1": -2.0}))
    frames = 6
    traj = _rollout(sim, p, params, world, frames)
    dt = 1.0 / (FPS * sim.options.substeps)
    n = sim.options.substeps * torch.arange(frames + 1, dtype=torch.float64)[:, None]
    g = torch.tensor([0.0, 0.0, -11.8], dtype=torch.float64)
    expected = p.positions.double().mean(0) + v0 * n * dt + g * dt**2 * n * (n + 1) / 2
    assert (traj.centroids()[1].double() - expected).abs().max() < POSITION_TOL


def test_linear_drag_expression_decays_the_velocity_exponentially(sim):
    """a = -c v on every axis (c = 2 1/s), no gravity: each substep multiplies the uniform
    velocity by (1 - c dt), within float32 round-off; that is e^(-c t) within n (c dt)^2 / 2
    (0.14 % after 40 substeps), and the test allows 0.3 %."""
    c = 2.0
    p = _block((0.4, 0.5, 0.5))
    v0 = torch.tensor([1.0, -0.5, 0.5])
    params = default_params(p, velocities={1: tuple(v0.tolist())})
    params.terms.update(_terms({f"a_{a}:v_{a}": -c for a in AXES}))
    traj = _rollout(sim, p, params, frames=4)
    dt = 1.0 / (FPS * sim.options.substeps)
    n = sim.options.substeps * torch.arange(5, dtype=torch.float64)
    discrete = v0.double()[None] * (1 - c * dt) ** n[:, None]
    exact = v0.double()[None] * torch.exp(-c * n * dt)[:, None]
    velocity = traj.velocities.double().mean(dim=1)
    assert (velocity - discrete).abs().max() < VELOCITY_TOL
    assert ((velocity - exact).abs() / exact.abs()).max() < 3e-3


def _centroid_recursion(c0, u0, accel, substeps, frames, dt):
    """Centroids per frame of symplectic Euler: U += dt a(C, t); C += dt U."""
    c, u, out = c0.clone(), u0.clone(), [c0.clone()]
    for i in range(substeps * frames):
        u = u + dt * accel(c, u, i * dt)
        c = c + dt * u
        if (i + 1) % substeps == 0:
            out.append(c.clone())
    return torch.stack(out)


def test_height_and_time_features_follow_the_centroid_recursion(sim):
    """a_z = -30 h (a spring towards the ground plane z = 0) and a_x = 4 t (a jerk): the
    centroid follows the recursion of the law at the centre of mass; and the continuous
    solutions: z0 cos(w t) within z0 w dt (symplectic Euler lags by about half a substep, here
    12.6 mm of 0.55 m), x0 + u t + j t^3 / 6 within 1 mm over the 0.25 s."""
    k, jerk = 30.0, 4.0
    p = _block((0.3, 0.5, 0.55))
    params = default_params(p, velocities={1: (0.2, 0.0, 0.0)})
    params.terms.update(_terms({"a_z:h": -k, "a_x:t": jerk}))
    frames, dt = 6, 1.0 / (FPS * sim.options.substeps)
    traj = _rollout(sim, p, params, frames=frames)

    def accel(c, u, t):
        return torch.tensor([jerk * t, 0.0, -k * float(c[2])], dtype=torch.float64)

    c0 = p.positions.double().mean(0)
    expected = _centroid_recursion(
        c0, torch.tensor([0.2, 0.0, 0.0], dtype=torch.float64), accel,
        sim.options.substeps, frames, dt,
    )  # fmt: skip
    got = traj.centroids()[1].double()
    assert (got - expected).abs().max() < POSITION_TOL
    t = torch.arange(frames + 1, dtype=torch.float64) / FPS
    lag = float(c0[2]) * k**0.5 * dt
    assert (got[:, 2] - c0[2] * torch.cos(k**0.5 * t)).abs().max() < lag
    assert (got[:, 0] - (c0[0] + 0.2 * t + jerk * t**3 / 6)).abs().max() < 1e-3


def test_two_bodies_pulled_towards_each_others_centre(sim):
    """a_x = kappa dp_x, a_y = -0.5 dv_y on two equal blocks (one field each): each body's
    centroid follows the recursion with a = kappa (C_other - C) and -0.5 (U_other - U)."""
    kappa = 8.0  # the blocks come no closer than 0.33 m: their grid stencils never meet
    p = combine([_block((0.25, 0.45, 0.5), 1), _block((0.75, 0.55, 0.5), 2)])
    params = default_params(p, velocities={1: (0.0, 0.3, 0.0), 2: (0.0, -0.1, 0.0)})
    params.terms.update(_terms({"a_x:dp_x": kappa, "a_y:dv_y": -0.5}))
    frames, dt = 5, 1.0 / (FPS * sim.options.substeps)
    traj = _rollout(sim, p, params, frames=frames)
    cents = traj.centroids()
    c = torch.stack([p.positions[p.object_ids == k].double().mean(0) for k in (1, 2)])
    u = torch.tensor([[0.0, 0.3, 0.0], [0.0, -0.1, 0.0]], dtype=torch.float64)
    out = [c.clone()]
    for i in range(sim.options.substeps * frames):
        a = torch.zeros_like(c)
        a[:, 0] = kappa * (c[[1, 0], 0] - c[:, 0])
        a[:, 1] = -0.5 * (u[[1, 0], 1] - u[:, 1])
        u = u + dt * a
        c = c + dt * u
        if (i + 1) % sim.options.substeps == 0:
            out.append(c.clone())
    expected = torch.stack(out)
    for j, k in enumerate((1, 2)):
        assert (cents[k].double() - expected[:, j]).abs().max() < POSITION_TOL
    assert float(cents[2][-1, 0] - cents[1][-1, 0]) < 0.4  # they approached (0.5 apart)


def _loss(sim, particles, params, world, frames, weights):
    traj = sim.rollout(particles, params, world=world, frames=frames)
    return ((traj.positions[1:] - traj.positions[:1]) * weights).sum(dim=(1, 2)).mean()


def _check_gradients(sim, particles, params, world, frames, names):
    """Autograd vs averaged central differences for the named tensors; returns the pairs."""
    weights = torch.randn(len(particles), 3, generator=torch.Generator().manual_seed(0))
    named = dict(params.named_tensors())
    leaves = {n: named[n].detach().clone().requires_grad_(True) for n in names}
    loss = _loss(sim, particles, params.with_tensors(leaves), world, frames, weights)
    grads = torch.autograd.grad(loss, [leaves[n] for n in names])
    bad, pairs = [], {}
    for n, grad in zip(names, grads):
        base = named[n].detach()

        def loss_of(t, n=n):
            return _loss(sim, particles, params.with_tensors({n: t}), world, frames, weights)

        quantity = "v0" if n.startswith("v0.") else "coefficient"
        scale = max(float(base.abs().max()), 1e-3)
        for i in range(base.numel()):
            h = FD_STEP[quantity] * max(abs(float(base.reshape(-1)[i])), scale)
            fd = central_difference(loss_of, base, i, h)
            ad = float(grad.reshape(-1)[i])
            pairs[f"{n}[{i}]"] = (ad, fd)
            if abs(ad - fd) > FD_TOL[quantity] * abs(fd) + 1e-6 * abs(float(loss.detach())):
                bad.append(f"{n}[{i}]: autograd {ad:.5g} vs finite difference {fd:.5g}")
    assert not bad, "expression gradients disagree with central differences:\n" + "\n".join(bad)
    return pairs


def test_gradients_of_every_node_feature_match_finite_differences(sim):
    """A block thrown onto a table with friction (contact, sliding) under an expression of
    every kind of node-local feature: d loss / d coefficient, per coefficient."""
    world = World((0.0, 0.0, 0.0), (0.5, 0.5, 0.5), gravity=(0.0, 0.0, -9.8), ground_height=0.0)
    p = block((0.2, 0.2, 0.04), (0.3, 0.28, 0.1), spacing=1.0 / 48, object_id=1)
    values = {
        "a_x:1": 0.5,
        "a_y:v_y": -1.0,
        "a_z:|v|v_z": -0.3,
        "a_x:h": -2.0,
        "a_y:t": 1.0,
        "a_z:x": 0.5,
    }
    params = default_params(p, velocities={1: (1.0, 0.3, -1.0)}, ground_friction=0.4)
    params.terms.update(_terms(values))
    names = [f"term.expression.{n}" for n in values]
    pairs = _check_gradients(sim, p, params, world, 3, names)
    assert all(abs(fd) > 0 for _ad, fd in pairs.values())


def test_gradients_through_the_other_bodys_centre_match_finite_differences(sim):
    """Two bodies, each pulled by the other's centre (dp) and velocity (dv): the gradients
    w.r.t. the coefficients and w.r.t. body 2's initial velocity (which reaches body 1 only
    through the centre sums) match central differences."""
    p = combine([_block((0.3, 0.45, 0.5), 1), _block((0.7, 0.55, 0.5), 2)])
    params = default_params(p, velocities={1: (0.2, 0.3, 0.0), 2: (-0.1, -0.1, 0.2)})
    params.terms.update(_terms({"a_x:dp_x": 15.0, "a_y:dv_y": -2.0, "a_z:dp_y": 5.0}))
    names = ["term.expression.a_x:dp_x", "term.expression.a_y:dv_y", "term.expression.a_z:dp_y"]
    _check_gradients(sim, p, params, FREE, 3, names + ["v0.obj2"])


def test_batched_members_with_different_expressions_equal_their_single_rollouts(sim):
    p = combine([_block((0.3, 0.45, 0.5), 1), _block((0.7, 0.55, 0.5), 2)])
    params_list = []
    for values in ({"a_x:v_x": -1.0}, {"a_z:dp_z": 8.0, "a_x:1": 0.5}, {}):
        params = default_params(p, velocities={1: (0.5, 0.0, 0.1), 2: (0.0, 0.0, -0.1)})
        if values:
            params.terms.update(_terms(values))
        params_list.append(params)
    batched = sim.rollout_batch(p, params_list, world=FREE, frames=3)
    for params, got in zip(params_list, batched):
        single = _rollout(sim, p, params, frames=3)
        assert torch.allclose(got.positions, single.positions, atol=1e-6)


def test_an_unknown_feature_is_refused_naming_the_valid_ones(sim):
    p = _block((0.5, 0.5, 0.5))
    params = default_params(p)
    params.terms.update(_terms({"a_x:speed": 1.0}))
    with pytest.raises(ConfigError, match=r"unknown feature 'speed'; valid features: 1, x, y"):
        _rollout(sim, p, params, frames=1)
    params.terms.update(_terms({"b_x:v_x": 1.0}))
    with pytest.raises(ConfigError, match="a_AXIS:FEATURE with AXIS one of x, y, z"):
        _rollout(sim, p, params, frames=1)


def test_the_other_objects_features_need_one_field_per_object(make_warp_simulator):
    sim = make_warp_simulator(grid=16, substeps=10, contact="single_field")
    p = combine([_block((0.3, 0.45, 0.5), 1), _block((0.7, 0.55, 0.5), 2)])
    params = default_params(p)
    params.terms.update(_terms({"a_x:dp_x": 1.0}))
    with pytest.raises(ConfigError, match="set the simulator's contact: multi_field"):
        _rollout(sim, p, params, frames=1)
