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
def counts(o: Plain, normals: wp.array(dtype=vec3), grid: Grid, k: int):
    """Whether node item k counts for the slave: every node, or (Own) another node whose
    normal is at an obtuse angle to the slave's."""
    return True


@wp.func
def counts(o: Own, normals: wp.array(dtype=vec3), grid: Grid, k: int):  # noqa: F811
    i = item_id(grid, k)
    return i != o.node and wp.dot(o.normal, normals[i]) <= real(FACING_TOL)


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
    """Within d_max: the smallest distance, the second smallest (of another node), the
    smallest node id at distance <= limit (limit < 0: the id at the smallest distance) and its
    item, over the tree depth first (_grid: a visit tests an entry's W children, goes on with
    the nearest, keeps the others in `stack`), within the reach: d_max or `bound` (at least
    the smallest distance plus the tie band), cut to the running minimum plus the tie band
    (or the tie limit). shared = 1: every item is of this world (a master shared by all
    worlds). o: Plain, or Own (self-contact: only nodes other than the slave's whose normal,
    normals[id], is at an obtuse angle to the slave's count)."""
    dmin = real(3.0e38)
    second = real(3.0e38)
    best = int(-1)
    best_k = int(-1)
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
                        near = counts(o, normals, grid, kk)
                    if near:
                        d = wp.sqrt(d2)
                        if d <= d_max:
                            i = item_id(grid, kk)
                            if d < dmin:
                                second = dmin
                                dmin = d
                                if limit < real(0.0):
                                    best = i
                                    best_k = kk
                            else:
                                second = wp.min(second, d)
                            if d <= limit and (best < 0 or i < best):
                                best = i
                                best_k = kk
                            reach = wp.min(reach, wp.max(dmin + tie, limit))
                            wide = reach * real(1.0001)
            else:
                mask, near_c = children(grid, s, world, shared, k, box.first, wide, 1, o)
                if mask != 0:
                    stack, k, j = descend(stack, k, box.first, mask, near_c)
                    visit = 1
        if visit == 0:
            stack, k, j, visit = next_pending(grid, top, stack, k, j)
    return dmin, second, best, best_k


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
):
    """(node id or -1, distance or 3e38). One scan; the tie rule needs a second only when
    another node is within `tie` of the closest (a slave equidistant from two nodes).
    o, normals: self-contact's (see _scan)."""
    best, dmin, k = hinted_closest_node(s, world, shared, grid, d_max, tie, o, normals, -1)
    return best, dmin


@wp.func
def hinted_closest_node(
    s: vec3,
    world: int,
    shared: int,
    grid: Grid,
    d_max: real,
    tie: real,
    o: Any,
    normals: wp.array(dtype=vec3),
    hint: int,
):
    """closest_node, and the item of the node it gives (-1: none). hint: an item of the tree
    (a detection's last answer for this slave) or -1. Where it holds a node that counts for
    this slave, that node's distance bounds the closest one's, and the scan starts from it
    plus the tie band instead of d_max: the entries beyond it are never marked to visit (a
    refit keeps the items in their slots; after a build the slot holds another node, whose
    distance bounds as well). CPU, 2^16, steady detections: the closest-node scan's thread
    time 12.4 -> 10.9 ms (uniform), 20.4 -> 15.0 (graded_1000), 19.3 -> 13.2 (d_max 10x)."""
    bound = real(3.0e38)
    if hint >= 0:
        ok = item_id(grid, hint) >= 0
        if ok and shared == 0:
            ok = item_world(grid, hint) == world
        if ok:
            ok = counts(o, normals, grid, hint)
        if ok:
            bound = wp.sqrt(wp.length_sq(item_lo(grid, hint) - s)) + tie
    dmin, second, best, k = _scan(s, world, shared, grid, d_max, tie, real(-1.0), bound, o, normals)
    if dmin <= d_max and second <= dmin + tie:
        band = dmin + tie
        d2, s2, best, k = _scan(s, world, shared, grid, d_max, tie, band, band, o, normals)
    return best, dmin, k


__all__ = ["closest_node", "hinted_closest_node"]
