"""Stage 2: a size-adaptive search structure built by one sort and segment reductions.

Why not a uniform grid: one cell size must hold the largest face, so on a graded mesh (faces
1000x smaller at the contact than far from it) one cell holds thousands of small faces and
every slave near them scans them all: the cost grows with the size ratio, not the answer.

The structure (the same in every back end): items (master nodes as points, or faces as boxes)
sorted by the Morton code of their centres (21 bits an axis over the scene's box), then a tree
of fan-out W over that order: level k holds its entries in groups of W slots (empty slots:
lo > hi), each group an entry of level k + 1 whose box is the box of the group. A group is the
largest node of the keys' binary radix tree holding at most W entries (`grouping`), so every
group is a compact Morton cluster whatever the items' sizes and the boxes adapt to the local
face size by themselves; W consecutive entries a group would straddle two Morton cells
wherever the order jumps (a stretched zone's rows, a fine patch and the coarse plate after
it). The grouping is computed on the host when the items are sorted (a plan's), the levels by
a gather into the slots and a reduction over each group of W (reshapes); a slot's `down`
gives its children's group. The Warp back end (arraycontact_warp._grid) groups by the same
rule on the device. Sharded and swept JAX plans keep W consecutive entries a group
(`consecutive`).
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
    """One array per level (level 0 the item slots, the last level a single root), in slots:
    the entries of level k in groups of W slots (`group` below), an empty slot with lo > hi.

    ids [S_0]: the item id in each item slot (-1: empty); lo, hi, rep: [S_k, 3] per level;
    down: per level k >= 1, [S_k] the group of level k - 1 under each slot (its children are
    that level's slots W down .. W down + W - 1; -1: an empty slot; down[0] is unused)."""

    ids: object
    lo: tuple
    hi: tuple
    rep: tuple
    down: tuple
    # Self-contact: per level, a box holding the unit normals of the items under each entry
    # (_surface.normal_boxes), so a scan skips entries that nowhere face the query's normal.
    nlo: tuple = ()
    nhi: tuple = ()


def _spread(v):
    """The low 21 bits of int64 v moved to every third bit (Morton interleaving)."""
    v = v & 0x1FFFFF
    v = (v | (v << 32)) & 0x1F00000000FFFF
    v = (v | (v << 16)) & 0x1F0000FF0000FF
    v = (v | (v << 8)) & 0x100F00F00F00F00F
    v = (v | (v << 4)) & 0x10C30C30C30C30C3
    v = (v | (v << 2)) & 0x1249249249249249
    return v


def morton_keys(x: np.ndarray, lo: np.ndarray, extent: float) -> np.ndarray:
    """The 63-bit Morton keys [n] of the rows of x [n, 3] over 2^21 cells an axis of the cube
    [lo, lo + extent] (host, float64)."""
    scale = (1 << BITS) / max(float(extent), np.finfo(float).tiny)
    c = np.clip(np.floor((np.asarray(x, float) - lo) * scale), 0, (1 << BITS) - 1)
    c = c.astype(np.int64)
    return _spread(c[:, 0]) | (_spread(c[:, 1]) << 1) | (_spread(c[:, 2]) << 2)


def morton_order(x: np.ndarray, lo: np.ndarray, extent: float) -> np.ndarray:
    """Rows of x [n, 3] in the order of their morton_keys (stable: equal keys keep their row
    order)."""
    return np.argsort(morton_keys(x, lo, extent), kind="stable")


def _bit_length(x):
    """The bit length of each non-negative int64 of x (through float64, exact below 2^53:
    above, a rounding up could add one, so those go by their high 32 bits)."""
    out = np.frexp(x.astype(np.float64))[1]
    big = x >= 1 << 53
    if big.any():
        out[big] = 32 + np.frexp((x[big] >> 32).astype(np.float64))[1]
    return out


def grouping(keys) -> tuple:
    """The slots of every level of the tree over items whose keys [n] are sorted (the
    arraycontact_warp._grid rule, computed on the host): per level k below the root, [S_k]
    the entry of level k in each slot (-1: empty), S_k = W x its groups. A group is the
    largest node of the keys' binary radix tree (equal keys told apart by their positions)
    that holds at most W entries; a group of level k is an entry of level k + 1, and the
    splits between level k + 1's entries are those between the groups. A level whose groups
    would hold fewer than 2 entries on average takes W consecutive entries a group instead
    (slots stay within 4x the entries), and a level of at most W^2 entries in more than W
    groups merges neighbouring groups where that makes the next level the root's (`_top`;
    the Warp back end's device grouping does not). Why not W consecutive items a group
    everywhere: where the Morton order jumps (between the halves of a cell) such a group
    straddles both and its box spans the two, and so do its ancestors."""
    keys = np.asarray(keys, np.int64)
    n = len(keys)
    if n <= 1:
        return (np.array([0] * n + [-1] * (W - n), np.int32),)
    # The radix tree's depth at each pair of neighbours: the leading bits they share.
    x = keys[:-1] ^ keys[1:]
    split = 64 - _bit_length(x)
    same = np.flatnonzero(x == 0)
    split[same] = 96 - _bit_length(same ^ (same + 1))
    out = []
    while True:
        m = len(split) + 1
        end = np.r_[_ends(split), True]
        start = np.r_[0, np.flatnonzero(end[:-1]) + 1]
        if m / len(start) < 2:  # W consecutive entries a group
            end = (np.arange(m) % W == W - 1) | (np.arange(m) == m - 1)
            start = np.arange(0, m, W)
        elif W < len(start) and m <= W * W:
            start, end = _top(start, end, m)
        group = np.cumsum(end) - end
        slots = np.full(W * len(start), -1, np.int32)
        slots[W * group + np.arange(m) - start[group]] = np.arange(m)
        out.append(slots)
        if len(start) == 1:
            return tuple(out)
        split = split[np.flatnonzero(end[:-1])]


def _top(start, end, m):
    """The groups (start, end) of a level of at most W^2 entries in more than W groups,
    neighbouring groups merged (next fit: each as full as whole groups allow) where that
    leaves at most W, so the level above is the root's: a level fewer where the groups end
    just past W (a sharded part's node tree at 2^21: 54 entries in 9 groups, so 2 entries
    under the root, a scan step more a slave). Otherwise as they were."""
    size = np.diff(np.r_[start, m])
    keep, fill = [0], 0
    for i, c in enumerate(size):
        if fill + c > W:
            keep.append(i)
            fill = 0
        fill += c
    if len(keep) > W:
        return start, end
    start = start[keep]
    end = np.zeros(m, bool)
    end[np.r_[start[1:] - 1, m - 1]] = True
    return start, end


def _ends(split):
    """Whether each pair of neighbours ends a group: the radix tree's node split there (the
    run of pairs around it that split no higher) holds more than W entries."""
    d = len(split)
    padded = np.r_[np.full(W, -1), split, np.full(W, -1)]  # (splits are >= 0)
    left, right = np.zeros(d, np.int8), np.zeros(d, np.int8)
    go_left, go_right = np.ones(d, bool), np.ones(d, bool)
    for t in range(1, W):
        go_left &= padded[W - t : W - t + d] >= split
        go_right &= padded[W + t : W + t + d] >= split
        left += go_left
        right += go_right
    return left + right + 2 > W


def consecutive(n: int) -> tuple:
    """`grouping`'s shape with W consecutive entries a group at every level."""
    out, m = [], n
    while True:
        g = max(-(-m // W), 1)
        slots = np.full(W * g, -1, np.int32)
        slots[:m] = np.arange(m)
        out.append(slots)
        if g == 1:
            return tuple(out)
        m = g


def _empty(dtype):
    # Large enough never to be within reach, small enough that a square stays finite
    # in differences.
    return float(np.finfo(dtype).max) ** 0.25


def build(xp, ids, lo, hi, rep, normals=None, groups=None) -> Tree:
    """The tree over items in key order: ids [n], boxes lo, hi [n, 3], points of the surface
    inside them rep [n, 3]; normals (self-contact): the items' normal boxes (nlo, nhi) [n, 3]
    each; groups: the slots of `grouping` for the items' keys (host arrays), or None: W
    consecutive items a group. Each level is a gather into the slots and a reduction over
    each group of W."""
    n = lo.shape[0]
    groups = consecutive(n) if groups is None else groups
    big = _empty(lo.dtype)

    def levels(values, fills, reduce):
        """Per kind of `values` (each [n, 3], the items), its slots at every level."""
        out = []
        for k, slots in enumerate(groups):
            if k:  # the entries of level k: the groups of level k - 1
                values = [r(v.reshape(-1, W, 3)) for r, v in zip(reduce, out[-1])]
            elif not n:  # (something to gather from)
                values = [xp.zeros((1, 3), lo.dtype) for _ in values]
            s = xp.asarray(slots)
            out.append([xp.where((s >= 0)[:, None], v[xp.maximum(s, 0)], f)
                        for v, f in zip(values, fills)])  # fmt: skip
        out.append([r(v.reshape(-1, W, 3)) for r, v in zip(reduce, out[-1])])  # the root
        return [tuple(level[i] for level in out) for i in range(len(fills))]

    def lo_min(v):
        return xp.min(v, 1)

    def hi_max(v):
        return xp.max(v, 1)

    def first(v):  # a group's first slot holds an entry: its point is a point of the surface
        return v[:, 0]

    los, his, reps = levels([lo, hi, rep], [big, -big, 0.0], [lo_min, hi_max, first])
    s0 = xp.asarray(groups[0])
    slot_ids = xp.where(s0 >= 0, xp.asarray(ids)[xp.maximum(s0, 0)] if n else -1, -1)
    down = (None,) + tuple(xp.asarray(s) for s in groups[1:]) + (xp.zeros(1, np.int32),)
    if normals is None:
        return Tree(slot_ids, los, his, reps, down)
    # Empty slots: lo = 1, hi = -1, neutral in the minimum and maximum.
    nlos, nhis = levels(list(normals), [1.0, -1.0], [lo_min, hi_max])
    return Tree(slot_ids, los, his, reps, down, nlos, nhis)


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
        first = W * xp.maximum(tree.down[k][entry], 0)
        child = (first[:, None] + xp.arange(W, dtype=np.int32)[None, :]).reshape(-1)
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
