"""The ``genesis`` scene source.

The planning parts (options, shapes, parameters, layout, cameras, concealment specs) are plain
numpy and always tested. Generating a scene needs the Genesis engine (genesis-world); those
tests are marked ``genesis_engine`` and deselected, with the reason, when it is not installed
(conftest.py). What reads a Genesis recording is tested on the committed scene in
test_genesis_recording.py.
"""

from __future__ import annotations

import math
import subprocess
import sys

import numpy as np
import pytest
import torch
from mosiv_genesis import plan as P
from mosiv_genesis.options import GenesisOptions

from mosiv_framework.conceal import parse_conceal
from mosiv_framework.errors import ConfigError
from mosiv_framework.registry import get_registry
from mosiv_framework.scene.protocol import launch_velocity


# ------------------------------------------------------------------ planning (no Genesis)
def test_plugin_registers_without_importing_genesis():
    code = "import sys, mosiv_genesis.plugin; print('genesis' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"
    assert get_registry().get("scene_source", "genesis").options is GenesisOptions


def test_options_list_every_problem():
    with pytest.raises(ConfigError) as err:
        GenesisOptions(n_objects=4, materials="elastic,lava", vis_mode="x", conceal="fog")
    text = str(err.value)
    for part in ("n_objects=4", "'lava'", "vis_mode", "conceal"):
        assert part in text
    assert GenesisOptions(materials="sand, snow").materials == ["sand", "snow"]


def test_conceal_specs_round_trip_and_ground_friction_is_refused():
    effects = parse_conceal("wind:acceleration=2,0,0;linear_drag")
    assert effects[0].params == {"acceleration": (2.0, 0.0, 0.0)}
    assert effects[1].params == {"coefficient": 1.5}
    assert parse_conceal([e.spec() for e in effects]) == effects
    with pytest.raises(ConfigError, match="ground_friction"):
        GenesisOptions(conceal="ground_friction")


@pytest.mark.parametrize("name", P.SHAPE_NAMES)
def test_meshes_are_watertight_centred_and_sized(name):
    rng = np.random.default_rng(0)
    mesh = P.make_mesh(name, 0.12, P.random_rotation(rng))
    assert mesh.is_watertight and mesh.volume > 0
    assert np.allclose(mesh.center_mass, 0.0, atol=1e-9)
    # rotated, the axis-aligned box may grow, but the farthest vertex stays within the size
    assert 0.06 <= 2 * np.max(np.linalg.norm(mesh.vertices, axis=1)) <= 0.12 * math.sqrt(3)


def _genesis_liquid_stress(j_old: float, C: torch.Tensor, dt: float, mu: float, lam: float):
    """Genesis's viscous Liquid (genesis-world 1.4.5): F was reset to j_old^(1/3) I, the next
    substep's F_tmp = j_old^(1/3) (I + dt C) gives 2 mu (F_tmp - R) F_tmp^T + lam J (J - 1) I,
    R the rotation of F_tmp's polar decomposition (written here from that definition)."""
    eye = torch.eye(3, dtype=torch.float64)
    F = j_old ** (1.0 / 3.0) * (eye + dt * C)
    U, _, Vh = torch.linalg.svd(F)
    J = torch.linalg.det(F)
    return 2.0 * mu * (F - U @ Vh) @ F.T + lam * J * (J - 1.0) * eye, F


