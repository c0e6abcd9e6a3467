"""The particle-grid transfers (transfer_kernels.py): each particle array read once per thread,
and the split kernels equal to the fused ones they replaced.

Warp's adjoint of a read a[p] is one atomic add into a's gradient per read in the code, so each
transfer kernel reads each particle array once, into a local. P2G and G2P were each one kernel
with the law's stress or return map inside; forward rollouts still run those fused forms
(transfer_kernels.p2g_fused, g2p_fused), while the backward's taped replay runs the split
kernels. The comparison below tapes the fused forms in the replay instead (MPMRun's own
launches, asked for the fused form), so the rollouts are the same code and what it checks is
the backward: the split kernels' adjoints give the fused kernels' gradients, the same sums
grouped differently
(measured on the CPU: within 2e-6 of the largest magnitude, E's); and that the split kernels
compute what the fused ones do, over every law.
"""

from __future__ import annotations

import ast
import inspect
import textwrap
from collections import Counter

import pytest
import torch
import warp as wp
from mosiv_warp_mpm import transfer_kernels as T
from mosiv_warp_mpm.run import MPMRun

from mosiv_framework.laws import FAMILIES
from mosiv_framework.testing.shapes import combine, default_params, sphere
from mosiv_framework.types import World

_own_p2g = MPMRun.p2g
_own_g2p_launches = MPMRun._g2p_launches


def _fused_p2g(run, src, grid, gathered=None, stress=None, looped_on=None) -> None:
    """MPMRun.p2g in its fused form even where the replay asks for the split one: one launch,
    the stress inside the scatter, taped as it ran."""
    _own_p2g(run, src, grid, gathered)


def _fused_g2p_launches(run, src, dst, grid, s, gathered=None, *, split=False) -> list[tuple]:
    """MPMRun._g2p_launches in its fused form even where the replay asks for the split one."""
    return _own_g2p_launches(run, src, dst, grid, s, gathered, split=False)


WORLD = World((0.0, 0.0, 0.0), (0.5, 0.5, 0.5), ground_height=0.0, fps=24.0)
#: |new - old| <= RTOL max |old| per gradient: float32 round-off in F's gradient, carried
#: back through the frames and substeps (measured on the CPU: up to 8e-6, in nu and E; rho 0)
RTOL = 5e-5


def _particle_reads(kernel) -> Counter:
    """How many times the kernel's source reads each array at index ``p``."""
    tree = ast.parse(textwrap.dedent(inspect.getsource(kernel.func)))  # per-law: nested
    reads = Counter()
    for node in ast.walk(tree):
        if (
            isinstance(node, ast.Subscript)
            and isinstance(node.ctx, ast.Load)
            and isinstance(node.value, ast.Name)
            and isinstance(node.slice, ast.Name)
            and node.slice.id == "p"
        ):
            reads[node.value.id] += 1
    return reads


TRANSFERS = [T.p2g, T.g2p, *T.PARTICLE_STRESS.values(), *T.UPDATE_DEFORMATION.values()]
TRANSFERS += [T.p2g_fused, T.g2p_fused]


@pytest.mark.parametrize("kernel", TRANSFERS, ids=lambda k: k.key)
def test_each_particle_array_is_read_once(kernel) -> None:
    reads = _particle_reads(kernel)
    assert reads and max(reads.values()) == 1, reads


def _reads_twice(a: wp.array(dtype=float), out: wp.array(dtype=float)):
    p = wp.tid()
    out[p] = a[p] * a[p]


def test_the_read_count_sees_repeated_reads() -> None:
    reads_twice = type("Kernel", (), {"func": _reads_twice})  # _particle_reads reads .func
    assert _particle_reads(reads_twice) == Counter({"a": 2})


def _scene():
    # two laws, contact between two fields, ground contact and material damping
    a = sphere((0.30, 0.25, 0.07), 0.05, spacing=1.0 / 64, object_id=1, material="elastic")
    b = sphere((0.40, 0.25, 0.09), 0.05, spacing=1.0 / 64, object_id=2, material="plasticine")
    p = combine([a, b])
    params = default_params(
        p,
        overrides={1: {"friction": 0.3}, 2: {"friction": 0.2}},
        velocities={1: (2.0, 0.0, -0.5), 2: (-0.5, 0.0, -1.0)},
        terms={"material_damping": {"viscosity": 2.0}},
        requires_grad=True,
    )
    return p, params


def _rollout(sim) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    p, params = _scene()
    traj = sim.rollout(p, params, world=WORLD, frames=3)
    weights = torch.randn(len(p), 3, generator=torch.Generator().manual_seed(2))
    (traj.positions[1:] * weights).sum().backward()
    grads = {n: t.grad.clone() for n, t in params.named_tensors() if t.grad is not None}
    return traj.positions.detach(), grads


def _every_law():
    """One small sphere of each law, side by side and falling onto the ground together."""
    parts = [
        sphere((0.08 + 0.045 * i, 0.25, 0.06), 0.02, spacing=1.0 / 64, object_id=i + 1, material=f)
        for i, f in enumerate(FAMILIES)
    ]
    p = combine(parts)
    velocities = {i + 1: (0.5 - 0.1 * i, 0.2, -1.0) for i in range(len(FAMILIES))}
    return p, default_params(p, velocities=velocities)


def test_split_transfers_compute_what_the_fused_ones_do(make_warp_simulator, monkeypatch):
    """The taped replay recomputes with the split transfers what the forward rollout and the
    re-simulation computed with the fused ones: every law, contact and ground, bit for bit on
    the CPU (float32 rounding of CUDA's atomics apart)."""
    p, params = _every_law()
    fused = make_warp_simulator(grid=24, substeps=20).rollout(p, params, world=WORLD, frames=3)
    fused_substep = MPMRun.substep

    def split_substep(self, src, dst, grid, s, window, stress=None):
        stress = wp.zeros(self.n, dtype=wp.mat33, device=self.device)
        fused_substep(self, src, dst, grid, s, window, stress)

    monkeypatch.setattr(MPMRun, "substep", split_substep)
    split = make_warp_simulator(grid=24, substeps=20).rollout(p, params, world=WORLD, frames=3)
    assert float((fused.positions[-1] - fused.positions[0]).abs().max()) > 0.01  # they moved
    if not wp.get_device(make_warp_simulator().device).is_cuda:
        assert torch.equal(split.positions, fused.positions)
        assert torch.equal(split.velocities, fused.velocities)
    else:
        assert torch.allclose(split.positions, fused.positions, rtol=1e-4, atol=1e-6)


def test_split_adjoints_give_the_fused_kernels_gradients(make_warp_simulator, monkeypatch):
    pos_new, new = _rollout(make_warp_simulator(grid=16, substeps=30))
    with monkeypatch.context() as m:
        m.setattr(MPMRun, "p2g", _fused_p2g)
        m.setattr(MPMRun, "_g2p_launches", _fused_g2p_launches)
        pos_old, old = _rollout(make_warp_simulator(grid=16, substeps=30))
    on_cpu = not wp.get_device(make_warp_simulator().device).is_cuda
    if on_cpu:
        assert torch.equal(pos_new, pos_old)
    else:  # CUDA adds P2G's atomics in schedule order
        assert torch.allclose(pos_new, pos_old, rtol=1e-4, atol=1e-6)
    assert new.keys() == old.keys() and len(new) >= 5
    for name, g in old.items():
        scale = float(g.abs().max())
        assert scale > 0.0, name
        err = float((new[name] - g).abs().max()) / scale
        assert err <= (RTOL if on_cpu else 1e-3), f"{name}: {err:.2g}"
