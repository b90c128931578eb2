"""Stage 3 in Warp: the closest master node within d_max through the 3x3x3 stencil; ties
(within `tie`) go to the smallest node id, as in every back end."""

from __future__ import annotations

import warp as wp

from ._grid import Grid, box_near, cell_key, cell_of, item_lo, read_slot
from ._real import real, vec3

# Forward only, no loop unrolling: the 27-cell stencil unrolled would copy the whole
# projection 27 times into the kernel (minutes of CUDA compilation for no speed).
wp.set_module_options({"enable_backward": False, "max_unroll": 1})


@wp.func
def _cell_near(s: vec3, c: wp.vec3i, cell: real, reach: real):
    """Whether cell c is within reach of s. (Three nested loops over the stencil, skipping a
    row or layer out of reach whole, ran slower: 2.3 against 1.8 ms at 2^20 on an H100.)"""
    lo = vec3(real(c[0]), real(c[1]), real(c[2])) * cell
    g = vec3(0.0)
    for k in range(3):
        g[k] = wp.max(wp.max(lo[k] - s[k], s[k] - (lo[k] + cell)), real(0.0))
    return wp.length_sq(g) <= reach * reach


@wp.func
def stencil_offset(q: int):
    """The q-th of the 27 stencil cells, the slave's own cell first: searching it first makes
    the running minimum small early, which prunes the other cells and candidates."""
    j = q - 1
    if q == 0:
        j = 13
    elif q <= 13:
        j = q - 1
    else:
        j = q
    return wp.vec3i(j % 3 - 1, (j // 3) % 3 - 1, j // 9 - 1)


@wp.func
def _scan(s: vec3, world: int, shared: int, grid: Grid, d_max: real, tie: real, limit: real):
    """Within d_max: the smallest distance, the second smallest (of another node) and the
    smallest node id at distance <= limit (limit < 0: the id at the smallest distance).
    shared = 1: every item is of this world (a master shared by all worlds)."""
    c0 = cell_of(s, grid.cell)
    dmin = real(3.0e38)
    second = real(3.0e38)
    best = int(-1)
    # Cells beyond the running minimum plus the tie band (or the tie limit) cannot change the
    # answer; nor can a slot whose items' box is that far.
    reach = wp.min(d_max, wp.max(dmin + tie, limit))
    for q in range(27):
        c = c0 + stencil_offset(q)
        # A node may have moved grid.margin from the cell it was keyed in (a refit).
        if _cell_near(s, c, grid.cell, reach + grid.margin):
            slot = read_slot(grid, cell_key(c, world, grid.table))
            wide = reach * real(1.0001)
            if box_near(s, slot, wide):
                for k in range(slot.begin, slot.end):
                    # Squares first: most nodes are out of reach, need no root.
                    d2 = wp.length_sq(item_lo(grid, k) - s)
                    near = d2 <= wide * wide
                    if near and shared == 0:  # (Warp evaluates both sides of `or`)
                        near = grid.items[k].world == world
                    if near:
                        d = wp.sqrt(d2)
                        if d <= d_max:
                            j = grid.sorted_ids[k]
                            if d < dmin:
                                second = dmin
                                dmin = d
                                if limit < real(0.0):
                                    best = j
                            else:
                                second = wp.min(second, d)
                            if d <= limit and (best < 0 or j < best):
                                best = j
                            reach = wp.min(d_max, wp.max(dmin + tie, limit))
                            wide = reach * real(1.0001)
    return dmin, second, best


@wp.func
def closest_node(s: vec3, world: int, shared: int, grid: Grid, d_max: real, tie: real):
    """(node id or -1, distance or 3e38). One scan; the tie rule needs a second only when
    another node is within `tie` of the closest (a slave equidistant from two nodes)."""
    dmin, second, best = _scan(s, world, shared, grid, d_max, tie, real(-1.0))
    if dmin <= d_max and second <= dmin + tie:
        d2, s2, best = _scan(s, world, shared, grid, d_max, tie, dmin + tie)
    return best, dmin


__all__ = ["closest_node"]