@pytest.mark.parametrize("nu", [0.15, 0.25, 0.4])
def test_liquid_is_a_newtonian_fluid_of_viscosity_mu_dt_and_bulk_modulus_k(nu):
    """The scene-format parameters of a Genesis Liquid give MOSIV's newtonian law the stress
    Genesis takes, to first order: over random strain rates and volume changes of 1e-3 the
    two deviatoric Kirchhoff stresses differ by < 1 % of the viscous stress, and the mean
    stresses by the newtonian law's bulk viscosity to < 1 % of the pressure."""
    from mosiv_framework.laws import get_law

    p = {"E": 8.0e4, "nu": nu, "rho": 1000.0}
    dt = 1.0 / (24.0 * 140.0)
    params = P.scene_format_params("newtonian", p, substep_dt=dt)
    mu = p["E"] / (2.0 * (1.0 + nu))
    lam = p["E"] * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))
    assert params["viscosity"] == pytest.approx(mu * dt)
    assert params["bulk_modulus"] == pytest.approx(lam + 2.0 * mu / 3.0)
    law = get_law("newtonian")
    values = {
        k: torch.tensor([params[k]], dtype=torch.float64) for k in ("viscosity", "bulk_modulus")
    }
    eye = torch.eye(3, dtype=torch.float64)

    def dev(s: torch.Tensor) -> torch.Tensor:
        return s - s.trace() / 3.0 * eye

    gen = torch.Generator().manual_seed(0)
    for _ in range(10):
        C = torch.randn(3, 3, generator=gen, dtype=torch.float64)  # 1/s, |C| ~ 3
        j_old = 1.0 + 1e-3 * float(torch.randn(1, generator=gen))
        theirs, F = _genesis_liquid_stress(j_old, C, dt, mu, lam)
        J = torch.linalg.det(F)
        ours = law.kirchhoff_stress(
            (J ** (1.0 / 3.0) * torch.eye(3, dtype=torch.float64))[None],
            values,
            velocity_gradient=C[None],
        )[0]
        viscous = 2.0 * mu * dt * (C + C.T) / 2.0
        assert torch.linalg.norm(dev(ours) - dev(theirs)) < 0.01 * torch.linalg.norm(viscous)
        # the mean stresses differ by the newtonian law's bulk viscosity, (2/3) viscosity div v,
        # which Genesis's liquid lacks and a nearly incompressible flow hardly excites
        pressure = (lam + 2.0 * mu / 3.0) * abs(float(J) - 1.0)
        bulk_viscous = 2.0 / 3.0 * float(J) * mu * dt * float(C.trace())
        mean_gap = float(ours.trace() - theirs.trace()) / 3.0
        assert abs(mean_gap - bulk_viscous) < 0.01 * pressure


def test_scene_format_keeps_the_solids_own_names():
    assert set(
        P.scene_format_params(
            "snow", P.sample_params("snow", np.random.default_rng(0)), substep_dt=1e-4
        )
    ) == {"E", "nu", "rho"}


@pytest.mark.parametrize("k", [2, 3])
def test_layout_aims_objects_to_touch_at_the_collision_point(k):
    rng = np.random.default_rng(5)
    shapes = [P.make_mesh(n, 0.1, P.random_rotation(rng)).vertices for n in P.SHAPE_NAMES[:k]]
    radii = [float(np.max(np.linalg.norm(s, axis=1))) for s in shapes]
    a = np.array([0.3, 0.0, -9.8])
    t = 0.2
    layout = P.plan_layout(shapes, radii=radii, collision_time=t, acceleration=a, rng=rng)
    u = layout.targets[1] - layout.targets[0]
    u /= np.linalg.norm(u)
    # objects 1 and 2 meet at the collision point: each reaches it exactly along u
    assert P.support(shapes[0] + layout.targets[0], u) == pytest.approx(layout.collision_point @ u)
    assert P.support(shapes[1] + layout.targets[1], -u) == pytest.approx(
        -layout.collision_point @ u
    )
    for start, target, r in zip(layout.starts, layout.targets, radii):
        v0 = launch_velocity(start, target, t, a)
        assert np.allclose(start + v0 * t + 0.5 * a * t * t, target)  # ballistic x(t)
        for s in np.linspace(0.0, t, 9):  # the whole planned flight stays inside the domain
            x = start + v0 * s + 0.5 * a * s * s
            assert np.all(x - r >= np.array(P.DOMAIN_LOWER)) and np.all(x + r <= P.DOMAIN_UPPER)


# ------------------------------------------------------------ generation (needs Genesis)
def visible_hit_fractions(scene, frame: int = 0):
    """(camera, object) -> (fraction of GT points no other object hides, fraction of those
    whose pixel (floor v, floor u) carries the object's id); same rule as mosiv-synth's test."""
    gt = {k: p[frame].double() for k, p in scene.gt_points().items()}
    out = {}
    for cam in scene.cameras:
        mask = scene.mask(cam.id, frame)
        proj = {}
        for k, pts in gt.items():
            uv, z = cam.project(pts)
            proj[k] = (np.floor(uv.numpy()).astype(np.int64), z.numpy())
        for k, (pix, depth) in proj.items():
            col, row = pix[:, 0], pix[:, 1]
            inside = (col >= 0) & (col < cam.width) & (row >= 0) & (row < cam.height) & (depth > 0)
            hidden = np.zeros(len(col), dtype=bool)
            for j, (pj, dj) in proj.items():
                if j == k:
                    continue
                nearest = np.full((cam.height, cam.width), np.inf)
                ok = (pj[:, 0] >= 0) & (pj[:, 0] < cam.width) & (pj[:, 1] >= 0)
                ok &= pj[:, 1] < cam.height
                np.minimum.at(nearest, (pj[ok, 1], pj[ok, 0]), dj[ok])
                hidden[inside] |= nearest[row[inside], col[inside]] < depth[inside]
            hit = np.zeros(len(col), dtype=bool)
            hit[inside] = mask[row[inside], col[inside]] == k
            out[(cam.id, k)] = (float((~hidden).mean()), float(hit[~hidden].mean()))
    return out


