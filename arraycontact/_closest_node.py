"""Stage 3: the closest master node of every slave within d_max, through a 3x3x3 stencil.

The node grid's cells are at least d_max wide, so every node within d_max of a slave lies in
the 27 cells around the slave's cell (seed 000, eq. 11 and Fig. 5); cells whose box is farther
than d_max are skipped. Ties go to the smallest node id.
"""

from __future__ import annotations

import numpy as np

from ._grid import stencil_counts
from ._xp import expand, norm, segment_min

BIG = np.iinfo(np.int32).max


def closest_node(xp, grid, nodes_x, slave_x, *, cell, table, d_max, tie, capacity):
    """Returns (node index or -1 [n], distance or inf [n], pair count)."""
    n = slave_x.shape[0]
    reach = xp.zeros(n, slave_x.dtype) + d_max
    counts, begin = stencil_counts(xp, grid, slave_x, cell, table, reach)
    seg, rank, valid, total = expand(xp, counts.reshape(-1), capacity)
    slave = seg // 27
    node = grid[0][xp.where(valid, begin.reshape(-1)[seg] + rank, 0)]
    d = norm(xp, nodes_x[node] - slave_x[slave])
    ok = valid & (d <= d_max)
    d = xp.where(ok, d, np.inf)
    dmin = segment_min(xp, d, slave, n)
    best = segment_min(xp, xp.where(ok & (d <= dmin[slave] + tie), node, BIG), slave, n)
    return xp.where(dmin < np.inf, best, -1), dmin, total
