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
def window_count(boxes: wp.array(dtype=wp.vec3i), row: int):
    # nodes per field of row ``row``'s box
    dims = boxes[2 * row + 1]
    return dims[0] * dims[1] * dims[2]


@wp.func
def window_ijk(boxes: wp.array(dtype=wp.vec3i), row: int, r: int):
    # node (i, j, k) of the r-th node of row ``row``'s box, k fastest
    return box_ijk(r, boxes[2 * row], boxes[2 * row + 1])


# A launch over a node window (state.Window) has ``stride`` threads per field: thread t serves
# field t // stride and the box's nodes r = t % stride, r + stride, ... below window_count, so
# the launch size need not be the box's. The box's own count when the host knows it (one node a
# thread); a fixed count (state.WINDOW_THREADS) when the box is found on the device inside a
# captured CUDA graph, whose launch sizes are fixed at capture.


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
