"""Velocity initialisation, free-flight detection and the CFL stiffness ceiling (analytic)."""

from __future__ import annotations

import math

import pytest
import torch

from mosiv_framework.pipeline.params import (
    ParameterVector,
    free_flight_frames,
    initial_velocity_from_points,
    stiffness_ceilings,
)
from mosiv_framework.types import World

FPS, G = 24.0, (0.0, 0.0, -9.8)
WORLD = World((-1.0, -1.0, 0.0), (1.0, 1.0, 1.0), gravity=G, ground_height=0.0, fps=FPS)


def spinning_body(v0, c0, frames=6):
    """Points of a cube spinning about z while its centre flies a ballistic arc."""
    g = torch.linspace(-0.05, 0.05, 5)
    body = torch.stack(torch.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    out = []
    for f in range(frames):
        t = f / FPS
        a = 3.0 * t  # rad
        rot = torch.tensor(
            [[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]]
        )
        centre = torch.tensor(c0) + torch.tensor(v0) * t + 0.5 * torch.tensor(G) * t**2
        out.append(body @ rot.T + centre)
    return torch.stack(out)


def test_ballistic_fit_recovers_v0_of_a_spinning_body_over_any_window():
    pts = {1: spinning_body([0.4, -1.2, 0.9], [0.0, 0.3, 0.4])}
    for frames in (2, 4, 6):
        v0 = initial_velocity_from_points(pts, fps=FPS, gravity=G, frames=frames)[1]
        assert torch.allclose(v0, torch.tensor([0.4, -1.2, 0.9]), atol=1e-4), frames


def test_free_flight_ends_when_bodies_come_within_the_gap():
    a = spinning_body([0.0, 1.0, 0.0], [0.0, -0.3, 0.5], frames=8)
    b = spinning_body([0.0, -1.0, 0.0], [0.0, 0.3, 0.5], frames=8)
    # surfaces start 0.5 m apart and close at 2 m/s: 0.5 - 2 f / 24 < 0.1 from f = 5 on
    assert free_flight_frames({1: a, 2: b}, WORLD, gap=0.1) == 5
    # alone it falls from z = 0.5: its base (0.45 m - g t^2 / 2) is below 0.1 m from f = 7 on
    assert free_flight_frames({1: a}, WORLD, gap=0.1) == 7


def test_stiffness_ceiling_puts_the_p_wave_at_the_cfl_speed():
    dx, dt, cfl = 0.025, 1.0 / 960, 0.5
    caps = stiffness_ceilings({1: "elastic"}, {1: {"rho": 800.0, "nu": 0.3}}, dx=dx, dt=dt, cfl=cfl)
    e, nu, rho = caps[1]["E"], 0.3, 800.0
    p_wave = e * (1 - nu) / ((1 + nu) * (1 - 2 * nu))
    assert math.sqrt(p_wave / rho) == pytest.approx(cfl * dx / dt)
    vec = ParameterVector.create(
        {1: "elastic", 2: "elastic"},
        {1: torch.zeros(3), 2: torch.zeros(3)},
        values={2: {"E": 1e7}},
        ceilings=stiffness_ceilings({1: "elastic", 2: "elastic"}, {}, dx=dx, dt=dt, cfl=cfl),
    )
    # a start above the ceiling starts at it; the optimiser's bound is the ceiling
    e2 = float(vec.physical().objects[2].values["E"])
    assert e2 == pytest.approx(vec.specs["obj2.E"].upper, rel=1e-5) and e2 < 1e6


@pytest.mark.parametrize("backend", ["warp-mpm", "taichi-mpm"])
def test_ballistic_fit_of_a_simulated_fall_recovers_v0_once_given_the_time_step(backend):
    """A free body rolled out by an MPM backend: its centroid follows symplectic Euler, whose
    line through c(t) - g t^2 / 2 has slope v0 + g h / 2 (h the substep). Told h, the fit
    returns the v0 the simulator was given; without it, one off by g h / 2."""
    from mosiv_framework.registry import get_registry
    from mosiv_framework.testing.shapes import block, default_params

    if backend not in get_registry().names("simulator"):  # each backend is an optional plugin
        pytest.skip(f"simulator {backend!r} is not installed")
    substeps = 10
    sim = get_registry().create(
        "simulator", backend, {"grid": 16, "substeps": substeps, "device": "cpu"}
    )
    world = World((0.0, 0.0, 0.0), (1.0, 1.0, 1.0), gravity=G, ground_height=None, fps=FPS)
    particles = block((0.4, 0.4, 0.5), (0.5, 0.5, 0.6), spacing=0.025, object_id=1)
    v0 = (0.3, -0.2, 0.8)
    params = default_params(particles, velocities={1: v0})
    traj = sim.rollout(particles, params, world=world, frames=4)
    points = {1: traj.object_positions(1).detach()}
    h = 1.0 / (FPS * substeps)
    told = initial_velocity_from_points(points, fps=FPS, gravity=G, frames=5, time_step=h)[1]
    assert torch.allclose(told.double(), torch.tensor(v0, dtype=torch.float64), atol=2e-5)
    untold = initial_velocity_from_points(points, fps=FPS, gravity=G, frames=5)[1]
    bias = untold.double() - torch.tensor(v0, dtype=torch.float64)
    expected = 0.5 * h * torch.tensor(G, dtype=torch.float64)  # -20 mm/s in z here
    assert torch.allclose(bias, expected, atol=2e-5)


def _p_wave_speed(values: dict) -> float:
    e, nu, rho = values["E"], values["nu"], values["rho"]
    return math.sqrt(e * (1 - nu) / ((1 + nu) * (1 - 2 * nu)) / rho)


def test_keep_stable_holds_the_p_wave_limit_at_the_current_poisson_ratio_and_density():
    dx, dt, cfl = 0.025, 1.0 / 960, 0.5
    limit = cfl * dx / dt
    vec = ParameterVector.create(
        {1: "elastic", 2: "elastic", 3: "elastic"},
        {k: torch.zeros(3) for k in (1, 2, 3)},
        # 1: at its ceiling (computed at the default nu 0.25) but nu 0.44; 2: nu 0.44 and a
        # soft E; 3: at the ceiling with a density half the default's
        values={1: {"E": 1e7, "nu": 0.44}, 2: {"E": 1e4, "nu": 0.44}, 3: {"E": 1e7, "rho": 500.0}},
        ceilings=stiffness_ceilings({k: "elastic" for k in (1, 2, 3)}, {}, dx=dx, dt=dt, cfl=cfl),
    )
    vec.wave_speed_limit = limit  # given to create, the start would already be held to it

    def values(k):
        return {n: float(v) for n, v in vec.physical().objects[k].values.items()}

    assert _p_wave_speed(values(1)) > 1.5 * limit  # the start's ceiling does not hold at nu 0.44
    e2 = values(2)["E"]
    assert sorted(vec.keep_stable()) == ["obj1.E", "obj3.E"]
    for k in (1, 3):
        assert _p_wave_speed(values(k)) == pytest.approx(limit, rel=1e-4)
    assert values(1)["nu"] == pytest.approx(0.44) and values(3)["rho"] == pytest.approx(500.0)
    assert values(2)["E"] == e2  # inside the limit: untouched
    assert vec.keep_stable() == []  # idempotent
    vec.wave_speed_limit = None
    assert vec.keep_stable() == []


def _cube_along(centres: torch.Tensor) -> torch.Tensor:
    """A spinning cube of 5x5x5 points 2.5 cm apart whose centroid follows ``centres``."""
    g = torch.linspace(-0.05, 0.05, 5)
    body = torch.stack(torch.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    out = []
    for f, centre in enumerate(centres):
        a = 3.0 * f / FPS
        rot = torch.tensor(
            [[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]]
        )
        out.append(body @ rot.T + centre)
    return torch.stack(out)


def _path(c0, v0, frames=8, *, bounce_at=None, extra=(0.0, 0.0, 0.0)):
    """Centroids of a ballistic flight (plus a constant ``extra`` acceleration), the y
    velocity reversed at time ``bounce_at`` (frames)."""
    acc = torch.tensor(G) + torch.tensor(extra)
    c, v = torch.tensor(c0), torch.tensor(v0)
    out = []
    for f in range(frames):
        t = f / FPS
        if bounce_at is not None and f > bounce_at:
            tb = bounce_at / FPS
            cb, vb = c + v * tb + 0.5 * acc * tb**2, (v + acc * tb) * torch.tensor([1, -1, 1])
            out.append(cb + vb * (t - tb) + 0.5 * acc * (t - tb) ** 2)
        else:
            out.append(c + v * t + 0.5 * acc * t**2)
    return torch.stack(out)


def test_free_flight_ends_where_a_contact_acting_at_a_distance_bends_the_centroids():
    """Two cubes that close at 2 m/s and bounce at 4.5 frames with their surfaces still
    2.5 cm apart (as an MPM engine's grid holds touching bodies): the gap of a fine simulator
    grid (1.6 cm) never sees them touch; the centroids leaving their parabolas do, at frame 5."""
    world = World((-1.0, -1.0, 0.0), (1.0, 1.0, 1.0), gravity=G, ground_height=None, fps=FPS)
    a = _cube_along(_path([0.0, -0.25, 0.5], [0.0, 1.0, 0.0], bounce_at=4.5))
    b = _cube_along(_path([0.0, 0.25, 0.5], [0.0, -1.0, 0.0], bounce_at=4.5))
    assert free_flight_frames({1: a, 2: b}, world, gap=0.016) == 8
    assert free_flight_frames({1: a, 2: b}, world, gap=0.016, ballistic_tolerance=0.1) == 5


def test_a_body_force_far_from_everything_does_not_end_free_flight():
    """A constant wind bends a lone body's centroid off the gravity parabola, but nothing is
    near it to touch: free flight goes on (the diagnosis reads such forces from these frames);
    with a second body passing close, the same bend ends it."""
    world = World((-1.0, -1.0, 0.0), (1.0, 1.0, 1.0), gravity=G, ground_height=None, fps=FPS)
    windy = _cube_along(_path([0.0, -0.5, 0.5], [0.0, 0.5, 0.0], extra=(3.0, 0.0, 0.0)))
    assert free_flight_frames({1: windy}, world, gap=0.016, ballistic_tolerance=0.1) == 8
    near = _cube_along(_path([0.18, -0.5, 0.5], [0.0, 0.5, 0.0]))  # 8 cm beside it
    assert free_flight_frames({1: windy, 2: near}, world, gap=0.016, ballistic_tolerance=0.1) <= 3


def test_keep_stable_scales_both_moduli_of_a_two_modulus_law_to_the_limit():
    """non_newtonian's P-wave modulus is K + 4 G / 3: both identified moduli go down by one
    factor until their sum is at the limit (each capped alone, the sum could reach twice it);
    a start past the limit given to create starts at it."""
    limit = 20.0
    vec = ParameterVector.create(
        {1: "elastic", 2: "non_newtonian"},
        {1: torch.zeros(3), 2: torch.zeros(3)},
        values={2: {"bulk_modulus": 1e6, "shear_modulus": 3e5}},
        wave_speed_limit=limit,
    )
    p = {n: float(v) for n, v in vec.physical().objects[2].values.items()}
    modulus = p["bulk_modulus"] + 4 * p["shear_modulus"] / 3
    assert math.sqrt(modulus / p["rho"]) == pytest.approx(limit, rel=1e-4)
    assert p["bulk_modulus"] / p["shear_modulus"] == pytest.approx(1e6 / 3e5, rel=1e-4)
    assert vec.keep_stable() == []


def test_a_stiffness_at_its_lower_bound_is_not_reported_as_lowered_again():
    # density 50 and nu 0.45: even E's lower bound (1e3 Pa) runs past a 1 m/s limit
    vec = ParameterVector.create(
        {1: "elastic", 2: "elastic"},
        {1: torch.zeros(3), 2: torch.zeros(3)},
        values={2: {"E": 5e4, "nu": 0.45, "rho": 50.0}},
    )
    vec.wave_speed_limit = 1.0
    assert vec.keep_stable() == ["obj1.E", "obj2.E"]
    assert float(vec.physical().objects[2].values["E"]) == pytest.approx(1e3, rel=1e-4)
    assert vec.keep_stable() == []
