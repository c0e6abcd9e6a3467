"""The engine runs its particles in scatter order (mosiv_framework.particle_order); rollouts
hand everything back in the caller's order, and gradients reach the caller's tensors.

Two bodies with different initial velocities make a wrong order visible at frame 0: a
particle's position must be its own, its velocity its object's v0. The caller's particles are
shuffled first, so the caller's order is not already the cell order.
"""

import pytest
import torch

from mosiv_framework.types import ParticleSet


def _shuffled(particles: ParticleSet) -> ParticleSet:
    """The same particles in another order."""
    perm = torch.randperm(len(particles), generator=torch.Generator().manual_seed(0))
    return ParticleSet(
        particles.positions[perm],
        particles.volumes[perm],
        particles.object_ids[perm],
        particles.materials,
    )


def test_frame_zero_is_the_callers_particles_and_velocities(simulator_factory, thrown_spheres):
    particles, params, world = thrown_spheres({})
    particles = _shuffled(particles)
    traj = simulator_factory(grid=16, substeps=30).rollout(particles, params, world=world, frames=1)
    assert torch.equal(traj.positions[0], particles.positions.float())
    for k, v0 in params.initial_velocity.items():
        rows = traj.velocities[0][particles.object_ids == k]
        assert torch.allclose(rows, v0.float().expand_as(rows))


def test_gradients_do_not_depend_on_the_callers_order(simulator_factory, thrown_spheres):
    """A loss on one physical particle's final position gives the same parameter gradients
    whether the caller's particles come shuffled or not: the permutation took the gradient
    back to the right particle. (The engine's order within a cell follows the caller's, so
    the float sums may differ in their last bits.)"""
    grads = []
    for shuffle in (False, True):
        particles, params, world = thrown_spheres({}, requires_grad=True)
        perm = torch.randperm(len(particles), generator=torch.Generator().manual_seed(0))
        if not shuffle:
            perm = torch.arange(len(particles))
        shuffled = ParticleSet(
            particles.positions[perm],
            particles.volumes[perm],
            particles.object_ids[perm],
            particles.materials,
        )
        picked = int((perm == 5).nonzero())  # particle 5 of the scene, wherever it is now
        traj = simulator_factory(grid=16, substeps=30).rollout(
            shuffled, params, world=world, frames=1
        )
        traj.positions[-1, picked].sum().backward()
        grads.append(torch.cat([params.initial_velocity[k].grad for k in (1, 2)]))
    assert grads[0].abs().max() > 0
    torch.testing.assert_close(grads[1], grads[0], rtol=1e-4, atol=1e-7)


def test_the_kernel_profiler_cannot_be_chosen_once_the_runtime_runs(simulator_factory):
    from mosiv_taichi_mpm import runtime

    runtime.ensure(simulator_factory(grid=16, substeps=30).device_name)
    with pytest.raises(RuntimeError, match="before the Taichi runtime starts"):
        runtime.profile_kernels()
