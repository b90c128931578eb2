"""Stage 2: a size-adaptive search structure built by one sort and segment reductions.

Why not a uniform grid: one cell size must hold the largest face, so on a graded mesh (faces
1000x smaller at the contact than far from it) one cell holds thousands of small faces and
every slave near them scans them all: the cost grows with the size ratio, not the answer.

The structure (the same in every back end): items (master nodes as points, or faces as boxes)
sorted by the Morton code of their centres (21 bits an axis over the scene's box), then a tree
of fixed fan-out W over that order: entry j of level k is the box around entries W j ... W j +
W - 1 of level k - 1 (level 0: the items). Morton order makes every run of consecutive items a
compact cluster whatever the items' sizes, so the boxes adapt to the local face size by
themselves; the levels are segment reductions (reshapes: the segments have a fixed length)
and need no pointers. (The Warp back end, arraycontact_warp._grid, groups tighter: a group is
the largest node of the keys' radix tree holding at most W entries, padded to W slots, so no
group straddles two Morton cells where the order jumps, at the price of a pointer a slot.)
A moving master keeps the order and recomputes the boxes (a refit): the tree stays exact, only
less tight, until the order is computed again.

Each entry also keeps a representative point: a point of the surface inside it (the first
item's first node). The distance to it bounds the answer from above, so a query starts with
reach min(d_max, ...) and shrinks it as it descends ("a shrinking radius": DESIGN section 10).

Query (NumPy), level by level from the root: every (slave, entry) pair within reach is expanded
into its W children; a child survives when its box is within the slave's reach, and the reach
shrinks to the smallest representative distance seen (plus the rounding and tie slack). Cost
model, per slave: the entries within reach at each of the log_W(n) levels, times W. The reach
is at most the distance to a surface point the slave's own neighbourhood holds, so at every
level only the entries near the slave survive: a few near the root (boxes there are large but
few) and, near the leaves, the entries whose size is the local face size, which is what a
uniform grid of the local size would visit. It depends on the face sizes near the slave and on
how many faces are within the distance of its answer, not on the ratio of the largest to the
smallest face; a slave with nothing within d_max stops at the first level whose boxes are all
farther. Memory is the surviving pairs of one level at a time (bounded per slave by the same
count; the NumPy back end runs the slaves in chunks). The JAX back end walks the same trees
depth first, one fixed-size state a slave (arraycontact_jax._grid), and the Warp kernels
likewise.

Self-contact (detect_self): every entry also holds a box around the unit normals of the items
under it (_surface.normal_boxes), and a query carries the slave's pseudo-normal; an entry
whose normals all make n_i . n >= 0 holds nothing that faces the slave and is skipped (the
slave's own sheet around it, in general). Representatives bound nothing there (the nearest
surface point may lie on a face that does not count): the face search starts from the
nearest face that counts around the closest obtuse node (NumPy, JAX: _detect.self_reach) or
from d_max, shrinking as faces that count are found (Warp). The cost per slave is then the
entries within that reach whose normals may face it; an entry holding both sides of a sheet
thinner than itself faces every way, and only its items are told apart.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from ._surface import min_dot
from ._xp import compact, segment_min

#: Fan-out: children per entry (8 boxes of 32 bytes are two cache lines on a GPU).
W = 8
#: Morton bits per axis (63-bit keys).
BITS = 21


class Tree(NamedTuple):
    """ids [n]: item ids in Morton order; lo, hi, rep: one array per level (level 0 the items
    in that order, the last level a single root), [size_k, 3] each. An entry with no item has
    lo > hi (an empty box no query reaches)."""

    ids: object
    lo: tuple
    hi: tuple
    rep: tuple
    # Self-contact: per level, a box holding the unit normals of the items under each entry
    # (_surface.normal_boxes), so a scan skips entries that nowhere face the query's normal.
    nlo: tuple = ()
    nhi: tuple = ()


def level_sizes(n: int) -> tuple:
    """Entries per level for n items: (n, ceil(n / W), ..., 1) (at least one entry)."""
    sizes = [max(n, 1)]
    while sizes[-1] > 1:
        sizes.append(-(-sizes[-1] // W))
    if len(sizes) == 1:
        sizes.append(1)  # a root above a single item: queries always expand at least once
    return tuple(sizes)


def _spread(v):
    """The low 21 bits of int64 v moved to every third bit (Morton interleaving)."""
    v = v & 0x1FFFFF
    v = (v | (v << 32)) & 0x1F00000000FFFF
    v = (v | (v << 16)) & 0x1F0000FF0000FF
    v = (v | (v << 8)) & 0x100F00F00F00F00F
    v = (v | (v << 4)) & 0x10C30C30C30C30C3
    v = (v | (v << 2)) & 0x1249249249249249
    return v


def morton_order(x: np.ndarray, lo: np.ndarray, extent: float) -> np.ndarray:
    """Rows of x [n, 3] in Morton order of 2^21 cells an axis over the cube [lo, lo + extent]
    (host, float64, stable: equal codes keep their row order)."""
    scale = (1 << BITS) / max(float(extent), np.finfo(float).tiny)
    c = np.clip(np.floor((np.asarray(x, float) - lo) * scale), 0, (1 << BITS) - 1)
    c = c.astype(np.int64)
    key = _spread(c[:, 0]) | (_spread(c[:, 1]) << 1) | (_spread(c[:, 2]) << 2)
    return np.argsort(key, kind="stable")


def _empty(dtype):
    # Large enough never to be within reach, small enough that a square stays finite
    # in differences.
    return float(np.finfo(dtype).max) ** 0.25


def build(xp, ids, lo, hi, rep, normals=None) -> Tree:
    """The tree over items already in Morton order: ids [n], boxes lo, hi [n, 3], points of
    the surface inside them rep [n, 3]; normals (self-contact): the items' normal boxes
    (nlo, nhi) [n, 3] each."""
    n = lo.shape[0]
    sizes = level_sizes(n)
    big = _empty(lo.dtype)
    if n == 0:
        lo = xp.full((1, 3), big, lo.dtype)
        hi, rep = -lo, xp.zeros((1, 3), lo.dtype)
    los, his, reps = [lo], [hi], [rep]
    for size in sizes[1:]:
        pad = size * W - los[-1].shape[0]
        lo_k = xp.concatenate([los[-1], xp.full((pad, 3), big, lo.dtype)])
        hi_k = xp.concatenate([his[-1], xp.full((pad, 3), -big, lo.dtype)])
        los.append(xp.min(lo_k.reshape(size, W, 3), 1))
        his.append(xp.max(hi_k.reshape(size, W, 3), 1))
        reps.append(reps[-1][::W])  # the first child's point: a point of the surface
    if normals is None:
        return Tree(ids, tuple(los), tuple(his), tuple(reps))
    nlos, nhis = [normals[0]], [normals[1]]
    if n == 0:
        nlos, nhis = [xp.ones((1, 3), lo.dtype)], [-xp.ones((1, 3), lo.dtype)]
    for size in sizes[1:]:
        pad = size * W - nlos[-1].shape[0]
        # Padding: lo = 1, hi = -1, neutral in the minimum and maximum.
        nlo_k = xp.concatenate([nlos[-1], xp.ones((pad, 3), lo.dtype)])
        nhi_k = xp.concatenate([nhis[-1], -xp.ones((pad, 3), lo.dtype)])
        nlos.append(xp.min(nlo_k.reshape(size, W, 3), 1))
        nhis.append(xp.max(nhi_k.reshape(size, W, 3), 1))
    return Tree(ids, tuple(los), tuple(his), tuple(reps), tuple(nlos), tuple(nhis))


#: Self-contact's rule (_detect.detect_self): faces count when n_i . n_f < -FACING_TOL, nodes
#: when n_i . n_j <= FACING_TOL (unit normals).
FACING_TOL = 1e-6
#: Self-contact skips an entry when every normal in its box has n_i . n >= FACING_MARGIN
#: (above zero against rounding in the boxes; the exact test is made on each candidate).
FACING_MARGIN = 1e-4


def facing(normal, nlo, nhi):
    """Whether some normal in the boxes [nlo, nhi] may face `normal` (n . v < 0)."""
    return min_dot(normal, nlo, nhi) < FACING_MARGIN


def query(xp, tree: Tree, q, reach, slack, capacity=None, name="level", normal=None, shrink=True):
    """The items whose box is within reach of each query point, reach shrunk on the way to the
    smallest representative distance + slack (items farther than some point of the surface
    cannot hold the closest point, nor be within the tie band of it).

    q [n, 3], reach [n]. capacity: None (eager, exact sizes) or a dict of static sizes per
    level (keys f"{name}{k}"). normal [n, 3] (self-contact, a tree with normal boxes): only
    entries that may face the query's normal, and no shrinking (a representative may lie on
    a face that does not count). shrink=False: every item whose box is within reach (swept
    detection's capture boxes, whose representatives bound nothing). Returns (query row [P],
    item position in tree order [P], valid [P], counts {key: true count}); pairs are grouped
    by query row in increasing order."""
    n = q.shape[0]
    top = len(tree.lo) - 1
    slave = xp.arange(n, dtype=np.int32)
    entry = xp.zeros(n, dtype=np.int32)
    valid = xp.ones(n, dtype=bool)
    reach = reach + 0 * q[:, 0]
    counts = {}
    for k in range(top, 0, -1):
        size = tree.lo[k - 1].shape[0]
        child = (entry[:, None] * W + xp.arange(W, dtype=np.int32)[None, :]).reshape(-1)
        s = xp.broadcast_to(slave[:, None], (slave.shape[0], W)).reshape(-1)
        ok = xp.broadcast_to(valid[:, None], (slave.shape[0], W)).reshape(-1) & (child < size)
        c = xp.where(ok, child, 0)
        lo, hi = tree.lo[k - 1][c], tree.hi[k - 1][c]
        qs = q[s]
        g = xp.maximum(xp.maximum(lo - qs, qs - hi), 0)
        gap2 = xp.sum(g * g, -1)
        filled = ok & xp.all(lo <= hi, -1)
        if normal is None and shrink:
            d = tree.rep[k - 1][c] - qs
            ub = xp.where(filled, xp.sqrt(xp.sum(d * d, -1)), np.inf)
            reach = xp.minimum(reach, segment_min(xp, ub, s, n, sorted=True) + slack)
        elif normal is not None:
            filled = filled & facing(normal[s], tree.nlo[k - 1][c], tree.nhi[k - 1][c])
        keep = filled & (gap2 <= reach[s] ** 2)
        key = f"{name}{k - 1}"
        idx, count = compact(xp, keep, None if capacity is None else capacity[key])
        counts[key] = count
        slave, entry = s[idx], c[idx]
        valid = xp.arange(idx.shape[0]) < count
    return slave, entry, valid, counts
