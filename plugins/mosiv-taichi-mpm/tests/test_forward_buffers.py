"""Forward-only rollouts (nothing to differentiate: torch.no_grad, or no parameter requires grad)
run on a forward-only engine: two particle-state buffers taking turns and no adjoints
(mosiv_taichi_mpm/fields.py), instead of one buffer per substep with adjoints beside them.

The two engines run the same kernels on the same state, so their rollouts agree to float32
round-off (on this machine's CPU bit for bit); their memory differs in how it grows with the
substep count.
"""

import pytest
import torch

FRAMES = 5
#: metres; the same kernels in the same order, so only the order of the particles' float32
#: atomic adds onto grid nodes may differ between runs (measured: 0 on the CPU); the split and
#: fused kernels, which also reorder those sums, differ by about 1e-6 m here (test_fused_forward)
POSITION_TOLERANCE = 1e-6
#: m/s; a position difference of POSITION_TOLERANCE within one substep (dt = 1 / (24 x 30) s)
VELOCITY_TOLERANCE = POSITION_TOLERANCE * 24 * 30


#: a ground bounce and a drag: terms every engine applies
TERMS = {"ground_restitution": {"coefficient": 0.3}, "linear_drag": {"coefficient": 0.3}}


@pytest.mark.parametrize("fused_forward", [True, False], ids=["fused", "split"])
def test_forward_only_rollout_equals_the_differentiable_one(
    simulator_factory, thrown_spheres, fused_forward
):
    sim = simulator_factory(grid=16, substeps=30, fused_forward=fused_forward)
    particles, params, world = thrown_spheres(TERMS, requires_grad=False)
    with torch.no_grad():
        forward = sim.rollout(particles, params, world=world, frames=FRAMES)
    particles, params, world = thrown_spheres(TERMS, requires_grad=True)
    taped = sim.rollout(particles, params, world=world, frames=FRAMES)
    assert taped.positions.requires_grad, "the second rollout did not take the reverse-mode path"
    assert not forward.positions.requires_grad

    moved = (forward.positions[-1] - forward.positions[0]).norm(dim=-1).max().item()
    assert moved > 0.05, "the scene barely moved: it tests nothing"
    assert forward.contact[:, 0, 1].any(), "the bodies never touched: contact is not exercised"
    position_gap = (forward.positions - taped.positions.detach()).abs().max().item()
    velocity_gap = (forward.velocities - taped.velocities).abs().max().item()
    assert position_gap <= POSITION_TOLERANCE, f"positions differ by {position_gap} m"
    assert velocity_gap <= VELOCITY_TOLERANCE, f"velocities differ by {velocity_gap} m/s"
    assert torch.equal(forward.contact, taped.contact)


def _peak_bytes(sim, scene, requires_grad: bool) -> int:
    particles, params, world = scene(TERMS, requires_grad=requires_grad)
    sim.reset_peak_memory()
    with torch.set_grad_enabled(requires_grad):
        sim.rollout(particles, params, world=world, frames=2)
    return sim.peak_memory_bytes()


def test_forward_only_memory_does_not_grow_with_substeps(thrown_spheres):
    """Field bytes (read from the allocated fields' shapes) plus checkpoints, at 10 and 40
    substeps a frame: the same forward only; the differentiable rollout's grow with the
    per-substep buffers. Fresh simulators: the shared ones may hold a differentiable engine of
    this layout from another test."""
    from mosiv_taichi_mpm.plugin import make_simulator

    few = make_simulator(device="cpu", grid=16, substeps=10)
    many = make_simulator(device="cpu", grid=16, substeps=40)
    forward = {s: _peak_bytes(sim, thrown_spheres, False) for s, sim in ((10, few), (40, many))}
    assert forward[10] == forward[40], f"forward-only bytes grow with substeps: {forward}"
    particles, params, world = thrown_spheres(TERMS)
    families = [params.objects[k].family for k in particles.object_list]
    for sim in (few, many):
        fields = sim.engine_for(len(particles), families, world, differentiable=False).fields
        assert fields.x.shape[0] == 2 and fields.F_trial.shape[0] == 1
        # the simulator keeps its engines by their ``differentiable`` flag: only the
        # forward-only one may exist after forward-only rollouts
        assert set(sim._engines) == {False}, "a forward-only rollout built another engine"

    taped = {s: _peak_bytes(sim, thrown_spheres, True) for s, sim in ((10, few), (40, many))}
    # 30 more substeps x (46 state + 12 trial floats) x 2 (values, adjoints) x 4 bytes a particle
    n = len(particles)
    assert taped[40] - taped[10] >= 30 * 58 * 2 * 4 * n, f"differentiable bytes: {taped}"
    assert taped[10] > forward[10]
