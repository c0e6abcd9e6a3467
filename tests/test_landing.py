"""mosiv_framework.pipeline.landing: the ground's Coulomb coefficient from recorded landings.

Checked against Coulomb's law itself: a body that lands and keeps sliding loses tangential
momentum mu times the normal impulse, so an exactly integrated landing must give mu back; a
body that stops sliding gives less (a lower bound); a landing next to another body, or none,
gives nothing. Then against warp-mpm's ground: a block landing on a table of coefficient
0.3 reads as about 0.3. Finally the start: ``identify.ground_friction_start: landing`` sets
the parameter vector's coefficient, the default where nothing can be read.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

from mosiv_framework.pipeline.landing import landing_friction, landings
from mosiv_framework.pipeline.params import GROUND_FRICTION, ParameterVector
from mosiv_framework.types import World

FPS = 24.0
G = 9.8
WORLD = World((-1, -1, 0), (1, 1, 1), gravity=(0, 0, -G), ground_height=0.0, fps=FPS)


def _cube(spacing=0.01, n=4) -> np.ndarray:
    axis = np.arange(n) * spacing
    grid = np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3)
    return grid - grid.mean(0)


def _landing(mu: float, *, vx=1.0, vz=-2.0, height=0.3, frames=16, start_x=0.0) -> np.ndarray:
    """[F, N, 3] points of a cube that falls from ``height`` (its lowest point), lands
    inelastically and slides with Coulomb friction ``mu``, integrated in steps of 1e-5 s."""
    offsets = _cube()
    half = -offsets[:, 2].min()
    x, z, u, w = start_x, height + half, vx, vz
    step, t, out = 1e-5, 0.0, []
    for f in range(frames):
        while t < f / FPS - 1e-12:
            if z - half > 0:
                w -= G * step
                z += w * step
                if z - half <= 0:  # the landing: the normal velocity stops, friction acts
                    z = half
                    u = max(0.0, u - mu * (-w))
                    w = 0.0
            else:  # sliding on the table
                u = max(0.0, u - mu * G * step)
            x += u * step
            t += step
        out.append(offsets + np.array([x, 0.0, z]))
    return np.stack(out)


def _points(*bodies) -> dict[int, torch.Tensor]:
    return {k + 1: torch.tensor(b, dtype=torch.float64) for k, b in enumerate(bodies)}


def test_a_sliding_landing_gives_its_coefficient_back():
    for mu in (0.1, 0.3):
        value, found = landing_friction(_points(_landing(mu, vx=3.0)), WORLD, 16)
        assert [x.object_id for x in found] == [1]
        assert value == pytest.approx(mu, rel=0.03), (mu, found)


def test_a_body_that_stops_sliding_gives_a_lower_bound_and_the_largest_ratio_wins():
    stopped = _landing(0.6, vx=0.3)  # the tangential speed is gone before the window ends
    sliding = _landing(0.2, start_x=0.5)
    value, found = landing_friction(_points(stopped, sliding), WORLD, 16)
    ratios = {x.object_id: x.ratio for x in found}
    assert ratios[1] < 0.6 * 0.8
    assert value == pytest.approx(max(ratios.values())) and value == pytest.approx(0.2, rel=0.03)


def test_no_ground_no_landing_or_a_neighbour_reads_nothing():
    flying = _landing(0.3, vz=3.0, height=0.5)  # still in the air at the last frame
    assert float(flying[:, :, 2].min()) > 0.1
    assert landing_friction(_points(flying), WORLD, 16) == (None, [])
    no_ground = World((-1, -1, 0), (1, 1, 1), ground_height=None, fps=FPS)
    assert landing_friction(_points(_landing(0.3)), no_ground, 16) == (None, [])
    # a second body 10 mm beside the first (the clearance is 15 mm): its push would count
    beside = _landing(0.3, start_x=0.04)
    assert landings(_points(_landing(0.3), beside), WORLD, 16) == []
    # the landing must lie inside the frames given
    landed = landings(_points(_landing(0.3)), WORLD, 16)[0].frame
    assert landing_friction(_points(_landing(0.3)), WORLD, landed + 2) == (None, [])


def test_warp_mpm_landings_read_as_a_tight_lower_bound_of_the_tables_coefficient():
    """warp-mpm's ground acts only on nodes moving into it, so a block's rebound adds normal
    impulse without friction: the reading is a lower bound, here within 35 % of the truth."""
    from mosiv_framework.testing.pytest_plugin import require_simulator
    from mosiv_framework.testing.shapes import block, default_params

    registry = require_simulator("warp-mpm")
    world = World((0, 0, 0), (1, 1, 1), gravity=(0, 0, -G), ground_height=0.0, fps=FPS)
    particles = block((0.2, 0.44, 0.12), (0.32, 0.56, 0.24), spacing=0.02, object_id=1)
    sim = registry.create("simulator", "warp-mpm", {"grid": 32, "substeps": 40, "device": "cpu"})
    read = {}
    for mu in (0.1, 0.3):
        params = default_params(
            particles, overrides={1: {"E": 2e5}}, velocities={1: (2.0, 0.0, -1.0)},
            ground_friction=mu,
        )  # fmt: skip
        with torch.no_grad():
            traj = sim.rollout(particles, params, world=world, frames=10)
        read[mu], found = landing_friction({1: traj.object_positions(1)}, world, 11)
        assert len(found) == 1, found
        assert 0.65 * mu <= read[mu] <= 1.05 * mu, (mu, found)
    assert read[0.3] > 2 * read[0.1]


def test_the_start_vector_takes_the_coefficient_whether_identified_or_fixed():
    v0 = {1: torch.zeros(3)}
    identified = ParameterVector.create({1: "elastic"}, v0, ground_friction=0.3)
    identified.set_ground_friction(0.12)
    assert float(identified.physical().ground_friction.detach()) == pytest.approx(0.12, rel=1e-5)
    fixed = ParameterVector.create(
        {1: "elastic"}, v0, ground_friction=0.3, identify_ground_friction=False
    )
    fixed.set_ground_friction(5.0)  # clamped to the coefficient's bounds
    assert float(fixed.physical().ground_friction) == pytest.approx(GROUND_FRICTION.upper)


def test_identification_starts_the_ground_at_the_landings_or_at_the_default():
    from mosiv_framework.pipeline.identification import start_ground_at_landings

    v0 = {1: torch.zeros(3)}
    vector = ParameterVector.create({1: "elastic"}, v0, ground_friction=0.3)
    vector.move_to_centre()  # the data-independent start puts the coefficient at 1.0
    assert float(vector.physical().ground_friction) == pytest.approx(1.0, rel=1e-5)
    targets = {1: torch.tensor(_landing(0.2, vx=3.0), dtype=torch.float32)}
    landed = landings({1: targets[1]}, WORLD, 16)[0].frame
    start_ground_at_landings(vector, targets, WORLD, landed + 2)  # the landing not yet seen
    assert float(vector.physical().ground_friction) == pytest.approx(GROUND_FRICTION.default)
    start_ground_at_landings(vector, targets, WORLD, 16)
    assert float(vector.physical().ground_friction) == pytest.approx(0.2, rel=0.03)
    flying = {1: torch.tensor(_landing(0.2, vz=3.0, height=0.5), dtype=torch.float32)}
    start_ground_at_landings(vector, flying, WORLD, 16)
    assert float(vector.physical().ground_friction) == pytest.approx(GROUND_FRICTION.default)


def test_the_recipe_option_reads_only_the_frames_the_parameter_phase_fits():
    """``start_vector`` with ``identify.ground_friction_start: landing``: the landing read when
    it lies in the observed frames, not when only the future or a held-out tail shows it; the
    option left at "start" keeps the stage key of runs made before it existed."""
    from types import SimpleNamespace

    from mosiv_framework.pipeline.identification import start_vector
    from mosiv_framework.pipeline.run import stage_keys
    from mosiv_framework.recipes import load_recipe

    root = Path(__file__).resolve().parents[1]
    targets = {1: torch.tensor(_landing(0.2, vx=3.0), dtype=torch.float32)}
    landed = landings(targets, WORLD, 16)[0].frame

    def start(observed, **identify):
        sets = [f"identify.{k}={v}" for k, v in identify.items()]
        recipe = load_recipe(root / "recipes" / "quickstart.yaml", ["identify.start=centre", *sets])
        scene = SimpleNamespace(
            world=WORLD, fps=FPS, gravity=WORLD.gravity, observed_frames=observed
        )
        vector, _ = start_vector(recipe, scene, {1: "elastic"}, targets, {})
        return float(vector.physical().ground_friction)

    assert start(16, ground_friction_start="landing") == pytest.approx(0.2, rel=0.03)
    assert start(16) == pytest.approx(1.0, rel=1e-5)  # the centre start, as before
    assert start(landed + 2, ground_friction_start="landing") == pytest.approx(0.3)
    held = start(landed + 5, ground_friction_start="landing", holdout_frames=3)
    assert held == pytest.approx(GROUND_FRICTION.default)
    recipe = load_recipe(root / "recipes" / "quickstart.yaml")
    plain = OmegaConf.to_container(recipe, resolve=True)
    before = {k: v for k, v in plain["identify"].items() if k != "ground_friction_start"}
    assert stage_keys(plain)["identify"] == stage_keys({**plain, "identify": before})["identify"]
    landing = {**plain, "identify": {**plain["identify"], "ground_friction_start": "landing"}}
    assert stage_keys(landing)["identify"] != stage_keys(plain)["identify"]
