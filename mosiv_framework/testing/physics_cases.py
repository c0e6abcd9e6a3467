"""Physics acceptance tests shared by every MPM backend (written once, called by each plugin).

Each case takes ``make_simulator(**options)`` (options: grid, substeps, contact) and uses only
the Simulator interface. Scenes are small (grid <= 32, <= a few thousand particles, <= 0.5 s) so
they run on 2 CPU cores. Every case asserts an analytic or conservation criterion with the
tolerance stated in its docstring and returns the measured numbers.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch

from mosiv_framework.testing.shapes import block, combine, default_params, sphere
from mosiv_framework.types import ParticleSet, SimulationParams, World

MakeSimulator = Callable[..., object]
G = 9.8


def _world(upper=(1.0, 1.0, 1.0), *, ground: float | None = 0.0, gravity=(0.0, 0.0, -G)) -> World:
    return World((0.0, 0.0, 0.0), upper, gravity=gravity, ground_height=ground, fps=24.0)


def _run(sim, particles: ParticleSet, params: SimulationParams, world: World, frames: int):
    with torch.no_grad():
        return sim.rollout(particles, params, world=world, frames=frames)


def _masses(particles: ParticleSet, params: SimulationParams) -> torch.Tensor:
    rho = torch.stack([params.objects[int(k)]["rho"].detach() for k in particles.object_ids])
    return rho * particles.volumes


def _extent(points: torch.Tensor) -> torch.Tensor:
    """Axis-aligned size [3] (m) of a point set, robust to stray particles (1%-99% quantiles)."""
    q = torch.quantile(points, torch.tensor([0.01, 0.99]), dim=0)
    return q[1] - q[0]


def free_fall(make_simulator: MakeSimulator) -> dict:
    """No ground: the block falls as the scheme's own discrete solution, within float32 round-off.

    MPM integrates symplectic Euler on the grid (v += dt g, then x += dt v with the new v), and
    for a uniform velocity field P2G/G2P transfer it unchanged. After n substeps of dt the
    velocity is exactly v0 + g t and the position x0 + v0 t + g dt^2 n (n + 1) / 2, i.e. the
    parabola x0 + v0 t + g t^2 / 2 shifted by g t dt / 2 (5.1 mm here). Both are compared with
    one float32 epsilon of relative round-off per substep, of the 1 m domain for positions
    (2.9e-5 m) and of the largest speed for velocities: 175 times smaller than the offset, so
    a scheme with another update order (explicit Euler lags by g t dt / 2) fails.
    """
    substeps, frames = 20, 12
    sim = make_simulator(grid=24, substeps=substeps)
    world = _world(ground=None)
    p = block((0.45, 0.45, 0.45), (0.55, 0.55, 0.55), spacing=0.02, object_id=1)
    v0 = torch.tensor((0.3, 0.0, 2.0), dtype=torch.float64)
    params = default_params(p, velocities={1: tuple(v0.tolist())})
    traj = _run(sim, p, params, world, frames)

    dt = 1.0 / (world.fps * substeps)
    n = substeps * torch.arange(frames + 1, dtype=torch.float64)[:, None]  # substeps per frame
    g = torch.tensor(world.gravity, dtype=torch.float64)[None]
    x0 = p.positions.double().mean(0)[None]
    expected_x = x0 + v0[None] * n * dt + g * dt**2 * n * (n + 1) / 2
    expected_v = v0[None] + g * n * dt
    rounding = float(n[-1]) * torch.finfo(torch.float32).eps
    tol_x = rounding * 1.0  # the domain size (m) bounds |x|
    tol_v = rounding * float(expected_v.norm(dim=1).max())

    x_err = (traj.centroids()[1].double() - expected_x).abs().max().item()
    v_err = (traj.velocities.double() - expected_v[:, None]).abs().max().item()
    offset = 0.5 * G * float(n[-1]) * dt * dt  # how far the scheme falls below the parabola (m)
    assert x_err <= tol_x, (
        f"free fall: centroid off the symplectic-Euler solution by {x_err:.3g} m > {tol_x:.3g} m "
        f"(the scheme's offset from the exact parabola is {offset:.3g} m)"
    )
    assert v_err <= tol_v, f"free fall: velocity off v0 + g t by {v_err:.3g} m/s > {tol_v:.3g}"
    return {"max_error_m": x_err, "max_velocity_error_m_s": v_err, "scheme_offset_m": offset}


def momentum_conservation(make_simulator: MakeSimulator) -> dict:
    """Two elastic blocks collide with gravity and ground off: total momentum is conserved
    within 1e-3 of its initial magnitude, and the collision really happens (block 1 slows)."""
    sim = make_simulator(grid=24, substeps=20)
    world = _world(ground=None, gravity=(0.0, 0.0, 0.0))
    a = block((0.25, 0.42, 0.42), (0.41, 0.58, 0.58), spacing=0.02, object_id=1)
    b = block((0.47, 0.45, 0.45), (0.57, 0.55, 0.55), spacing=0.02, object_id=2)
    p = combine([a, b])
    params = default_params(p, velocities={1: (1.5, 0.0, 0.0), 2: (-1.0, 0.2, 0.0)})
    traj = _run(sim, p, params, world, 4)  # 0.17 s: contact at 0.025 s, walls not yet reached
    m = _masses(p, params)
    momentum = (m[None, :, None] * traj.velocities).sum(1)  # [T, 3]
    drift = (momentum - momentum[0]).norm(dim=1).max().item() / momentum[0].norm().item()
    v1 = traj.velocities[-1, p.object_ids == 1, 0].mean().item()
    assert v1 < 0.9 * 1.5, f"momentum test: the blocks did not collide (block 1 vx={v1:.3g})"
    assert drift <= 1e-3, f"total momentum drifted by {drift:.3g} (relative) > 1e-3"
    return {"relative_drift": drift, "block1_final_vx": v1}


def ground_friction_stop(make_simulator: MakeSimulator) -> dict:
    """A block sliding at v0 = 1 m/s on ground with friction mu = 0.5 stops after
    v0^2 / (2 mu g) = 0.102 m, within 10%."""
    sim = make_simulator(grid=32, substeps=20)
    world = _world((1.0, 0.5, 0.5))
    p = block((0.2, 0.2, 0.0), (0.36, 0.3, 0.06), spacing=1.0 / 64, object_id=1)
    v0, mu = 1.0, 0.5
    params = default_params(
        p, overrides={1: {"E": 2e5}}, velocities={1: (v0, 0.0, 0.0)}, ground_friction=mu
    )
    traj = _run(sim, p, params, world, 10)  # 0.42 s, the block stops at 0.2 s
    c = traj.centroids()[1]
    distance = (c[-1, 0] - c[0, 0]).item()
    expected = v0**2 / (2 * mu * G)
    final_speed = traj.velocities[-1, :, 0].mean().abs().item()
    assert final_speed < 0.05 * v0, f"sliding block still moves at {final_speed:.3g} m/s"
    assert abs(distance - expected) <= 0.1 * expected, (
        f"sliding block stopped after {distance:.4g} m, expected {expected:.4g} m +- 10%"
    )
    return {"distance_m": distance, "expected_m": expected}


def _drop_ball(make_simulator, family: str, overrides: dict, frames: int) -> tuple:
    sim = make_simulator(grid=24, substeps=40)
    world = _world((0.6, 0.6, 0.6))
    p = sphere((0.3, 0.3, 0.15), 0.08, spacing=0.0125, object_id=1, material=family)
    params = default_params(
        p, overrides={1: overrides}, velocities={1: (0.0, 0.0, -2.0)}, ground_friction=0.3
    )
    return p, _run(sim, p, params, world, frames)


def elastic_bounce(make_simulator: MakeSimulator) -> dict:
    """An elastic ball thrown at the ground at 2 m/s rebounds (upward centroid speed >= 20% of
    the impact speed) and recovers its shape (height/width within 10% of the initial ones)."""
    p, traj = _drop_ball(make_simulator, "elastic", {"E": 1e5, "nu": 0.3}, 12)
    vz = traj.velocities[:, :, 2].mean(1)
    rebound = vz.max().item()
    size0 = _extent(traj.positions[0])
    size_end = _extent(traj.positions[-1])
    change = ((size_end - size0).abs() / size0).max().item()
    assert rebound >= 0.2 * 2.0, f"elastic ball did not rebound (max centroid vz {rebound:.3g} m/s)"
    assert change <= 0.1, f"elastic ball kept a deformation of {100 * change:.1f}% (> 10%)"
    return {"rebound_vz": rebound, "shape_change": change}


def plasticine_flattening(make_simulator: MakeSimulator) -> dict:
    """A plasticine ball thrown at the ground keeps a permanent flattening: its final height is
    below 85% of its diameter and its width above it."""
    p, traj = _drop_ball(make_simulator, "plasticine", {"E": 1e5, "yield_stress": 500.0}, 12)
    size0 = _extent(traj.positions[0])
    size_end = _extent(traj.positions[-1])
    vz_end = traj.velocities[-1, :, 2].mean().abs().item()
    height, width = (size_end[2] / size0[2]).item(), (size_end[:2] / size0[:2]).mean().item()
    assert vz_end < 0.1, f"plasticine ball has not settled (centroid |vz| {vz_end:.3g} m/s)"
    assert height < 0.85 and width > 1.0, (
        f"plasticine ball not flattened: height {height:.3f}, width {width:.3f} of initial"
    )
    return {"height_ratio": height, "width_ratio": width}


def _volume(points: torch.Tensor, spacing: float) -> float:
    """Volume (m^3) of the convex hull of the points dilated by half a lattice spacing (a
    polyhedral Minkowski sum; exact for a lattice box). Valid while the body stays near-convex,
    which is why the newtonian case stops early in the collapse."""
    from scipy.spatial import ConvexHull

    r = 0.5 * spacing
    dirs = np.array(
        [
            (i, j, k)
            for i in (-1, 0, 1)
            for j in (-1, 0, 1)
            for k in (-1, 0, 1)
            if (i, j, k) != (0, 0, 0)
        ],
        dtype=np.float64,
    )
    pts = points.double().numpy()
    dilated = (pts[:, None, :] + r * dirs[None]).reshape(-1, 3)
    return float(ConvexHull(dilated).volume)


def newtonian_volume(make_simulator: MakeSimulator) -> dict:
    """A newtonian blob collapsing on the ground spreads (footprint +15%) while its volume
    (dilated convex hull, an upper bound for a slumping mound) stays within 5% of the initial one."""
    sim = make_simulator(grid=24, substeps=50)  # sound speed 10 m/s: CFL 0.33
    world = _world((0.6, 0.6, 0.6))
    spacing = 0.0125
    p = block(
        (0.24, 0.24, 0.0), (0.36, 0.36, 0.12), spacing=spacing, object_id=1, material="newtonian"
    )
    params = default_params(p, overrides={1: {"viscosity": 10.0, "bulk_modulus": 1e5}})
    traj = _run(sim, p, params, world, 2)
    v0 = _volume(traj.positions[0], spacing)
    v1 = _volume(traj.positions[-1], spacing)
    spread = (_extent(traj.positions[-1])[:2] / _extent(traj.positions[0])[:2]).mean().item()
    assert spread > 1.15, f"newtonian blob did not spread (footprint ratio {spread:.3f})"
    change = abs(v1 - v0) / v0
    assert change <= 0.05, f"newtonian blob volume changed by {100 * change:.1f}% (> 5%)"
    return {"volume_change": change, "spread": spread}


def sand_friction_angle(make_simulator: MakeSimulator) -> dict:
    """A sand column collapses wider at friction angle 20 deg than at 45 deg (footprint at
    least 10% larger)."""
    sim = make_simulator(grid=24, substeps=30)
    world = _world((0.6, 0.6, 0.6))
    p = block((0.25, 0.25, 0.0), (0.35, 0.35, 0.2), spacing=0.0125, object_id=1, material="sand")
    widths = {}
    for angle in (20.0, 45.0):
        params = default_params(p, overrides={1: {"friction_angle": angle}}, ground_friction=0.5)
        traj = _run(sim, p, params, world, 8)
        widths[angle] = _extent(traj.positions[-1])[:2].mean().item()
    assert widths[20.0] >= 1.1 * widths[45.0], f"sand footprints (m) by friction angle: {widths}"
    return {"width_20deg_m": widths[20.0], "width_45deg_m": widths[45.0]}


def frictionless_contact(make_simulator: MakeSimulator) -> dict:
    """Multi-field contact, gravity and ground off: block 2 slides along +x over block 1 while
    pressing into it. Frictionless: its x speed changes < 2%; with friction 0.5: > 2%."""
    sim = make_simulator(grid=24, substeps=20, contact="multi_field")
    world = _world(ground=None, gravity=(0.0, 0.0, 0.0))
    # The slider overhangs the plate's leading end and starts past its trailing end, so only
    # the flat interface is in contact (edge nodes have oblique normals in any grid method).
    a = block((0.25, 0.35, 0.3), (0.55, 0.65, 0.42), spacing=0.02, object_id=1)
    b = block((0.4, 0.42, 0.46), (0.7, 0.58, 0.54), spacing=0.02, object_id=2)
    p = combine([a, b])
    changes = {}
    for mu in (0.0, 0.5):
        params = default_params(
            p,
            overrides={1: {"friction": mu, "E": 1e5}, 2: {"friction": mu, "E": 1e5}},
            velocities={2: (1.0, 0.0, -0.3)},
        )
        traj = _run(sim, p, params, world, 4)
        vz = traj.velocities[:, p.object_ids == 2, 2].mean(1)
        assert vz.max().item() > -0.2, "contact test: block 2 never touched block 1"
        vx = traj.velocities[-1, p.object_ids == 2, 0].mean().item()
        changes[mu] = abs(vx - 1.0)
    assert changes[0.0] < 0.02, (
        f"frictionless contact dragged the slider: dv/v = {changes[0.0]:.3g}"
    )
    assert changes[0.5] > 0.02, (
        f"frictional contact did not drag the slider: dv/v = {changes[0.5]:.3g}"
    )
    return {"frictionless_dv": changes[0.0], "friction_dv": changes[0.5]}


ALL_CASES = (
    free_fall,
    momentum_conservation,
    ground_friction_stop,
    elastic_bounce,
    plasticine_flattening,
    newtonian_volume,
    sand_friction_angle,
    frictionless_contact,
)


def _rollout_loss(sim, particles, params, world, frames, weights) -> torch.Tensor:
    """A smooth scalar of the whole rollout: weighted displacements summed over frames (m)."""
    traj = sim.rollout(particles, params, world=world, frames=frames)
    return ((traj.positions[1:] - traj.positions[:1]) * weights).sum(dim=(1, 2)).mean()


#: Law parameters that make the gradient scene well-posed for finite differences. Snow at its
#: default hardening xi = 10 softens exponentially as it stretches past its 0.75% critical
#: stretch, so the thrown block fractures and its rollout loss is rough at every float32 step:
#: central differences with steps from 3e-5 to 1e-2 (relative) disagree in sign, in both
#: backends. At xi = 2 the block still yields in compression and stretch (every snow parameter
#: has a non-zero gradient) but the loss is smooth, so differences can judge the adjoint.
#: plasticine_corotated: near its defaults (yield stress 2 kPa, nu 0.25) the loss of this block
#: is nearly flat in nu (autograd -3e-5, plasticine's -0.04), so central differences see float32
#: noise (+1.6e-4 on warp-mpm, -2.5e-4 on taichi-mpm); at 300 Pa and nu 0.25 still 4-12 %
#: (the two backends' autograd agree to 0.1 %). At 300 Pa and nu 0.35 the nu gradient is
#: -0.039 and the differences meet it within 1.4 % on both backends.
GRADIENT_SCENE_OVERRIDES: dict[str, dict[str, float]] = {
    "snow": {"hardening": 2.0},
    "plasticine_corotated": {"yield_stress": 300.0, "nu": 0.35},
}


#: Central differences are averaged over these multiples of the base step: small steps suffer
#: float32 round-off of the loss, large ones the kinks of return maps and contact switches;
#: averaging damps both (on the snow scene the spread across single steps reaches 5%).
FD_STEP_FACTORS = (1.0 / 3.0, 1.0, 3.0)


#: Relative tolerance of autograd against the averaged central differences, per quantity (a
#: parameter's name without its object: "v0", "rho", "friction", "ground_friction" or a law
#: parameter). The initial velocity, the density and the friction coefficients act through
#: smooth maps over the difference steps: 3% (largest errors measured on either backend: 2.0%
#: for sand's rho, 1.9% for the sliding component of v0, where ground friction switches nodes
#: between stick and slip).
#: Law parameters act through return maps whose kinks the steps straddle: 5% (largest measured:
#: 3.8%, snow's nu).
FD_REL_TOL = {"v0": 0.03, "rho": 0.03, "friction": 0.03, "ground_friction": 0.03}
FD_REL_TOL_LAW = 0.05


def fd_tolerance(name: str) -> float:
    """FD_REL_TOL of a named parameter tensor ("v0.obj1", "obj2.E", "ground_friction")."""
    quantity = "v0" if name.startswith("v0.") else name.split(".")[-1]
    return FD_REL_TOL.get(quantity, FD_REL_TOL_LAW)


def central_difference(
    loss_of: Callable[[torch.Tensor], float], base: torch.Tensor, i: int, h: float
):
    """d loss / d base[i] (flat index) by central differences averaged over FD_STEP_FACTORS * h;
    ``loss_of(tensor shaped like base)`` evaluates the loss (float) without gradients."""
    estimates = []
    for factor in FD_STEP_FACTORS:
        vals = []
        for sign in (1.0, -1.0):
            t = base.detach().clone().reshape(-1)
            t[i] += sign * factor * h
            with torch.no_grad():
                vals.append(float(loss_of(t.reshape(base.shape))))
        estimates.append((vals[0] - vals[1]) / (2 * factor * h))
    return sum(estimates) / len(estimates)


def _compare_with_differences(
    sim, particles, params, world, frames, weights, names, *, rel_step, floor_rel, label
) -> dict:
    """Autograd vs averaged central differences of _rollout_loss for the tensors ``names``.

    Each component must agree within fd_tolerance(name) of its difference plus a floor:
    ``floor_rel`` of the largest difference within the same tensor (a relative error of a
    component that nearly vanishes by symmetry is meaningless) and 1e-6 of the loss (float32
    round-off).
    """
    named = dict(params.named_tensors())
    leaves = {n: named[n].detach().clone().requires_grad_(True) for n in names}
    loss = _rollout_loss(sim, particles, params.with_tensors(leaves), world, frames, weights)
    grads = torch.autograd.grad(loss, [leaves[n] for n in names])

    report, bad = {}, []
    for n, grad in zip(names, grads):
        base = named[n].detach()

        def loss_of(t, n=n):
            with_t = params.with_tensors({n: t})
            return _rollout_loss(sim, particles, with_t, world, frames, weights).item()

        pairs = {}
        scale = max(base.abs().max().item(), 1e-6)
        for i in range(base.numel()):
            # step relative to the value, or to its tensor's largest entry for a zero component
            # of a vector (a floor like 0.1 would be 13x snow's critical stretch)
            h = rel_step * max(abs(base.reshape(-1)[i].item()), scale)
            key = f"{n}[{i}]" if base.numel() > 1 else n
            pairs[key] = (grad.reshape(-1)[i].item(), central_difference(loss_of, base, i, h))
        floor = floor_rel * max(abs(fd) for _ad, fd in pairs.values()) + 1e-6 * abs(loss.item())
        rtol = fd_tolerance(n)
        bad += [
            f"{key}: autograd {ad:.5g} vs finite difference {fd:.5g} (tolerance {rtol:.0%})"
            for key, (ad, fd) in pairs.items()
            if abs(ad - fd) > rtol * abs(fd) + floor
        ]
        report.update(pairs)
    assert not bad, f"{label} gradients disagree with central differences:\n" + "\n".join(bad)
    return report


def gradient_check(make_simulator: MakeSimulator, family: str, *, rel_step: float = 1e-2) -> dict:
    """Autograd gradients of a rollout loss w.r.t. every law parameter, rho, the initial
    velocity and ground friction agree with central finite differences within fd_tolerance.

    A block of ``family`` is thrown onto the ground (sliding and deforming) for 3 frames.
    Central differences use relative steps around ``rel_step`` (float32 needs them well above
    1e-4), averaged over FD_STEP_FACTORS.
    """
    sim = make_simulator(grid=16, substeps=30)
    world = _world((0.5, 0.5, 0.5))
    p = block((0.2, 0.2, 0.04), (0.3, 0.28, 0.1), spacing=1.0 / 48, object_id=1, material=family)
    params = default_params(
        p,
        overrides={1: GRADIENT_SCENE_OVERRIDES.get(family, {})},
        velocities={1: (1.0, 0.3, -1.0)},
        ground_friction=0.4,
    )
    weights = torch.randn(len(p), 3, generator=torch.Generator().manual_seed(0))
    names = [n for n, _ in params.named_tensors() if not n.endswith(".friction")]  # 1 body
    return _compare_with_differences(
        sim, p, params, world, 3, weights, names, rel_step=rel_step, floor_rel=0.0, label=family
    )


def _collision_scene() -> tuple[World, ParticleSet, SimulationParams, torch.Tensor]:
    """Two balls (elastic, plasticine) about to collide obliquely in mid-air, no gravity or
    ground; with the loss weights of collision_gradient_check."""
    world = _world((0.5, 0.5, 0.5), ground=None, gravity=(0.0, 0.0, 0.0))
    a = sphere((0.17, 0.25, 0.24), 0.06, spacing=1.0 / 48, object_id=1, material="elastic")
    b = sphere((0.33, 0.25, 0.26), 0.06, spacing=1.0 / 48, object_id=2, material="plasticine")
    p = combine([a, b])
    params = default_params(
        p,
        overrides={1: {"friction": 0.4}, 2: {"friction": 0.2, "yield_stress": 1e3}},
        velocities={1: (1.5, 0.1, 0.5), 2: (-1.5, 0.0, -0.5)},
    )
    weights = torch.randn(len(p), 3, generator=torch.Generator().manual_seed(1))
    return world, p, params, weights


def collision_gradient_check(make_simulator: MakeSimulator, *, rel_step: float = 1e-2) -> dict:
    """Two balls (elastic, plasticine) collide obliquely in mid-air in multi-field mode, gravity
    and ground off: gradients of a rollout loss w.r.t. both initial velocities, both friction
    coefficients and one law parameter of each agree with central differences within
    fd_tolerance (plus 1e-3 of the largest gradient, for components that nearly vanish by
    symmetry).

    This is the path single-body checks never reach: per-object fields, contact normals from
    mass gradients, the centre-of-mass velocity and the Coulomb projection between fields.
    """
    sim = make_simulator(grid=16, substeps=30)  # same options as gradient_check: one compile
    world, p, params, weights = _collision_scene()
    names = ["v0.obj1", "v0.obj2", "obj1.friction", "obj2.friction", "obj1.E", "obj2.yield_stress"]
    report = _compare_with_differences(
        sim,
        p,
        params,
        world,
        2,
        weights,
        names,
        rel_step=rel_step,
        floor_rel=1e-3,
        label="collision",
    )
    assert abs(report["obj1.friction"][1]) > 0, "collision scene: the balls never touched"
    return report


#: relative agreement (of the largest gradient) of a rollout's gradients with and without
#: another rollout between its forward and backward: the same computation, so only the order of
#: float32 atomic adds may differ
INTERLEAVED_REL_TOL = 1e-4


def interleaved_rollouts_check(make_simulator: MakeSimulator) -> dict[str, tuple[float, float]]:
    """A rollout's gradients are its own when another differentiable rollout of the same
    simulator, under other parameters, ran between its forward and its backward (as the
    default ``rollout_batch`` loop does before a loss over all members is back-propagated).

    On the collision scene of ``collision_gradient_check`` (same options: nothing new to
    compile), gradients w.r.t. an initial velocity and one law parameter of each ball, alone
    and interleaved. Returns {name[i]: (alone, interleaved)}.
    """
    sim = make_simulator(grid=16, substeps=30)
    world, p, params, weights = _collision_scene()
    names = ["v0.obj1", "obj1.E", "obj2.yield_stress"]
    named = dict(params.named_tensors())
    # the other rollout: stiffer, weaker and faster, and differentiable too (the same engine)
    other = params.with_tensors(
        {
            "obj1.E": (named["obj1.E"].detach() * 4.0).requires_grad_(True),
            "obj2.yield_stress": (named["obj2.yield_stress"].detach() * 0.25).requires_grad_(True),
            "v0.obj1": (named["v0.obj1"].detach() * 1.5).requires_grad_(True),
        }
    )

    def gradients(interleave: bool) -> torch.Tensor:
        leaves = {n: named[n].detach().clone().requires_grad_(True) for n in names}
        traj = sim.rollout(p, params.with_tensors(leaves), world=world, frames=2)
        if interleave:
            between = sim.rollout(p, other, world=world, frames=2)
            assert between.positions.requires_grad, "the other rollout was not differentiable"
        loss = ((traj.positions[1:] - traj.positions[:1]) * weights).sum()
        grads = torch.autograd.grad(loss, [leaves[n] for n in names])
        return torch.cat([g.reshape(-1) for g in grads])

    alone, interleaved = gradients(False), gradients(True)
    keys = [f"{n}[{i}]" for n in names for i in range(named[n].numel())]
    report = {k: (a.item(), b.item()) for k, a, b in zip(keys, alone, interleaved)}
    worst = (alone - interleaved).abs().max().item()
    scale = alone.abs().max().item()
    assert worst <= INTERLEAVED_REL_TOL * scale, (
        f"gradients changed by another rollout between forward and backward (largest change "
        f"{worst:.3g} of {scale:.3g}): {report}"
    )
    return report
