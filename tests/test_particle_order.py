"""particle_order: the interleaved cell order is a permutation with the promised structure, and
permute_rows' gather backward equals torch's own backward of the same indexing."""

from __future__ import annotations

import torch

from mosiv_framework.particle_order import (
    cell_keys,
    interleaved_cell_order,
    inverse_permutation,
    permute_rows,
    row_sums_in_order,
    row_sums_masked,
    rows_of,
    scatter_ordered,
)
from mosiv_framework.types import ParticleSet


def test_interleaved_order_puts_the_kth_particle_of_every_cell_before_the_next():
    gen = torch.Generator().manual_seed(0)
    keys = torch.randint(0, 40, (500,), generator=gen)
    order = interleaved_cell_order(keys)

    assert torch.equal(torch.sort(order).values, torch.arange(500))  # a permutation
    ordered = keys[order]
    # rank of each particle within its cell, in the original (stable) order
    rank = torch.empty(500, dtype=torch.long)
    for key in keys.unique():
        members = (keys == key).nonzero().flatten()
        rank[members] = torch.arange(members.numel())
    ranks = rank[order]
    assert torch.all(ranks[1:] >= ranks[:-1])  # all first particles, then all second ones...
    for r in ranks.unique():  # ...and within one rank, cells in increasing key order
        cells = ordered[ranks == r]
        assert torch.all(cells[1:] > cells[:-1])


def test_inverse_permutation_undoes_the_order():
    order = torch.randperm(97, generator=torch.Generator().manual_seed(1))
    x = torch.randn(97, 3)
    assert torch.equal(x[order][inverse_permutation(order)], x)


def test_permute_rows_backward_equals_indexing_backward():
    gen = torch.Generator().manual_seed(2)
    index = torch.randperm(64, generator=gen)
    x = torch.randn(5, 64, 3, generator=gen, requires_grad=True)
    weights = torch.randn(5, 64, 3, generator=gen)

    y = permute_rows(x, index, dim=1)
    (y * weights).sum().backward()
    ours = x.grad.clone()
    x.grad = None
    (x[:, index] * weights).sum().backward()

    assert torch.equal(y.detach(), x.detach()[:, index])
    assert torch.equal(ours, x.grad)  # a gather: the same bits, no accumulation


def test_permute_rows_without_grad_is_a_plain_index_select():
    x = torch.arange(12.0).reshape(4, 3)
    index = torch.tensor([2, 0, 3, 1])
    out = permute_rows(x, index)
    assert not out.requires_grad
    assert torch.equal(out, x[index])


def test_rows_of_backward_sums_per_row_as_indexing_does():
    gen = torch.Generator().manual_seed(3)
    table = torch.randn(4, 3, generator=gen, requires_grad=True)
    index = torch.randint(0, 3, (200,), generator=gen)  # row 3 unused: its gradient is zero
    weights = torch.randn(200, 3, generator=gen)

    out = rows_of(table, index)
    (out * weights).sum().backward()
    ours = table.grad.clone()
    table.grad = None
    (table[index] * weights).sum().backward()

    assert torch.equal(out.detach(), table.detach()[index])
    torch.testing.assert_close(ours, table.grad, rtol=1e-6, atol=1e-6)
    assert torch.all(ours[3] == 0)


def test_cell_keys_index_cells_along_the_last_axis_fastest():
    positions = torch.tensor([[0.05, 0.05, 0.05], [0.05, 0.05, 0.15], [0.15, 0.25, 0.35]])
    keys = cell_keys(positions, origin=(0.0, 0.0, 0.0), dx=0.1, nodes=(5, 6, 7))
    assert keys.tolist() == [0, 1, (1 * 6 + 2) * 7 + 3]


def test_interleaved_order_of_nothing_is_empty():
    assert interleaved_cell_order(torch.zeros(0, dtype=torch.long)).numel() == 0


def test_permute_rows_with_a_given_inverse_puts_results_back():
    """As a simulator uses it: results in scatter order, put back with index = the inverse of
    the order and the order itself as that index's inverse."""
    gen = torch.Generator().manual_seed(4)
    order = torch.randperm(50, generator=gen)
    caller = torch.randn(2, 50, 3, generator=gen, requires_grad=True)
    in_scatter_order = caller[:, order]
    back = permute_rows(in_scatter_order, inverse_permutation(order), dim=1, inverse=order)
    assert torch.equal(back.detach(), caller.detach())
    weights = torch.randn(2, 50, 3, generator=gen)
    (back * weights).sum().backward()
    assert torch.equal(caller.grad, weights)  # the identity map's gradient, exactly


def test_rows_of_a_one_dimensional_table_and_without_grad():
    table = torch.tensor([1.0, 2.0, 3.0], requires_grad=True)
    index = torch.tensor([2, 2, 0, 1, 2])
    out = rows_of(table, index)
    out.sum().backward()
    assert table.grad.tolist() == [1.0, 1.0, 3.0]
    with torch.no_grad():
        plain = rows_of(table, index)
    assert not plain.requires_grad and plain.tolist() == [3.0, 3.0, 1.0, 2.0, 3.0]


def test_both_row_sums_agree():
    """The CPU's index_add_ sums and the masked ones a GPU uses give the same per-row sums."""
    gen = torch.Generator().manual_seed(5)
    values = torch.randn(300, 3, generator=gen)
    index = torch.randint(0, 6, (300,), generator=gen)
    expected = torch.stack([values[index == r].sum(0) for r in range(7)])
    torch.testing.assert_close(row_sums_in_order(values, index, 7), expected)
    torch.testing.assert_close(row_sums_masked(values, index, 7), expected)


def test_scatter_ordered_particles_go_back_to_the_callers_order():
    gen = torch.Generator().manual_seed(6)
    positions = torch.rand(200, 3, generator=gen)
    ids = torch.where(positions[:, 0] < 0.5, 3, 7)  # object ids, not indices
    particles = ParticleSet(positions, torch.rand(200, generator=gen), ids, {3: "a", 7: "b"})
    ordered = scatter_ordered(
        particles, [3, 7], origin=(0.0, 0.0, 0.0), dx=0.25, nodes=(5, 5, 5), device="cpu"
    )
    assert torch.equal(ordered.positions, positions[ordered.order])
    assert torch.equal(ordered.volumes, particles.volumes[ordered.order])
    assert torch.equal(ordered.obj_index, (ids[ordered.order] == 7).long())
    keys = cell_keys(ordered.positions, (0.0, 0.0, 0.0), 0.25, (5, 5, 5))
    assert torch.equal(ordered.order, ordered.order[interleaved_cell_order(keys)])
    trajectory = ordered.positions.expand(2, 200, 3)
    assert torch.equal(ordered.to_caller(trajectory)[1], positions)
