"""Stage 3 in Warp: the closest master node within d_max through the node tree; ties (within
`tie`) go to the smallest node id, as in every back end."""

from __future__ import annotations

from typing import Any

import warp as wp

from ._grid import (
    Grid,
    Own,
    Plain,
    W,
    children,
    descend,
    enters,
    entry,
    item_id,
    item_lo,
    item_world,
    next_pending,
)
from ._real import real, vec3

# Forward only, no loop unrolling (a scan's loops unrolled copy their body many times).
wp.set_module_options({"enable_backward": False, "max_unroll": 1})


#: arraycontact._grid.FACING_TOL: self-contact counts nodes with n_i . n_j <= this.
FACING_TOL = 1.0e-6


@wp.func
def counts(o: Plain, normals: wp.array(dtype=vec3), node: int):
    """Whether the node counts for the slave: every node, or (Own) another node whose normal
    is at an obtuse angle to the slave's."""
    return True


@wp.func
def counts(o: Own, normals: wp.array(dtype=vec3), node: int):  # noqa: F811
    return node != o.node and wp.dot(o.normal, normals[node]) <= real(FACING_TOL)


@wp.func
def _scan(
    s: vec3,
    world: int,
    shared: int,
    grid: Grid,
    d_max: real,
    tie: real,
    limit: real,
    bound: real,
    o: Any,
    normals: wp.array(dtype=vec3),
):
    """Within d_max: the smallest distance, the second smallest (of another node) and the
    smallest node id at distance <= limit (limit < 0: the id at the smallest distance), over
    the tree depth first (_grid: a visit tests an entry's W children, goes on with
    the nearest, keeps the others in `stack`), within the reach: d_max or `bound` (at least
    the smallest distance plus the tie band), cut to the running minimum plus the tie band
    (or the tie limit). shared = 1: every item is of this world (a master shared by all
    worlds). o: Plain, or Own (self-contact: only nodes other than the slave's whose normal,
    normals[id], is at an obtuse angle to the slave's count)."""
    dmin = real(3.0e38)
    second = real(3.0e38)
    best = int(-1)
    reach = wp.min(d_max, wp.max(bound, limit))
    wide = reach * real(1.0001)
    stack = wp.uint64(0)  # level k's W bits: its children still to visit
    top = grid.root[0]
    k = top
    j = int(0)
    visit = int(1)
    while visit == 1:
        visit = 0
        box = entry(grid, k, j)
        if enters(s, world, shared, box, wide):
            if k == 1:
                for t in range(W):
                    kk = box.first + t  # (an empty slot is out of every reach)
                    # Squares first: most nodes are out of reach, need no root.
                    d2 = wp.length_sq(item_lo(grid, kk) - s)
                    near = d2 <= wide * wide
                    if near and shared == 0:  # (Warp evaluates both sides of `or`)
                        near = item_world(grid, kk) == world
                    if near:
                        near = counts(o, normals, item_id(grid, kk))
                    if near:
                        d = wp.sqrt(d2)
                        if d <= d_max:
                            i = item_id(grid, kk)
                            if d < dmin:
                                second = dmin
                                dmin = d
                                if limit < real(0.0):
                                    best = i
                            else:
                                second = wp.min(second, d)
                            if d <= limit and (best < 0 or i < best):
                                best = i
                            reach = wp.min(reach, wp.max(dmin + tie, limit))
                            wide = reach * real(1.0001)
            else:
                mask, near_c = children(grid, s, world, shared, k, box.first, wide, 1, o)
                if mask != 0:
                    stack, k, j = descend(stack, k, box.first, mask, near_c)
                    visit = 1
        if visit == 0:
            stack, k, j, visit = next_pending(grid, top, stack, k, j)
    return dmin, second, best


@wp.func
def closest_node(
    s: vec3,
    world: int,
    shared: int,
    grid: Grid,
    d_max: real,
    tie: real,
    o: Any,
    normals: wp.array(dtype=vec3),
    bound: real,
):
    """(node id or -1, distance or 3e38), the scan starting from `bound` (the distance to a
    node that counts for the slave, plus the tie band; 3e38: none) where it is below d_max:
    the entries beyond it are never marked to visit. One scan; the tie rule needs a second
    only when another node is within `tie` of the closest (a slave equidistant from two
    nodes). o, normals: self-contact's (see _scan)."""
    dmin, second, best = _scan(s, world, shared, grid, d_max, tie, real(-1.0), bound, o, normals)
    if dmin <= d_max and second <= dmin + tie:
        band = dmin + tie
        d2, s2, best = _scan(s, world, shared, grid, d_max, tie, band, band, o, normals)
    return best, dmin


__all__ = ["closest_node", "counts"]
