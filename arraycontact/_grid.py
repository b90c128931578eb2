"""Stage 2: a uniform grid by sorting (seed 000 eqs. 6-10, without a dense cell array).

Cell coordinates are `floor(x / cell)` in the local frame (floor, not truncation, so negative
coordinates work). Each cell is hashed to one integer key in a table of T = 2^k slots, items are
stably sorted by key, and the start of every slot comes from `searchsorted` on the sorted keys.
The table has about two slots per item whatever the extent of the scene: two small patches
10^6 box widths apart cost what two adjacent patches cost. Two cells that share a slot only add
candidates, which the exact distance tests downstream discard.
"""

from __future__ import annotations

import numpy as np

# Large odd multipliers (Teschner et al. 2003), in int32 wrap-around arithmetic on every back end.
_P = (73856093, 19349663, 83492791)
STENCIL = np.array([(i, j, k) for k in (-1, 0, 1) for j in (-1, 0, 1) for i in (-1, 0, 1)],
                   np.int32)


def table_size(n_items):
    return int(max(64, 1 << int(np.ceil(np.log2(max(2 * n_items, 1))))))


def cell_coords(xp, x, cell):
    # int64 where the float is float64: a global float64 frame may be far from the origin.
    return xp.floor(x / cell).astype(np.int64 if x.dtype == np.float64 else np.int32)


def cell_key(xp, c, table):
    h = (c[..., 0] * _P[0]) ^ (c[..., 1] * _P[1]) ^ (c[..., 2] * _P[2])
    return (h & (table - 1)).astype(np.int32)


def build(xp, x, cell, table):
    """Sort items at x [n, 3] into cells: (order [n], starts [table + 1])."""
    keys = cell_key(xp, cell_coords(xp, x, cell), table)
    order = xp.argsort(keys, stable=True)
    starts = xp.searchsorted(keys[order], xp.arange(table + 1), side="left")
    return order.astype(np.int32), starts.astype(np.int32)


def stencil_counts(xp, grid, q, cell, table, reach):
    """Items per stencil cell for queries q [n, 3]: ([n, 27] counts, [n, 27] slot starts).

    A cell whose box is farther than `reach` [n] from the query contributes no item."""
    order, starts = grid
    c = cell_coords(xp, q, cell)[:, None, :] + xp.asarray(STENCIL)  # [n, 27, 3]
    lo = c.astype(q.dtype) * cell
    gap = xp.maximum(xp.maximum(lo - q[:, None], q[:, None] - (lo + cell)), 0)
    near = xp.sum(gap * gap, -1) <= (reach * reach)[:, None]
    key = cell_key(xp, c, table)
    begin = starts[key]
    return xp.where(near, starts[key + 1] - begin, 0), begin
