"""Grid-node addressing for the grid kernels: a node's flat index, and the window of nodes a
substep visits (state.Window), either found on the host (``set_box_row``) or on the device
from the particles' stencil bases (``box_from_bounds``, kernels.stencil_base_bounds), where a
captured CUDA graph can replay it."""

from __future__ import annotations

import warp as wp


@wp.func
def node_index(f: int, i: int, j: int, k: int, nodes: wp.vec3i):
    return ((f * nodes[0] + i) * nodes[1] + j) * nodes[2] + k


@wp.func
def box_ijk(r: int, lo: wp.vec3i, dims: wp.vec3i):
    # node (i, j, k) of the r-th node of a box of nodes (state.NodeBox), k fastest
    return wp.vec3i(
        lo[0] + r // (dims[1] * dims[2]), lo[1] + (r // dims[2]) % dims[1], lo[2] + r % dims[2]
    )


@wp.func
def window_cell(t: int, boxes: wp.array(dtype=wp.vec3i), row: int, stride: int):
    # thread t of a launch over a node window (state.Window): (field, i, j, k) of its node, the
    # field -1 for a thread past the box's nodes. Row ``row`` of ``boxes`` is the box (first
    # node, then node counts per axis); each field has ``stride`` threads, at least the box's
    # node count: the box's own count when the host knows it, the whole grid's when the box is
    # found on the device inside a captured graph (whose launch sizes are fixed)
    lo = boxes[2 * row]
    dims = boxes[2 * row + 1]
    r = t % stride
    out = wp.vec4i(-1, 0, 0, 0)
    if r < dims[0] * dims[1] * dims[2]:
        c = box_ijk(r, lo, dims)
        out = wp.vec4i(t // stride, c[0], c[1], c[2])
    return out


@wp.kernel
def set_box_row(boxes: wp.array(dtype=wp.vec3i), row: int, lo: wp.vec3i, dims: wp.vec3i):
    # a box the host found (state.NodeBox) into row ``row`` of the run's box table
    boxes[2 * row] = lo
    boxes[2 * row + 1] = dims


@wp.kernel
def box_from_bounds(
    bounds: wp.array(dtype=int), nodes: wp.vec3i, boxes: wp.array(dtype=wp.vec3i), row: int
):
    """Row ``row`` of the box table from stencil_base_bounds' result, as NodeBox.from_bases
    makes it on the host: the nodes of every stencil between the bounds plus one node of
    margin each side, clipped to the grid; the whole grid if no particle was counted."""
    lo = wp.vec3i(0, 0, 0)
    dims = nodes
    if bounds[0] <= bounds[3] and bounds[1] <= bounds[4] and bounds[2] <= bounds[5]:
        top = nodes - wp.vec3i(1, 1, 1)
        lo = wp.vec3i(
            wp.clamp(bounds[0] - 1, 0, top[0]),
            wp.clamp(bounds[1] - 1, 0, top[1]),
            wp.clamp(bounds[2] - 1, 0, top[2]),
        )
        hi = wp.vec3i(  # the last stencil node (base + 2), plus the margin
            wp.clamp(bounds[3] + 3, 0, top[0]),
            wp.clamp(bounds[4] + 3, 0, top[1]),
            wp.clamp(bounds[5] + 3, 0, top[2]),
        )
        dims = hi - lo + wp.vec3i(1, 1, 1)
    boxes[2 * row] = lo
    boxes[2 * row + 1] = dims
