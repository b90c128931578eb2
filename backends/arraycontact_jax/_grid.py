"""Stages 3-4 in JAX: per-slave depth-first scans of the trees of arraycontact._grid (read its
docstring for the structure), all slaves in lockstep in one `lax.while_loop`.

Why not the level-by-level query of the NumPy back end: under `jit` each level's surviving
(slave, entry) pairs need a static capacity, planned on the host by running the query there
(seconds at 2^20), and each level is a compaction (a cumulative sum and a scatter over every
pair). Here each slave keeps a fixed-size state, as the Warp kernels' threads do: the entry
it visits, the pending children of each level as a W-bit mask (the whole stack), its reach,
and what it found. One step visits one entry per slave: it tests the entry's W children at
once (one gather of W boxes), shrinks the reach with their representative points, and goes
on with the nearest child, or else with the next pending entry of the deepest level that has
one. Pending entries are tested again when their turn comes, against the reach as it is then.
A slave that has nothing left idles until the last one is done: the loop runs as many steps
as the busiest slave needs (a few tens: the entries within its reach).

On a GPU the scans run as one Pallas kernel instead (`_kernel_scan`, below: each block of 32
slaves steps on its own, its state in registers), with the same answers and counts; the
while_loop runs elsewhere (the CPU) and for self-contact.

Memory: O(n) state plus, for the face scan, K candidate slots a slave (K planned from a
device-side count, reported as the capacity "face_candidates"); on triangles each slot also
holds its distance (`candidate_distances`: the tie rule then picks a slot from them and only
that face is projected). The closest-node scan stores
nothing: a first scan finds the smallest distance, a second (with a reach of that distance plus
the tie band) the smallest node id within the band.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from arraycontact._geometry import triangle_distance
from arraycontact._grid import FACING_MARGIN, FACING_TOL, Tree, W

BIG = np.iinfo(np.int32).max
# The index of the lowest set bit of a W-bit mask (0 for an empty mask, never read).
_LOWEST_BIT = np.array([(m & -m).bit_length() - 1 if m else 0 for m in range(1 << W)], np.int32)


class Flat(NamedTuple):
    """A tree's levels 0 .. top-1 as rows of W slots (a group of level k, [9, W]: box lo x, y,
    z, box hi x, y, z, representative point x, y, z; self-contact: [15, W], then the normal
    box's lo and hi), the levels one after the other from level 0, and per slot of a level
    k >= 1 the row of its children (`down`). One gather of 9 W contiguous values a step, and
    the arithmetic on [n, W] planes: as [W, 9] rows with reductions over the axis of 3, a
    step took 4x longer on the CPU."""

    groups: jax.Array  # [rows, 9 or 15, W]
    down: jax.Array  # [rows, W] (level 0's rows: 0)
    root: int  # the row of the root's children
    top: int


def flatten(tree: Tree) -> Flat:
    # Built first: left to XLA, the layout below was fused with the tree's reductions into
    # one loop that took 2.4 ms at 2^20 (H100) where the Pallas scan reads it whole.
    arrays = jax.lax.optimization_barrier((tree.lo, tree.hi, tree.rep, tree.nlo, tree.nhi))
    tree = tree._replace(**dict(zip(("lo", "hi", "rep", "nlo", "nhi"), arrays)))
    top = len(tree.lo) - 1
    rows, downs, offset = [], [], [0]
    for k in range(top):
        parts = [tree.lo[k], tree.hi[k], tree.rep[k]]
        if tree.nlo:
            parts += [tree.nlo[k], tree.nhi[k]]
        lv = jnp.concatenate(parts, -1)
        rows.append(jnp.swapaxes(lv.reshape(-1, W, lv.shape[-1]), 1, 2))
        down = jnp.zeros(lv.shape[0], jnp.int32)
        if k:
            down = offset[k - 1] + jnp.maximum(jnp.asarray(tree.down[k]), 0).astype(jnp.int32)
        downs.append(down.reshape(-1, W))
        offset.append(offset[-1] + rows[-1].shape[0])
    return Flat(jnp.concatenate(rows), jnp.concatenate(downs), offset[top - 1], top)


#: The scans go on with the busy slaves alone, gathered into 1/SHRINK of the lanes, once no
#: more than that many are busy (and they are MIN_LANES or more): the last steps of the
#: busiest slaves then cost what they touch, not a step of every slave.
SHRINK = 8
MIN_LANES = 4096


def scan(
    flat: Flat, q, reach, slack, visit, carry, active=None, normal=None, shrink=True, extra=()
):
    """Depth-first scans of `flat` from the root, one per query point q [n, 3], with reach [n].

    At each step every busy slave tests the W children of its entry; the reach becomes
    min(reach, nearest representative + slack) (self-contact, `normal` [n, 3] given: the
    reach stays, a representative may lie on a face that does not count, and only children
    whose normal box may face the normal are entered); `visit(carry, extra, pos, keep, dist)`
    is called with, per slave, the W children's slots in their level `pos` [n, W], which of
    them are items within reach (`keep`, false except where the children are items) and the
    representatives' distances `dist` [n, W], and returns the new carry. `carry` and `extra`
    (read only): pytrees of per-slave arrays [n, ...] (the busy slaves' rows when the lanes
    shrink). shrink=False: the reach stays (every item within it is visited). Returns
    (carry, reach, steps: the busiest slave's)."""
    n = q.shape[0]
    top = flat.top
    # Row vectors: the tests run JAX with rank promotion off (broadcasts written out).
    lane = jnp.arange(W, dtype=jnp.int32)[None, :]
    levels = jnp.arange(top + 1, dtype=jnp.int32)[None, :]
    bits = jnp.left_shift(1, lane)
    lowest = jnp.asarray(_LOWEST_BIT)
    done = jnp.zeros(n, bool) if active is None else ~active
    # Per slave: the level k of the entry whose children it tests, their row, the pending
    # entries of each level (W bits) and the row they are in; and what it reads.
    state = (
        jnp.full(n, top, jnp.int32),
        jnp.full(n, flat.root, jnp.int32),
        # (the pending masks, W = 8 bits, in bytes: with int32 masks a detection took 7 %
        # longer at 2^20 on an H100, uniform rough surfaces, and a stack column more, 11 %:
        # the step is memory-bound)
        jnp.zeros((n, top + 1), jnp.uint8),
        jnp.zeros((n, top + 1), jnp.int32),
        reach,
        done,
        carry,
    )
    inputs = (q, normal, extra)

    def step(loop):
        (k, row, stack, base, reach, done, carry), (q, normal, extra), steps = loop
        pos = W * row[:, None] + lane  # the children's slots (level 0's rows come first)
        box = flat.groups[row]  # [n, 9, W]
        lo, hi, rep = box[:, 0:3], box[:, 3:6], box[:, 6:9]
        qs = q[:, :, None]
        g = jnp.maximum(jnp.maximum(lo - qs, qs - hi), 0)
        d2 = g[:, 0] ** 2 + g[:, 1] ** 2 + g[:, 2] ** 2
        filled = (lo[:, 0] <= hi[:, 0]) & (lo[:, 1] <= hi[:, 1]) & (lo[:, 2] <= hi[:, 2])
        r = rep - qs
        dr = jnp.where(filled, jnp.sqrt(r[:, 0] ** 2 + r[:, 1] ** 2 + r[:, 2] ** 2), jnp.inf)
        if normal is None:
            if shrink:
                reach = jnp.where(done, reach, jnp.minimum(reach, jnp.min(dr, -1) + slack))
        else:
            nq = normal[:, :, None]
            nlo, nhi = box[:, 9:12], box[:, 12:15]
            low = 0.5 * jnp.sum(nq * (nlo + nhi) - jnp.abs(nq) * (nhi - nlo), 1)
            filled = filled & (low < FACING_MARGIN)
        keep = filled & (d2 <= (reach * reach)[:, None]) & ~done[:, None]
        leaf = k == 1
        carry = visit(carry, extra, pos, keep & leaf[:, None], dr)
        # Descend to the nearest child (among boxes that hold q, the nearest centre), keeping
        # the others pending at their level.
        c = 0.5 * (lo + hi) - qs
        rank = jnp.where(d2 == 0, -1 / (1 + c[:, 0] ** 2 + c[:, 1] ** 2 + c[:, 2] ** 2), d2)
        near = jnp.argmin(jnp.where(keep, rank, jnp.inf), -1).astype(jnp.int32)
        down = jnp.any(keep, -1) & ~leaf
        rest = jnp.sum(jnp.where(keep, bits, 0), -1, dtype=jnp.int32) & ~jnp.left_shift(1, near)
        at = levels == (k - 1)[:, None]
        stack_down = jnp.where(at, rest[:, None].astype(jnp.uint8), stack)
        base_down = jnp.where(at, row[:, None], base)
        # Else the next pending entry: the lowest level >= k with pending children.
        kk = jnp.min(jnp.where((stack != 0) & (levels >= k[:, None]), levels, top), -1)
        at = jnp.minimum(kk, top)[:, None]
        left = jnp.take_along_axis(stack, at, 1)[:, 0].astype(jnp.int32)
        popped = (left & (left - 1)).astype(jnp.uint8)
        stack_up = jnp.where(levels == kk[:, None], popped[:, None], stack)
        up = jnp.where(down, row, jnp.take_along_axis(base, at, 1)[:, 0])
        row_new = flat.down[up, jnp.where(down, near, lowest[left])]
        finished = ~down & (kk >= top)
        k_new = jnp.where(down, k - 1, kk)
        stack_new = jnp.where(down[:, None], stack_down, stack_up)
        base_new = jnp.where(down[:, None], base_down, base)
        keep_old = done | finished
        state = (
            jnp.where(keep_old, k, k_new),
            jnp.where(keep_old, row, row_new),
            jnp.where(keep_old[:, None], stack, stack_new),
            jnp.where(keep_old[:, None], base, base_new),
            reach,
            done | finished,
            carry,
        )
        return state, (q, normal, extra), steps + 1

    def run(state, inputs, steps):
        """Steps until no more than 1/SHRINK of the lanes are busy, then the busy ones on
        their own (recursively), put back in their rows."""
        size = state[5].shape[0]
        m = size // SHRINK
        until = m if m >= MIN_LANES else 0

        def busy(loop):
            b = ~loop[0][5]
            return jnp.any(b) & (jnp.sum(b, dtype=jnp.int32) > until)

        state, inputs, steps = jax.lax.while_loop(busy, step, (state, inputs, steps))
        if not until:
            return state, steps
        rows = jnp.nonzero(~state[5], size=m, fill_value=size)[0]
        at = jnp.minimum(rows, size - 1)
        sub = jax.tree.map(lambda a: a[at], state)
        sub = sub[:5] + (sub[5] | (rows >= size),) + sub[6:]  # the spare lanes: done
        sub, steps = run(sub, jax.tree.map(lambda a: a[at], inputs), steps)
        state = jax.tree.map(lambda a, b: a.at[rows].set(b, mode="drop"), state, sub)
        return state, steps

    state, steps = run(state, inputs, jnp.int32(0))
    return state[6], state[4], steps


def _shrinks_to(d_max, slack, n, dtype):
    return jnp.zeros(n, dtype) + (d_max + slack)


def closest_node(
    xp, tree: Tree, nodes_x, slave_x, *, d_max, tie, slack, capacity=None, self_contact=None
):
    """The closest master node within d_max of each slave (ties: the smallest node id within
    `tie` of the smallest distance), -1 and inf where none: (node [n], distance [n], counts).
    The same answer as arraycontact._closest_node's (self_contact: its rule too)."""
    n = slave_x.shape[0]
    flat = flatten(tree)
    ids = tree.ids
    normal = None if self_contact is None else self_contact[1]

    def counted(keep, pos, slave):
        """The nodes that count: all, or (self-contact, item 4) those other than the slave's
        own (slave: its node and normal) with a normal at an obtuse angle to its normal."""
        if self_contact is None:
            return keep
        own, normal = slave
        node = ids[jnp.minimum(pos, ids.shape[0] - 1)]
        dot = jnp.sum(self_contact[2][node] * normal[:, None, :], -1)
        return keep & (node != own[:, None]) & (dot <= FACING_TOL)

    def nearest(carry, slave, pos, keep, dist):
        """The smallest distance so far, and the smallest id within `tie` of it (and d_max)
        with its distance, or unsure: where the smallest distance fell by less than `tie`
        and the id kept fell out of the band, another id seen before may be in it."""
        dmin, best, best_d, unsure = carry
        d = jnp.where(counted(keep, pos, slave), dist, jnp.inf)
        low = jnp.minimum(dmin, jnp.min(d, -1))
        band = jnp.minimum(low + tie, d_max)
        node = ids[jnp.minimum(pos, ids.shape[0] - 1)]
        step_id = jnp.min(jnp.where(d <= band[:, None], node, BIG), -1)
        step_d = jnp.min(jnp.where(node == step_id[:, None], d, jnp.inf), -1)
        kept = best_d <= band
        unsure = unsure | (~kept & (best < BIG) & (dmin <= band))
        best_d = jnp.where(kept & (best < step_id), best_d, step_d)
        best = jnp.where(kept, jnp.minimum(best, step_id), step_id)
        return low, best, best_d, unsure

    reach = _shrinks_to(d_max, slack, n, slave_x.dtype)
    inf = jnp.full(n, jnp.inf, slave_x.dtype)
    own = None if self_contact is None else self_contact[:2]
    kernel = _pallas_ok(normal)
    consts = tuple(jnp.asarray(v, slave_x.dtype) for v in (slack, tie, d_max))
    if kernel:
        (dmin, best, _, unsure), steps = _kernel_scan(flat, ids, slave_x, reach, consts, "nearest")
        unsure = unsure != 0
    else:
        carry = (inf, jnp.full(n, BIG, jnp.int32), inf, jnp.zeros(n, bool))
        (dmin, best, _, unsure), _, steps = scan(
            flat, slave_x, reach, slack, nearest, carry, None, normal, extra=own
        )
    dmin = jnp.where(dmin <= d_max, dmin, jnp.inf)
    has = dmin < jnp.inf

    def smallest_id(best, slave, pos, keep, dist):
        ok = counted(keep, pos, slave[:2]) & (dist <= (slave[2] + tie)[:, None]) & (dist <= d_max)
        node = ids[jnp.minimum(pos, ids.shape[0] - 1)]
        return jnp.minimum(best, jnp.min(jnp.where(ok, node, BIG), -1))

    # The unsure slaves again, with a reach of the smallest distance (few: none at all where
    # no two nodes lie within `tie` of each other's distance).
    again = has & unsure
    band = jnp.where(again, dmin + slack, 0)
    if kernel:
        (best2,), steps2 = _kernel_scan(
            flat, ids, slave_x, band, consts, "smallest_id", active=again, extra=dmin
        )
    else:
        extra = (None, None, dmin) if own is None else (*own, dmin)
        best2, _, steps2 = scan(
            flat, slave_x, band, slack, smallest_id, jnp.full(n, BIG, jnp.int32), again,
            normal, extra=extra,
        )  # fmt: skip
    best = jnp.where(again, best2, best)
    return jnp.where(has, best, -1), dmin, {"node_scan_steps": steps + steps2}


#: candidate_faces' pairs are K slots a slave, in slave order (run_stages reduces over the
#: slots, with no scatter)
SLOTS = True


def candidate_faces(xp, tree: Tree, slave_x, rho, *, slack, capacity, normal=None, shrink=True):
    """Candidate (slave, face) pairs: the faces whose box is within the slave's reach (rho,
    shrunk by the scan to the nearest surface point it meets; self-contact, `normal` given:
    those that may face it), K = capacity["face_candidates"]
    slots a slave. Returns (slave [n K], face [n K], valid [n K], counts); the count is the
    largest number of candidates of one slave (above K: overflow, the extra ones dropped)."""
    K = capacity["face_candidates"]
    found, count, steps = _collect(tree, slave_x, rho, slack, K, normal, shrink)
    return _slot_pairs(tree.ids[found], count, steps)


def _slot_pairs(face, count, steps):
    """The K slots a slave of face ids [n, K] with their count [n] as (slave, face, valid)
    pairs [n K] (an empty slot: face 0) and the counts."""
    n, K = face.shape
    valid = jnp.arange(K, dtype=jnp.int32)[None, :] < count[:, None]
    counts = {"face_candidates": jnp.max(count, initial=0), "face_scan_steps": steps}
    slave = jnp.repeat(jnp.arange(n), K)
    return slave, jnp.where(valid, face, 0).reshape(-1), valid.reshape(-1), counts


def candidate_distances(xp, tree: Tree, slave_x, rho, nodes_x, faces, *, slack, capacity):
    """`candidate_faces` of triangles (faces [F, 3] on nodes_x) with each slot's distance from
    its slave to its face (inf in the empty slots): (slave, face, valid, distance, counts).
    The kernel measures them after its scan, the while_loop's after it, by the same function
    (arraycontact._geometry.triangle_distance)."""
    K = capacity["face_candidates"]
    if _pallas_ok(None):
        consts = tuple(jnp.asarray(v, slave_x.dtype) for v in (slack, 0, 0))
        (face, dist, count), steps = _kernel_scan(
            flatten(tree), tree.ids, slave_x, rho, consts, "collect", k=max(K, 1),
            geometry=(nodes_x, faces),
        )  # fmt: skip
        face, dist = face[:, :K], dist[:, :K]
    else:
        found, count, steps = _collect(tree, slave_x, rho, slack, K, None)
        face = tree.ids[found]
        x = nodes_x[faces[face]]  # [n, K, 3 corners, 3]
        r = [slave_x[:, None, i] - x[..., 0, i] for i in range(3)]
        e1 = [x[..., 1, i] - x[..., 0, i] for i in range(3)]
        e2 = [x[..., 2, i] - x[..., 0, i] for i in range(3)]
        dist = triangle_distance(r, e1, e2, jnp)
    slave, face, valid, counts = _slot_pairs(face, count, steps)
    return slave, face, valid, jnp.where(valid, dist.reshape(-1), jnp.inf), counts


def candidate_counts(tree: Tree, slave_x, rho, *, slack, normal=None, shrink=True):
    """The number of candidate faces of each slave [n] (`candidate_faces` without slots): the
    work per slave that the sharded plan balances. shrink=False: every face whose box is
    within rho (the sharded plan's halos)."""
    return _collect(tree, slave_x, rho, slack, 0, normal, shrink)[1]


def _collect(tree, slave_x, rho, slack, K, normal, shrink=True):
    """The scan of candidate_faces: the first K candidates of each slave [n, K] (tree
    positions), their count [n] and the scan's steps."""
    n = slave_x.shape[0]
    flat = flatten(tree)

    def collect(carry, slave, pos, keep, dist):
        found, count = carry
        rows = jnp.arange(found.shape[0])[:, None]
        slot = count[:, None] + jnp.cumsum(keep, -1, dtype=jnp.int32) - 1
        found = found.at[rows, jnp.where(keep, slot, K)].set(pos, mode="drop")
        return found, count + jnp.sum(keep, -1, dtype=jnp.int32)

    if _pallas_ok(normal):
        consts = tuple(jnp.asarray(v, slave_x.dtype) for v in (slack, 0, 0))
        (found, count), steps = _kernel_scan(
            flat, tree.ids, slave_x, rho, consts, "collect", k=max(K, 1), shrink=shrink
        )
        return found[:, :K], count, steps
    carry = (jnp.zeros((n, K), jnp.int32), jnp.zeros(n, jnp.int32))
    (found, count), _, steps = scan(flat, slave_x, rho, slack, collect, carry, None, normal, shrink)
    return found, count, steps


# The scans as one Pallas (Triton) kernel on GPUs: a program walks a block of BLOCK slaves,
# its state in registers, each block stepping until its own busiest slave is done (the
# while_loop above reads and writes every slave's state in memory at every step until the
# busiest slave of all is done). The same step as `scan`'s (a change to one is a change to
# both: the tests compare them), written per child (W lists of [BLOCK] vectors: no
# reductions across an axis, which Pallas' Triton lowering lacks in part), and the same
# answers. H100, 2^20 rough nodes, the closest-node scan's first pass: 5.2 ms in
# the while_loop, 0.53 ms as a kernel.
BLOCK = 32
#: Off: the while_loop everywhere (a switch for A/B runs). INTERPRET: the kernel on any
#: platform, interpreted (the tests' way to run it on the CPU).
PALLAS = True
INTERPRET = False


def _pallas_ok(normal):
    """Whether the kernel runs the scan: on a GPU, not self-contact (whose normal test the
    kernel does not have), while JAX has Pallas' Triton back end (deprecated in JAX 0.11 for
    Mosaic GPU: without it, the while_loop)."""
    if not (PALLAS and normal is None and (INTERPRET or jax.default_backend() == "gpu")):
        return False
    try:
        from jax.experimental.pallas import triton  # noqa: F401
    except ImportError:
        return False
    return True


def _kernel_scan(
    flat, ids, q, reach, consts, kind, *, active=None, extra=None, k=1, shrink=True, geometry=None
):
    """One scan per slave of q [n, 3] from reach [n] (active [n]: the others are done before
    the first step). kind "nearest": the first pass of closest_node ((dmin, best, best_d,
    unsure) as its `nearest`); "smallest_id": its second (`extra`: dmin [n]); "collect":
    _collect's first k candidates (found [n, k], count [n]; with `geometry`, (nodes_x, faces)
    of triangles: their face ids and distances, (face [n, k], distance [n, k], count [n])).
    consts: (slack, tie, d_max). Returns (outputs, steps of the busiest slave)."""
    from jax.experimental import pallas as pl

    n = q.shape[0]
    dt = q.dtype
    rows = max(n + (-n % BLOCK), BLOCK)  # (a block at least: no empty grid)
    pad = rows - n
    if active is None:
        active = jnp.ones(n, bool)
    lanes = [q[:, 0], q[:, 1], q[:, 2], reach.astype(dt)]
    lanes += [jnp.zeros(n, dt) if extra is None else extra.astype(dt)]
    lanes = [jnp.pad(v, (0, pad)) for v in lanes] + [jnp.pad(active, (0, pad)).astype(jnp.int32)]
    top, root, n_ids = flat.top, flat.root, ids.shape[0]
    # An entry's rows: its box and point (9), and in a self-contact tree its normal box too
    # (15), which the kernel steps over (the sharded plan's scans without the normal test).
    stride = flat.groups.shape[1] * W
    inf = float("inf")

    def kernel(groups, down, ids_r, consts_r, *refs):
        if geometry is not None:
            nodes_r, faces_r, *refs = refs
        qx_r, qy_r, qz_r, reach_r, extra_r, act_r, *outs = refs
        slack, tie, d_max = consts_r[0], consts_r[1], consts_r[2]
        qx, qy, qz = qx_r[...], qy_r[...], qz_r[...]
        zero = jnp.zeros_like(act_r[...])
        big = zero + BIG
        finf = jnp.zeros_like(qx) + inf

        def step(s):
            kk_, row, stack, base, rch, done, carry, steps = s
            busy = done == 0
            leaf = kk_ == 1
            at = row * stride
            d2, dr, filled, rank = [], [], [], []
            for j in range(W):
                c = [groups[at + (i * W + j)] for i in range(9)]
                gx = jnp.maximum(jnp.maximum(c[0] - qx, qx - c[3]), 0)
                gy = jnp.maximum(jnp.maximum(c[1] - qy, qy - c[4]), 0)
                gz = jnp.maximum(jnp.maximum(c[2] - qz, qz - c[5]), 0)
                f = (c[0] <= c[3]) & (c[1] <= c[4]) & (c[2] <= c[5])
                ex, ey, ez = c[6] - qx, c[7] - qy, c[8] - qz
                d2.append(gx * gx + gy * gy + gz * gz)
                dr.append(jnp.where(f, jnp.sqrt(ex * ex + ey * ey + ez * ez), inf))
                filled.append(f)
                cx = 0.5 * (c[0] + c[3]) - qx
                cy = 0.5 * (c[1] + c[4]) - qy
                cz = 0.5 * (c[2] + c[5]) - qz
                rank.append(jnp.where(d2[j] == 0, -1 / (1 + cx * cx + cy * cy + cz * cz), d2[j]))
            if shrink:
                low = dr[0]
                for j in range(1, W):
                    low = jnp.minimum(low, dr[j])
                rch = jnp.where(busy, jnp.minimum(rch, low + slack), rch)
            keep = [filled[j] & (d2[j] <= rch * rch) & busy for j in range(W)]
            items = [keep[j] & leaf for j in range(W)]
            pos = [row * W + j for j in range(W)]
            carry = visit(carry, pos, items, dr, (tie, d_max))
            # Descend to the nearest child, the others pending at their level.
            best_r, near, bits = finf, zero + W, zero
            for j in range(W):
                rj = jnp.where(keep[j], rank[j], inf)
                better = rj < best_r
                near = jnp.where(better, j, near)
                best_r = jnp.where(better, rj, best_r)
                bits = bits | jnp.where(keep[j], zero + (1 << j), zero)
            go_down = (bits != 0) & ~leaf
            near = jnp.minimum(near, W - 1)
            rest = bits & ~jnp.left_shift(1, near)
            # Else the next pending entry: the lowest level >= k with pending children.
            lvl = zero + top
            for j in reversed(range(top + 1)):
                lvl = jnp.where((stack[j] != 0) & (kk_ <= j), j, lvl)
            left, b_at = zero, zero
            for j in range(top + 1):
                left = jnp.where(lvl == j, stack[j], left)
                b_at = jnp.where(lvl == j, base[j], b_at)
            low_bit = zero
            for j in reversed(range(W)):
                low_bit = jnp.where((left >> j) & 1 == 1, j, low_bit)
            up = jnp.where(go_down, row, b_at)
            row_new = down[up * W + jnp.where(go_down, near, low_bit)]
            finished = ~go_down & (lvl >= top)
            stay = ~busy | finished
            popped = left & (left - 1)
            stack = tuple(
                jnp.where(
                    stay,
                    sj,
                    jnp.where(
                        go_down, jnp.where(kk_ - 1 == j, rest, sj), jnp.where(lvl == j, popped, sj)
                    ),
                )
                for j, sj in enumerate(stack)
            )
            base = tuple(jnp.where(~stay & go_down & (kk_ - 1 == j), row, bj)
                         for j, bj in enumerate(base))  # fmt: skip
            kk_ = jnp.where(stay, kk_, jnp.where(go_down, kk_ - 1, lvl))
            row = jnp.where(stay, row, row_new)
            done = jnp.where(stay, zero + 1, zero)
            return kk_, row, stack, base, rch, done, carry, steps + busy.astype(jnp.int32)

        if kind == "nearest":

            def visit(carry, pos, items, dist, scal):
                tie, d_max = scal
                dmin, best, best_d, unsure = carry
                d = [jnp.where(items[j], dist[j], inf) for j in range(W)]
                node = [ids_r[jnp.minimum(p, n_ids - 1)] for p in pos]
                low = dmin
                for j in range(W):
                    low = jnp.minimum(low, d[j])
                band = jnp.minimum(low + tie, d_max)
                step_id = big
                for j in range(W):
                    step_id = jnp.minimum(step_id, jnp.where(d[j] <= band, node[j], BIG))
                step_d = finf
                for j in range(W):
                    step_d = jnp.minimum(step_d, jnp.where(node[j] == step_id, d[j], inf))
                kept = best_d <= band
                unsure = unsure | (~kept & (best < BIG) & (dmin <= band)).astype(jnp.int32)
                best_d = jnp.where(kept & (best < step_id), best_d, step_d)
                best = jnp.where(kept, jnp.minimum(best, step_id), step_id)
                return low, best, best_d, unsure

            carry = (finf, big, finf, zero)
        elif kind == "smallest_id":
            dmin_x = extra_r[...]

            def visit(best, pos, items, dist, scal):
                tie, d_max = scal
                for j in range(W):
                    ok = items[j] & (dist[j] <= dmin_x + tie) & (dist[j] <= d_max)
                    node = ids_r[jnp.minimum(pos[j], n_ids - 1)]
                    best = jnp.minimum(best, jnp.where(ok, node, BIG))
                return best

            carry = big
        else:
            from jax.experimental.pallas import triton as plt

            found_r = outs[0]
            local = jax.lax.broadcasted_iota(jnp.int32, (BLOCK,), 0) * k  # each slave's k slots

            def visit(count, pos, items, dist, scal):
                for j in range(W):
                    put = items[j] & (count < k)
                    plt.store(found_r.at[local + jnp.minimum(count, k - 1)], pos[j], mask=put)
                    count = count + items[j].astype(jnp.int32)
                return count

            def measure(slot, _):
                """Slot `slot` of each slave: its face and distance, read where the slot is
                filled, in a frame at the face's first corner (as _projection's). After the
                scan, not as it finds them: a step's W children would cost W distances a
                lane, leaf or not (H100, uniform 2^20: 6.5 ms a detection, against 5.4 measured
                after the scan)."""
                put = slot < count
                at = local + slot

                def load(ref, i):
                    return plt.load(ref.at[i], mask=put, other=0)

                face = load(ids_r, load(found_r, at))
                x = [[load(nodes_r, load(faces_r, 3 * face + c) * 3 + i) for i in range(3)]
                     for c in range(3)]  # fmt: skip
                r = (qx - x[0][0], qy - x[0][1], qz - x[0][2])
                e1, e2 = ([x[c][i] - x[0][i] for i in range(3)] for c in (1, 2))
                plt.store(found_r.at[at], face, mask=put)
                plt.store(outs[1].at[at], triangle_distance(r, e1, e2, jnp), mask=put)
                return _

            carry = zero
        state = (zero + top, zero + root, (zero,) * (top + 1), (zero,) * (top + 1),
                 reach_r[...], 1 - act_r[...], carry, zero)  # fmt: skip
        state = jax.lax.while_loop(lambda s: jnp.min(s[5]) == 0, step, state)
        carry, steps = state[6], state[7]
        if geometry is not None:
            count = carry
            jax.lax.fori_loop(0, jnp.minimum(jnp.max(count), k), measure, 0)
        res = carry if isinstance(carry, tuple) else (carry,)
        rest_outs = outs[1 + (geometry is not None) :] if kind == "collect" else outs
        for o, v in zip(rest_outs, res + (steps,)):
            o[...] = v.astype(o.dtype)

    blk = pl.BlockSpec((BLOCK,), lambda i: (i,))
    whole = pl.no_block_spec
    i32 = jnp.int32
    if kind == "nearest":
        shapes = [(rows, dt), (rows, i32), (rows, dt), (rows, i32)]
    elif kind == "smallest_id":
        shapes = [(rows, i32)]
    else:
        shapes = [(rows * k, i32)] + [(rows * k, dt)] * (geometry is not None) + [(rows, i32)]
    shapes.append((rows, i32))  # steps
    specs = [blk] * len(shapes)
    if kind == "collect":
        specs[0] = pl.BlockSpec((BLOCK * k,), lambda i: (i,))
        if geometry is not None:
            specs[1] = specs[0]
    wholes = [flat.groups.reshape(-1), flat.down.reshape(-1), ids, jnp.stack(consts).astype(dt)]
    if geometry is not None:
        wholes += [geometry[0].astype(dt).reshape(-1), geometry[1][:, :3].reshape(-1)]
    kw = {}
    if not INTERPRET:
        from jax.experimental.pallas import triton as plt

        kw["compiler_params"] = plt.CompilerParams(num_warps=1, num_stages=1)
    outs = pl.pallas_call(
        kernel,
        out_shape=tuple(jax.ShapeDtypeStruct((s,), d) for s, d in shapes),
        grid=(rows // BLOCK,),
        in_specs=[whole] * len(wholes) + [blk] * 6,
        out_specs=tuple(specs),
        interpret=INTERPRET,
        **kw,
    )(*wholes, *lanes)
    steps = jnp.max(outs[-1][:n], initial=0)
    outs = outs[:-1]
    if kind == "collect":
        count = outs[-1][:n]
        valid = jnp.arange(k, dtype=i32)[None, :] < count[:, None]
        slots = [o.reshape(rows, k)[:n] for o in outs[:-1]]
        slots[0] = jnp.where(valid, slots[0], 0)
        return (*slots, count), steps
    return tuple(o[:n] for o in outs), steps
