"""Stage 3 in Warp: the closest master node within d_max through the 3x3x3 stencil; ties
(within `tie`) go to the smallest node id, as in every back end."""

from __future__ import annotations

import warp as wp

from ._grid import Grid, cell_key, cell_of
from ._real import real, vec3

# Forward only, no loop unrolling: the 27-cell stencil unrolled would copy the whole
# projection 27 times into the kernel (minutes of CUDA compilation for no speed).
wp.set_module_options({"enable_backward": False, "max_unroll": 1})


@wp.func
def _cell_near(s: vec3, c: wp.vec3i, cell: real, reach: real):
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
def _scan(s: vec3, world: int, grid: Grid, d_max: real, limit: real):
    """Smallest distance within d_max, and the smallest node id at distance <= limit."""
    c0 = cell_of(s, grid.cell)
    dmin = real(3.0e38)
    best = int(-1)
    for q in range(27):
        c = c0 + stencil_offset(q)
        # Cells beyond the running minimum (or the tie limit) cannot change the answer.
        if _cell_near(s, c, grid.cell, wp.min(d_max, wp.max(dmin, limit))):
            key = cell_key(c, world, grid.table)
            for k in range(grid.begin[key], grid.end[key]):
                ball = grid.balls[k]
                if grid.worlds[k] == world:
                    j = grid.sorted_ids[k]
                    d = wp.length(vec3(ball[0], ball[1], ball[2]) - s)
                    if d <= d_max:
                        dmin = wp.min(dmin, d)
                        if d <= limit and (best < 0 or j < best):
                            best = j
    return dmin, best


@wp.func
def closest_node(s: vec3, world: int, grid: Grid, d_max: real, tie: real):
    """(node id or -1, distance or 3e38)."""
    dmin, unused = _scan(s, world, grid, d_max, real(-1.0))
    best = int(-1)
    if dmin <= d_max:
        d2, best = _scan(s, world, grid, d_max, dmin + tie)
    return best, dmin


__all__ = ["closest_node"]
