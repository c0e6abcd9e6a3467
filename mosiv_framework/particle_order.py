"""Particle orders for a simulator's scatter kernels, and the permutation back to the caller's.

A GPU particle-to-grid scatter is fastest when neighbouring threads add into different grid
nodes (their atomic adds then do not serialise) that still share cache lines. Simulators keep
their particles in such an order and hand results back in the caller's order
(``scatter_ordered`` and ``ScatterOrdered.to_caller``, through ``permute_rows``, whose backward
is one gather: the same bits on every run). Per-object tables expanded to every
particle go through ``rows_of``, whose backward sums per object: torch's own backward of
``table[index]`` accumulates a million rows into a few through a sort, which took 0.21 s of a
0.57 s rollout with its backward at 1M particles on an H200 (benchmarks/rollout_profile.py,
docs/BENCHMARKS.md).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from mosiv_framework.types import ParticleSet


def cell_keys(
    positions: torch.Tensor, origin: tuple[float, float, float], dx: float, nodes: tuple[int, ...]
) -> torch.Tensor:
    """The linear index of each particle's grid cell.

    Args:
        positions: [N, 3] (m); origin: the world position of node (0, 0, 0) (m); dx: the cell
            size (m); nodes: grid nodes per axis.

    Returns:
        [N] int64 keys, increasing along the last axis fastest.
    """
    start = torch.tensor(origin, dtype=positions.dtype, device=positions.device)
    c = ((positions - start) / dx).floor().long()
    return (c[:, 0] * nodes[1] + c[:, 1]) * nodes[2] + c[:, 2]


def interleaved_cell_order(keys: torch.Tensor) -> torch.Tensor:
    """A permutation of particles with integer cell keys [N]: cell by cell, but the k-th
    particles of all cells come before the (k+1)-th ones.

    Neighbouring threads then handle neighbouring cells: their 3x3x3 stencils share cache lines
    yet rarely the same node, so the scatter's atomic adds seldom collide inside a GPU warp
    (plain cell sorting puts a cell's ~8 particles, and their 27 identical nodes, in one warp).

    Args:
        keys: [N] int64, the linear index of each particle's cell (any non-negative key).

    Returns:
        [N] int64: particle indices in scatter order.
    """
    by_cell = torch.argsort(keys, stable=True)
    sorted_keys = keys[by_cell]
    index = torch.arange(keys.numel(), device=keys.device)
    new_cell = torch.ones_like(sorted_keys, dtype=torch.bool)
    new_cell[1:] = sorted_keys[1:] != sorted_keys[:-1]
    run_start = torch.cummax(torch.where(new_cell, index, 0), dim=0).values
    rank_in_cell = index - run_start
    n_cells = int(sorted_keys[-1]) + 1 if keys.numel() else 1
    return by_cell[torch.argsort(rank_in_cell * n_cells + sorted_keys, stable=True)]


def inverse_permutation(order: torch.Tensor) -> torch.Tensor:
    """The permutation that undoes ``order``: ``x[order][inverse] == x``."""
    inverse = torch.empty_like(order)
    inverse[order] = torch.arange(order.numel(), device=order.device)
    return inverse


@dataclass(frozen=True)
class ScatterOrdered:
    """A ParticleSet's arrays in scatter order on a simulator's device (``scatter_ordered``),
    and the permutations both ways. positions [N, 3] float32 (autograd kept), volumes [N],
    obj_index [N] int64 (index into the object ids given); order: the caller's index of each
    scatter-ordered particle; inverse: its inverse."""

    positions: torch.Tensor
    volumes: torch.Tensor
    obj_index: torch.Tensor
    order: torch.Tensor
    inverse: torch.Tensor

    def to_caller(self, values: torch.Tensor, dim: int = 1) -> torch.Tensor:
        """``values`` in scatter order along ``dim`` (1 for trajectories [T, N, ...]) put back
        in the caller's order, differentiable (``permute_rows``)."""
        return permute_rows(values, self.inverse, dim=dim, inverse=self.order)


def scatter_ordered(
    particles: ParticleSet,
    object_ids: list[int],
    *,
    origin: tuple[float, float, float],
    dx: float,
    nodes: tuple[int, ...],
    device: torch.device,
) -> ScatterOrdered:
    """The particles in ``interleaved_cell_order`` of the grid (origin (m), cell size dx (m),
    nodes per axis), with each particle's object index into ``object_ids`` (ascending, as
    ``ParticleSet.object_list``)."""
    positions = particles.positions.to(device, torch.float32)
    order = interleaved_cell_order(cell_keys(positions, origin, dx, nodes))
    # object id -> object index, vectorised (a Python loop costs ~0.2 s per 1M particles)
    id_values = torch.tensor(object_ids, device=device)
    obj_index = torch.searchsorted(id_values, particles.object_ids.to(device))
    return ScatterOrdered(
        positions=positions[order],
        volumes=particles.volumes.to(device)[order],
        obj_index=obj_index[order],
        order=order,
        inverse=inverse_permutation(order),
    )


class _PermuteRows(torch.autograd.Function):
    """y = x.index_select(dim, index) for a permutation ``index`` whose inverse is given, so
    that the backward is the gather grad.index_select(dim, inverse): no accumulation, and the
    same bits on every run."""

    @staticmethod
    def forward(ctx, x, index, inverse, dim):
        ctx.inverse, ctx.dim = inverse, dim
        return x.index_select(dim, index)

    @staticmethod
    def backward(ctx, grad):
        return grad.index_select(ctx.dim, ctx.inverse), None, None, None


def permute_rows(
    x: torch.Tensor, index: torch.Tensor, dim: int = 0, inverse: torch.Tensor | None = None
) -> torch.Tensor:
    """``x`` with its entries along ``dim`` put in the order ``index`` (a permutation),
    differentiable with a gather as backward.

    Args:
        x: any tensor; index: [x.shape[dim]] int64 on x's device.
        dim: the particle axis (1 for trajectories [T, N, 3]).
        inverse: the inverse of ``index`` where the caller has it (else computed here).

    Returns:
        A new tensor of x's shape.
    """
    if x.requires_grad and torch.is_grad_enabled():
        if inverse is None:
            inverse = inverse_permutation(index)
        return _PermuteRows.apply(x, index, inverse, dim)
    return x.index_select(dim, index)


class _RowsOf(torch.autograd.Function):
    """y = table[index] for a small table (one row per object, say) and many indices, with a
    backward that sums the gradient per row in a fixed order: torch's own backward of
    ``table[index]`` accumulates through a sort, which took 0.21 s for 1M particles of one
    object on an H200 (benchmarks/rollout_profile.py). On the CPU ``index_add_`` adds in index
    order in one pass; on a GPU it would add in schedule order, so there each row is a masked
    sum (one bandwidth-bound pass per row)."""

    @staticmethod
    def forward(ctx, table, index):
        ctx.save_for_backward(index)
        ctx.rows = table.shape[0]
        return table.index_select(0, index)

    @staticmethod
    def backward(ctx, grad):
        (index,) = ctx.saved_tensors
        if grad.device.type == "cpu":
            return row_sums_in_order(grad, index, ctx.rows), None
        return row_sums_masked(grad, index, ctx.rows), None


def row_sums_in_order(values: torch.Tensor, index: torch.Tensor, rows: int) -> torch.Tensor:
    """[rows, ...]: the sum of ``values`` [N, ...] per row ``index`` [N] by ``index_add_``
    (in index order on the CPU)."""
    return values.new_zeros((rows, *values.shape[1:])).index_add_(0, index, values)


def row_sums_masked(values: torch.Tensor, index: torch.Tensor, rows: int) -> torch.Tensor:
    """The same sums, one masked reduction per row: a fixed order on any device."""
    zero = values.new_zeros(())
    shape = (values.shape[0],) + (1,) * (values.dim() - 1)
    sums = [torch.where((index == row).reshape(shape), values, zero).sum(0) for row in range(rows)]
    return torch.stack(sums)


def rows_of(table: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """Each entry's row of a small table (``table[index]``), differentiable in ``table`` with
    a per-row sum as backward.

    Args:
        table: [R, ...], e.g. one initial velocity per object; index: [N] int64 rows.

    Returns:
        [N, ...].
    """
    if table.requires_grad and torch.is_grad_enabled():
        return _RowsOf.apply(table, index)
    return table.index_select(0, index)
