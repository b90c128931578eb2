"""Stage 3: the closest master node of every slave within d_max, through the node tree
(_grid.query: every node within the shrinking reach). Ties go to the smallest node id.

Self-contact (seed 000 section 3, item 4): the closest node other than the slave itself whose
normal makes an obtuse angle with the slave's (n_i . n_j <= 0): nodes of the slave's own
sheet around it do not count.
"""

from __future__ import annotations

import numpy as np

from . import _grid
from ._grid import FACING_TOL
from ._surface import _dot
from ._xp import norm, segment_min

BIG = np.iinfo(np.int32).max


def closest_node(xp, tree, nodes_x, slave_x, *, d_max, tie, slack, capacity, self_contact=None):
    """Returns (node index or -1 [n], distance or inf [n], pair counts per tree level).
    self_contact: (the slaves' node ids [n], their normals [n, 3], every node's normal)."""
    n = slave_x.shape[0]
    reach = xp.zeros(n, slave_x.dtype) + (d_max + slack)
    normal = None if self_contact is None else self_contact[1]
    slave, pos, valid, counts = _grid.query(
        xp, tree, slave_x, reach, slack, capacity, "node_level", normal
    )
    node = tree.ids[pos]
    d = norm(xp, nodes_x[node] - slave_x[slave])
    ok = valid & (d <= d_max)
    if self_contact is not None:
        ids, normal, node_normals = self_contact
        ok = ok & (node != ids[slave]) & (_dot(normal[slave], node_normals[node]) <= FACING_TOL)
    d = xp.where(ok, d, np.inf)
    dmin = segment_min(xp, d, slave, n, sorted=True)
    best = segment_min(
        xp, xp.where(ok & (d <= dmin[slave] + tie), node, BIG), slave, n, sorted=True
    )
    return xp.where(dmin < np.inf, best, -1), dmin, counts
