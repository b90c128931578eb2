"""Stage 3: the closest master node of every slave within d_max, through the node tree
(_grid.query: every node within the shrinking reach). Ties go to the smallest node id.
"""

from __future__ import annotations

import numpy as np

from . import _grid
from ._xp import norm, segment_min

BIG = np.iinfo(np.int32).max


def closest_node(xp, tree, nodes_x, slave_x, *, d_max, tie, slack, capacity):
    """Returns (node index or -1 [n], distance or inf [n], pair counts per tree level)."""
    n = slave_x.shape[0]
    reach = xp.zeros(n, slave_x.dtype) + (d_max + slack)
    slave, pos, valid, counts = _grid.query(xp, tree, slave_x, reach, slack, capacity, "node_level")
    node = tree.ids[pos]
    d = norm(xp, nodes_x[node] - slave_x[slave])
    ok = valid & (d <= d_max)
    d = xp.where(ok, d, np.inf)
    dmin = segment_min(xp, d, slave, n, sorted=True)
    best = segment_min(
        xp, xp.where(ok & (d <= dmin[slave] + tie), node, BIG), slave, n, sorted=True
    )
    return xp.where(dmin < np.inf, best, -1), dmin, counts