@pytest.fixture(scope="module")
def genesis_scene(tmp_path_factory):
    source = get_registry().create(
        "scene_source",
        "genesis",
        {
            "resolution": 128,
            "n_cameras": 4,
            "n_frames": 6,
            "observed_frames": 3,
            "collision_frame": 4,
            "grid_density": 32,
            "substeps": 70,
            "particle_size": 0.015,
            "materials": "elastic,sand",
            "seed": 3,
            "progress": False,
        },
    )
    return source.generate(tmp_path_factory.mktemp("genesis") / "scene")


@pytest.mark.genesis_engine
@pytest.mark.slow
def test_genesis_scene_passes_the_checker(genesis_scene):
    from mosiv_framework.scene import check_scene, read_scene

    assert check_scene(genesis_scene) == []
    scene = read_scene(genesis_scene)
    assert scene.n_frames == 6 and len(scene.cameras) == 4 and len(scene.objects) == 2
    ids = scene.load_mask_ids(frames=[0])
    assert (ids == 1).any() and (ids == 2).any()


@pytest.mark.genesis_engine
@pytest.mark.slow
def test_genesis_gt_points_project_into_their_masks(genesis_scene):
    from mosiv_framework.scene import read_scene

    for (cam, k), (shown, hit) in visible_hit_fractions(read_scene(genesis_scene)).items():
        assert shown > 0.5, f"{cam}: object {k} mostly hidden"
        assert hit >= 0.95, f"{cam}: only {hit:.3f} of object {k}'s visible points in its mask"


@pytest.mark.genesis_engine
@pytest.mark.slow
def test_genesis_objects_fly_ballistically_before_contact(genesis_scene):
    """Frames 0..2 (collision planned at 4): centroids follow x0 + v0 t + g t^2 / 2."""
    import json

    from mosiv_framework.scene import read_scene

    scene = read_scene(genesis_scene)
    doc = json.loads((genesis_scene / "gt" / "params.json").read_text())
    gt = scene.gt_points()
    g = np.array(scene.gravity)
    for obj in doc["objects"]:
        x0, v0 = np.array(obj["initial_centroid"]), np.array(obj["initial_velocity"])
        for t in range(3):
            s = t / scene.fps
            expected = x0 + v0 * s + 0.5 * g * s * s
            assert np.allclose(gt[obj["id"]][t].numpy().mean(0), expected, atol=3e-3)


@pytest.mark.genesis_engine
@pytest.mark.slow
@pytest.mark.parametrize("kind", ["wind", "linear_drag"])
def test_genesis_concealed_effect_moves_the_recording(kind, tmp_path):
    """A concealed force field at its default strength shifts a centroid by > 1 cm by the last
    frame, and only gt/effects.json tells."""
    import json

    from mosiv_framework.scene import check_scene, read_scene

    tiny = {
        "resolution": 16, "n_cameras": 1, "n_frames": 12, "observed_frames": 6,
        "collision_frame": 3, "grid_density": 32, "substeps": 70, "particle_size": 0.015,
        "materials": "elastic,plasticine", "shapes": "apple,barrel", "seed": 1, "progress": False,
    }  # fmt: skip
    paths = {
        name: get_registry()
        .create("scene_source", "genesis", {**tiny, **extra})
        .generate(tmp_path / name)
        for name, extra in (("plain", {}), (kind, {"conceal": kind}))
    }
    centroids = {
        name: np.stack([p[-1].numpy().mean(0) for p in read_scene(path).gt_points().values()])
        for name, path in paths.items()
    }
    # the table (z = 0) stops the bodies: Genesis' MPM boundary sits on it, not above or below
    lowest = min(float(p[:, :, 2].min()) for p in read_scene(paths["plain"]).gt_points().values())
    assert -0.005 < lowest < 0.01
    shift = np.linalg.norm(centroids[kind] - centroids["plain"], axis=1)
    assert shift.max() > 0.01, f"{kind}: last-frame centroid shifts {shift} m"
    assert check_scene(paths[kind]) == []
    effects = json.loads((paths[kind] / "gt" / "effects.json").read_text())["effects"]
    assert effects == [parse_conceal(kind)[0].to_json()]
    plain_json = json.loads((paths["plain"] / "scene.json").read_text())
    assert json.loads((paths[kind] / "scene.json").read_text()) == plain_json
