"""Detection over the devices of a `jax.sharding.Mesh` (seed 004's RCB, seed 000's MDMR).

`plan(..., mesh=mesh)` splits the slaves and the master's faces by recursive coordinate
bisection (arraycontact._partition), balancing the JAX search's work (a lane per slave, a tree
entry per face some slave reaches), one part per device along the mesh axis. Each part gets a
master of its own: its halo faces (those its slaves may reach, listed by the tree), the ring
around them (so node normals, edges and boundary are the whole master's) and padding (small
faces far from everything) to the shapes every part shares, which shard_map needs. Its trees
hold its own items, in the one-device order and grouped by the one-device rule (Morton
prefixes), padded to the parts' common level sizes; the padding's items are in no group.

`detect` takes the coordinates as arrays sharded by rows over the axis (or replicated):
device d holds rows [d B, (d + 1) B). Inside shard_map each device

1. keeps the rows of its block that its own part needs, sends those other parts need and
   receives the rest of its own (one all_to_all for the master's nodes, one for the slaves):
   only rows another part needs cross devices;
2. runs the one-device detection (arraycontact_jax._detect.local_detect) on its part, with the
   scene's constants (d_max, tolerances, frame), so every row is the one-device answer (the
   search in JAX, or with search="warp" the part's own Warp plan on the device);
3. sends each answer back to the device holding the slave's row (one all_to_all, the integer
   fields and the counts riding with the float ones; each device takes the largest count).
Rows that are no whole number of blocks a device (slaves or master points: JAX shards rows
only in equal blocks) come replicated: each part takes its items from them (no exchange for
that side), and where the slaves are such, the answer goes out replicated: every part's
answer to every device, one all_gather (in place of step 3).

Gradients flow through the gathers and all_to_alls as through the one-device detection. The
halos hold as long as slaves and master nodes move less than the partition's margin from the
plan-time configuration, together; the motion is reported as the count `halo_motion` against
the capacity `margin` (overflow), and `update_plan` partitions again.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import NamedSharding
from jax.sharding import PartitionSpec as P

from arraycontact._contacts import Contacts
from arraycontact._detect import (
    Scalars,
    Static,
    build_grids,
    check_options,
    scalars,
)
from arraycontact._grid import W, grouping, morton_keys
from arraycontact._partition import Partition, partition
from arraycontact._prepare import Prepared
from arraycontact._surface import Surface, bounds, in_threads

from . import _grid
from ._detect import (
    Plan,
    _grown,
    _per_slave,
    _topology_arrays,
    _WarpSearch,
    contacts_of,
    local_detect,
    master_arrays,
    once,
    warp_plan,
)
from ._gradients import valence_fits

#: The answer's fields a part sends home (self-contact also `finer`).
_FIELDS = (
    "xi", "point", "gap", "distance", "normal", "active", "face", "feature", "master_node",
    "status",
)  # fmt: skip


@dataclass(frozen=True, eq=False)
class ShardedPlan:
    """A detection split over the devices of `mesh` along `axis` (build it with
    `plan(..., mesh=mesh)`); a pytree whose leaves are sharded over the axis.

    local: the one-device Plan every device runs (its topology leaves stacked [D, ...]);
    exchange: the index arrays of the all_to_alls and the plan-time coordinates;
    partition: the RCB cuts, halos and per-part counts (`counts`)."""

    local: object
    exchange: dict
    mesh: object = None
    axis: str = "space"
    partition: Partition = field(default=None, repr=False)
    n_slaves: int = 0
    blocks: tuple = (0, 0)  # rows a device holds: slaves, master points
    lebesgue: float = 1.0
    counts: tuple = ()  # sorted (name, per-part list): the balance the plan measured

    @property
    def d_max(self) -> float:
        return self.local.d_max

    @property
    def dtype(self) -> str:
        return self.local.dtype

    @property
    def master(self) -> Surface:
        return self.local.master

    @property
    def n_devices(self) -> int:
        return self.mesh.shape[self.axis]

    @property
    def replicated(self) -> tuple[bool, bool]:
        """Whether the slaves' rows, and the master's points, are no whole number of blocks a
        device (JAX shards rows only in equal blocks): such rows come replicated and each part
        takes its own from them; replicated slaves' rows get a replicated answer."""
        b_s, b_m = self.blocks
        n = self.n_devices
        return n * b_s != self.n_slaves, n * b_m != len(self.master.points)

    @property
    def capacity(self) -> dict:
        return {**dict(self.local.capacity), "halo_motion": self.partition.margin}


jax.tree_util.register_pytree_node(
    ShardedPlan,
    lambda p: (
        (p.local, p.exchange),
        (p.mesh, p.axis, p.partition, p.n_slaves, p.blocks, p.lebesgue, p.counts),
    ),
    lambda aux, ch: ShardedPlan(ch[0], ch[1], *aux),
)


def plan(
    master,
    slave_x,
    *,
    mesh,
    axis,
    mode,
    d_max,
    dtype,
    growth,
    minimum,
    search,
    self_contact,
    margin=None,
):
    """The sharded plan (see arraycontact_jax.plan: `mesh`, `axis`, `margin`)."""
    if axis not in mesh.shape:
        raise ValueError(f"mesh has no axis {axis!r} (its axes: {tuple(mesh.shape)})")
    n_dev = mesh.shape[axis]
    if len(mesh.shape) != 1:
        raise ValueError("the mesh must have the one axis the parts are split over")
    d_max, dtype = check_options(master, mode, d_max, None, dtype)
    element = master.element
    centres, radii = master.face_bounds
    r_max = float(radii.max())
    all_x = master.points[master.nodes] if self_contact else slave_x
    lo = np.minimum(bounds(all_x)[0], master.node_box[0]) - d_max
    hi = np.maximum(bounds(all_x)[1], master.node_box[1]) + d_max
    origin = lo if dtype == np.float32 else np.zeros(3)
    extent = float((hi - lo).max())
    # The one-device plan's trees: the nodes and faces in the Morton order of the scene's
    # cube, grouped by Morton prefixes as one device's JAX plan groups them.
    # (Each key once: morton_order's keys, sorted. At 2^20 on a GPU host the keys took 0.3 s
    # a call.)
    node_keys = morton_keys(master.points[master.nodes], lo, extent)
    order = np.argsort(node_keys, kind="stable")
    node_ids, node_keys = master.nodes[order], node_keys[order]
    face_keys = morton_keys(centres, lo, extent)
    face_ids = np.argsort(face_keys, kind="stable")
    face_keys = face_keys[face_ids]
    # The scene's constants, shared by every part: the answer is the one-device answer.
    prep = Prepared(
        slave_rows=np.arange(len(all_x)),
        node_ids=node_ids,
        face_ids=face_ids,
        origin=origin,
        d_max=d_max,
        r_max=r_max * growth,
        node_groups=grouping(node_keys),
        face_groups=grouping(face_keys),
        extent=2 * float(np.abs(np.r_[lo - origin, hi - origin]).max()),
    )
    sc = scalars(prep, master, dtype)
    st_global = Static.of(master, mode, prep, self_contact)

    # 1. The faces each slave reaches, on one device, then the RCB.
    sc_dev = Scalars(*(jnp.asarray(v, dtype=dtype) for v in sc))
    x_dev = jnp.asarray((all_x - origin).astype(dtype))
    ids = jnp.asarray(master.nodes.astype(np.int32)) if self_contact else None
    m = jax.tree.map(jnp.asarray, master_arrays(master, prep, dtype))
    margin = (growth - 1) * (d_max + r_max) if margin is None else float(margin)
    if not margin >= 0:
        raise ValueError(f"margin must be >= 0, got {margin}")
    reached = _Reached(sc_dev, m, x_dev, _reach(sc_dev, m, x_dev, margin, st_global), st_global)
    # The work the JAX search does per item: every slave is a lane of the same scans and the
    # same candidate slots, whatever its candidates (weighting slaves by 1 + candidates
    # left 2^23 rough nodes split 3.6M / 4.8M on two H200s: 122 ms where the even split
    # takes 101); a face costs its tree entry and geometry where some slave reaches it (a
    # halo face: within a slave's reach).
    weights, face_weights = np.ones(len(all_x)), None
    if mode == "exact":
        face_weights = reached(np.zeros(len(all_x), np.int32), 1)[0].astype(float)
    part = partition(
        master,
        None if self_contact else slave_x,
        n_dev,
        d_max=d_max,
        margin=margin,
        weights=weights,
        face_weights=face_weights,
        self_contact=self_contact,
        reached=partial(reached, n_groups=n_dev),
    )
    del reached  # (its device buffers)
    parts = in_threads(part.part, range(n_dev))

    # 2. Each part's master, padded to shared shapes.
    k = element.nodes_per_face
    f_cap = max(len(q.faces) for q in parts) + 1  # one spare face at least: padded slaves' own
    p_cap = max(len(q.nodes) + k * (f_cap - len(q.faces)) for q in parts)
    s_cap = max(max(len(q.slaves) for q in parts), 1)
    reach = d_max + part.margin
    spacing = 4 * (reach + r_max) + 2 * master.longest_edge
    far = hi + spacing  # the padding's corner, beyond reach of every slave
    nowhere = lo - spacing  # where padded slave rows sit, beyond reach of every face
    node_rank = np.zeros(len(master.points), np.int64)
    node_rank[prep.node_ids] = np.arange(len(prep.node_ids))
    face_rank = np.argsort(prep.face_ids)
    # Each part's trees over its own items in the one-device Morton order, grouped by the
    # same rule (Morton prefixes), padded to the parts' common level sizes.
    trees = in_threads(
        lambda q: (
            _part_tree(node_rank[q.nodes], node_keys),
            _part_tree(face_rank[q.faces], face_keys),
        ),
        parts,
    )
    t_n = max(len(q.nodes) for q in parts)
    t_f = max(len(q.faces) for q in parts)
    node_groups = _common_levels([t[0][1] for t in trees])
    face_groups = _common_levels([t[1][1] for t in trees])
    locals_, tables, lives = [], [], []
    padded = in_threads(
        lambda q: _padded(q, element, f_cap, p_cap, far, spacing, master.longest_edge), parts
    )
    for e, ((n_ids, _), (f_ids, _)) in enumerate(trees):
        surf, pad_x = padded[e]
        pq = replace(
            prep,
            node_ids=np.pad(n_ids, (0, t_n - len(n_ids))),
            face_ids=np.pad(f_ids, (0, t_f - len(f_ids))),
            node_groups=node_groups[e],
            face_groups=face_groups[e],
        )
        locals_.append((surf, pq))
        tables.append(pad_x)
        # (the padding items are in no group; dead all the same)
        lives.append((np.arange(t_n) < len(n_ids), np.arange(t_f) < len(f_ids)))

    table = valence_fits(master)
    topo = in_threads(
        lambda sp: _topology_arrays(*sp, self_contact, part=True, table=table), locals_
    )
    for e, q in enumerate(parts):
        slave_nodes = None
        if self_contact:
            own = np.searchsorted(q.nodes, master.nodes[q.slaves]).astype(np.int32)
            slave_nodes = np.full(s_cap, len(q.nodes), np.int32)  # a padding node
            slave_nodes[: len(own)] = own
        n_live, f_live = lives[e]
        topo[e] = topo[e]._replace(slave_nodes=slave_nodes, node_live=n_live, face_live=f_live)
    topo = _stack(topo)
    pq = locals_[0][1]
    st = replace(st_global, node_levels=pq.node_levels, face_levels=pq.face_levels)

    # 3. The exchange: rows a device sends to each part and where each part reads them.
    n_rows, n_pts = len(all_x), len(master.points)
    b_s, b_m = -(-n_rows // n_dev), -(-n_pts // n_dev)
    s_route, s_sent = _routes([q.slaves for q in parts], b_s, n_dev, s_cap, "s_")
    m_route, m_sent = _routes([q.nodes for q in parts], b_m, n_dev, p_cap, "m_", back=False)
    pad_x = np.stack(tables)
    x_ref = np.zeros((n_dev * b_s, 3))
    x_ref[:n_rows] = all_x
    m_ref = np.zeros((n_dev * b_m, 3))
    m_ref[:n_pts] = master.points
    s_used = np.arange(n_dev * b_s) < n_rows
    m_used = np.zeros(n_dev * b_m, bool)
    m_used[master.nodes] = True
    face_ids = np.full((n_dev, f_cap), -1, np.int32)
    node_ids = np.full((n_dev, p_cap), -1, np.int32)
    for e, q in enumerate(parts):
        face_ids[e, : len(q.faces)] = q.faces
        node_ids[e, : len(q.nodes)] = q.nodes
    exchange = dict(
        **s_route,
        **m_route,
        s_ref=x_ref.reshape(n_dev, b_s, 3),
        s_used=s_used.reshape(n_dev, b_s),
        m_pad=pad_x,
        m_ref=m_ref.reshape(n_dev, b_m, 3),
        m_used=m_used.reshape(n_dev, b_m),
        face_ids=face_ids,
        node_ids=node_ids,
        nowhere=np.broadcast_to(nowhere, (n_dev, 3)),
    )
    if n_dev * b_s != n_rows:  # the answer replicated (`_everywhere`): each row's part slot
        row = np.zeros(n_rows, np.int32)
        rows = np.zeros((n_dev, s_cap), np.int32)  # (and the slaves come replicated: their rows)
        for e, q in enumerate(parts):
            row[q.slaves] = e * s_cap + np.arange(len(q.slaves))
            rows[e, : len(q.slaves)] = q.slaves
        exchange["s_all"] = np.broadcast_to(row, (n_dev, n_rows))
        if not self_contact:
            exchange["s_rows"] = rows
    engine, cand, cap = None, [], {}
    if search == "warp":  # each part's Warp plan on its device, sized by its own counts
        # In the frame and the box one device's Warp plan takes (a part's padding, far off,
        # would move its own frame and change float32's roundings, and widen its box and
        # coarsen its Morton keys: on two H200s the parts' kernels took 11-13 % longer).
        frame = bounds(all_x)[0] - d_max
        plans = []
        for e, (surf, _) in enumerate(locals_):
            if self_contact:  # every node of the part's surface, answered by its point id
                if not np.array_equal(surf.nodes, np.arange(len(surf.nodes))):
                    raise AssertionError("a part's used points must come first")
                xs = surf.points[surf.nodes]
            else:
                xs = _part_slaves(all_x, parts[e].slaves, s_cap, nowhere)
            plans.append(
                warp_plan(
                    surf,
                    xs,
                    d_max,
                    dtype,
                    growth,
                    origin,
                    self_contact=self_contact,
                    device=mesh.devices.flat[e],
                    tie=float(sc.tie),
                    frame=frame,
                    box=(lo, hi),
                )
            )
        engine = _WarpSearch(plans, dtype, self_contact, axis=axis)
    else:
        # The capacities: one device's counts, times growth. A part's slave has about the
        # candidates it has on one device: its part holds every face within its reach and
        # its trees group them by the one-device rule (the same groups but where the part's
        # items end). (Each part's own count was a compilation for the parts' shapes and a
        # search, most of a second plan's time; the detection counts and reports overflow.)
        per = np.asarray(once(_per_slave, sc_dev, m, x_dev, ids, st=st_global))
        cand = [per[q.slaves] for q in parts]
        if mode == "exact":
            counts = {"face_candidates": max(int(c.max(initial=0)) for c in cand)}
        else:
            counts = {"attached": max(int(c.sum()) for c in cand)}
        cap = _grown(counts, growth, s_cap, minimum)
    balance = dict(
        slaves=[len(q.slaves) for q in parts],
        halo_faces=[len(h) for h in part.halo],
        local_faces=[len(q.faces) for q in parts],
        candidates=[int(c.sum()) for c in cand],  # the JAX search's (none with Warp's)
        work=[float(w) for w in part.work],
        # Rows that cross devices in the exchange (slaves: none in self-contact) and the
        # widest route to another device (slaves, master).
        sent_slave_rows=0 if self_contact else s_sent,
        sent_master_rows=m_sent,
        route_widths=[s_route["s_send"].shape[2], m_route["m_send"].shape[2]],
    )
    sharding = NamedSharding(mesh, P(axis))

    def put(a):
        a = np.ascontiguousarray(a)
        return jax.make_array_from_callback(a.shape, sharding, lambda i: a[i])

    local = Plan(
        jax.tree_util.tree_map(put, topo),
        master,
        st,
        tuple(sorted(cap.items())),
        sc,
        tuple(float(v) for v in origin),
        np.dtype(dtype).name,
        s_cap,
        growth,
        engine,
    )
    return ShardedPlan(
        local,
        {k2: put(v.astype(dtype) if v.dtype.kind == "f" else v) for k2, v in exchange.items()},
        mesh,
        axis,
        part,
        n_rows,
        (b_s, b_m),
        float(element.lebesgue),
        tuple(sorted(balance.items())),
    )


def _part_slaves(all_x, mine, s_cap, nowhere):
    """A part's slave coordinates [s_cap, 3] as detect gathers them: its own rows, then padding
    rows beyond reach of every face."""
    xs = np.repeat(nowhere[None], s_cap, 0)
    xs[: len(mine)] = all_x[mine]
    return xs


def _reach(sc, m, x, margin, st):
    """How far from each slave [n] its halo reaches: the faces it may need while slaves and
    master nodes move less than `margin` together. The search needs the faces within
    min(dn, d_max) of a slave (dn: its closest master node's distance, which such motion
    changes by at most the margin), and a face comes at most the margin closer: so
    min(dn + margin, d_max) + margin, tighter than d_max + margin where the mesh is finer
    than d_max (graded meshes). Self-contact's reach is bounded by faces, not nodes: d_max +
    margin."""
    d_max, slack = float(sc.d_max), float(sc.slack)
    if st.self_contact:
        return np.full(x.shape[0], d_max + margin + slack)
    dn = np.asarray(_closest_distance(sc, m, x, st=st), np.float64)
    return np.minimum(dn + margin, d_max) + margin + slack


@partial(jax.jit, static_argnames=("st",))
def _closest_distance(sc, m, x, *, st):
    grids = build_grids(jnp, st, m)
    return _grid.closest_node(
        jnp,
        grids.node,
        m.nodes_x,
        x,
        d_max=sc.d_max,
        tie=sc.tie,
        slack=sc.slack,
    )[1]


class _Reached:
    """The faces each slave reaches (its face's box within `reach` [n] of it): the halos of
    each slave on its own (a part holding slaves both near and far from the master needs the
    faces near each, not those near the box around them all). Found once on the device, in
    chunks of slaves that keep the candidate slots under `slots`, and kept there; a call
    (group [n], n_groups) returns [n_groups, F] host bools: whether a slave of each group
    reaches the face. (The pairs themselves, brought to the host, took most of a graded
    scene's plan at 2^20.)"""

    def __init__(self, sc, m, x, reach, st, chunk=1 << 16, slots=1 << 24):
        # (Node mode too: a face incident to a node within reach has its box within reach.)
        grid = _face_tree(sc, m, st=replace(st, mode="exact"))
        n, self.n_faces = x.shape[0], m.faces.shape[0]
        rho = jnp.asarray(reach, x.dtype)
        count = np.asarray(_counts_within(grid, x, rho, sc.slack))
        # Padded by a chunk of rows (of no group: dropped when marked), so that every chunk
        # has one of a few shapes: a few compilations serve every chunk. No chunk longer
        # than the slaves (to a power of two): a chunk's scan and marks run over all its
        # rows, real or padding (4096 graded slaves on two CPU devices: a plan 1.30 -> 0.78
        # s). (Chunks of slaves sorted by their counts, each chunk's slots fitting its count
        # class, took that to 0.60 s but a plan at 2^21 on two H200s from 5.29 to 5.70 s,
        # its first from 25.6 to 35.2 s: the sort and a compilation a class.)
        self.pad = chunk = min(chunk, 1 << max(n - 1, 1).bit_length())
        x = jnp.pad(x, ((0, chunk), (0, 0)))
        rho = jnp.pad(rho, (0, chunk))
        self.chunks = []  # (first slave, slots a slave, the slots' faces or -1)
        start = 0
        while start < n:
            k = 1 << (max(int(count[start : start + chunk].max()), 1) - 1).bit_length()
            size = 1 << (min(chunk, max(slots // k, 1)).bit_length() - 1)
            faces = _reached_faces(grid, x, rho, jnp.int32(start), sc.slack, k=k, size=size)
            self.chunks.append((start, k, faces))
            start += size

    def __call__(self, group, n_groups):
        group = jnp.asarray(np.pad(group, (0, self.pad), constant_values=n_groups), jnp.int32)
        hit = jnp.zeros((n_groups, self.n_faces), bool)
        for start, k, faces in self.chunks:
            hit = _mark(hit, group, jnp.int32(start), faces, k=k)
        return np.asarray(hit)


@partial(jax.jit, static_argnames=("k", "size"))
def _reached_faces(grid, x, rho, start, slack, *, k, size):
    """The candidate slots' faces of slaves [start, start + size) [size k], -1 where empty."""
    xs = jax.lax.dynamic_slice_in_dim(x, start, size)
    rs = jax.lax.dynamic_slice_in_dim(rho, start, size)
    _, face, valid, _ = _grid.candidate_faces(
        jnp, grid, xs, rs, slack=slack, capacity={"face_candidates": k}, shrink=False
    )
    return jnp.where(valid, face, -1).astype(jnp.int32)


@partial(jax.jit, static_argnames=("k",))
def _mark(hit, group, start, faces, *, k):
    rows = jnp.repeat(jax.lax.dynamic_slice_in_dim(group, start, faces.shape[0] // k), k)
    rows = jnp.where(faces >= 0, rows, hit.shape[0])  # (an empty slot: dropped)
    return hit.at[rows, faces].set(True, mode="drop")


@partial(jax.jit, static_argnames=("st",))
def _face_tree(sc, m, *, st):
    return build_grids(jnp, st, m).face


@jax.jit
def _counts_within(grid, x, rho, slack):
    return _grid.candidate_counts(grid, x, rho, slack=slack, shrink=False)


def _part_tree(rank, keys):
    """A part's tree over its items whose positions in the one-device tree's order are
    `rank` (the items' keys there: `keys`): (ids, the part's items (local ids) in that order;
    groups, `grouping` of their keys)."""
    ids = np.argsort(rank)
    return ids, grouping(keys[rank[ids]])


def _common_levels(groups):
    """The parts' tree slots (`grouping`'s, one tuple a part) to the same shapes: as many
    levels as the deepest (a shallower part's root gets parents of one entry) and each
    level's slots padded with empty ones (-1) to the widest; padding groups are empty boxes
    no level above points to."""
    depth = max(len(g) for g in groups)
    root = np.array([0] + [-1] * (W - 1), np.int32)
    groups = [list(g) + [root] * (depth - len(g)) for g in groups]
    width = [max(len(g[k]) for g in groups) for k in range(depth)]
    return [
        tuple(np.pad(g[k], (0, width[k] - len(g[k])), constant_values=-1) for k in range(depth))
        for g in groups
    ]


def _padded(q, element, f_cap, p_cap, far, spacing, size):
    """Part q's master with f_cap faces and p_cap points: its own, then small flat faces on
    nodes of their own on a grid beyond `far` (apart by `spacing`: none within reach of
    another or of the scene), then unused points there. Also [p_cap, 3]: the padding's
    coordinates (0 on the part's own rows)."""
    k = element.nodes_per_face
    n_pad = f_cap - len(q.faces)
    side = max(int(np.ceil(n_pad ** (1 / 3))), 1)
    j = np.arange(n_pad)
    corner = far + spacing * np.stack([j % side, (j // side) % side, j // side**2], -1)
    flat = np.c_[element.nodes, np.zeros(k)] * size  # the reference element, scaled
    pts = (corner[:, None, :] + flat[None]).reshape(-1, 3)
    n_real = len(q.nodes)
    unused = p_cap - n_real - len(pts)
    pts = np.concatenate([pts, np.repeat(far[None] - spacing, unused, 0)])
    faces = np.concatenate([q.master.faces, n_real + np.arange(n_pad * k).reshape(n_pad, k)])
    points = np.concatenate([q.master.points, pts])
    pad_x = np.zeros((p_cap, 3))
    pad_x[n_real:] = pts
    return Surface(points, faces, element), pad_x


def _routes(members, block, n_dev, cap, prefix, back=True):
    """The routes of items held in row blocks of `block` rows (device d: rows
    [d block, (d + 1) block)) to the parts whose sorted ids are `members[e]`, and back.

    Out: `send` [D(src), D(dst), C]: the rows of its block each device sends to each other
    part (C the widest route, 1 at least; unused slots row 0); `take` [D, cap]: where a part
    reads its i-th item in [its device's block; received D C rows], `ok`: which are real.
    With `back` (the slaves', whose answers go home): `back` [D(part), D(dst), C]: the item a
    part sends to each device in each slot, `home` [D, block]: where a device reads each of
    its rows in [its part's items (cap); received D C rows]. Only the rows another part needs
    cross devices; everything else is a gather (no scatter)."""
    c = max(
        [
            int(np.sum(m // block == d))
            for e, m in enumerate(members)
            for d in range(n_dev)
            if d != e
        ]
        + [1]
    )
    send = np.zeros((n_dev, n_dev, c), np.int32)
    take = np.zeros((n_dev, cap), np.int32)
    ok = np.zeros((n_dev, cap), bool)
    ret = np.zeros((n_dev, n_dev, c), np.int32)
    home = np.zeros((n_dev, block), np.int32)
    sent = 0
    for e, m in enumerate(members):
        src = m // block
        # members are sorted, so those of one source block are consecutive
        slot = np.arange(len(m)) - np.searchsorted(src, np.arange(n_dev))[src]
        mine = src == e
        away = ~mine
        i = np.arange(len(m))
        send[src[away], e, slot[away]] = m[away] - src[away] * block
        take[e, : len(m)] = np.where(mine, m - e * block, block + src * c + slot)
        ok[e, : len(m)] = True
        if back:
            ret[e, src[away], slot[away]] = i[away]
            home[e, m[mine] - e * block] = i[mine]
            home[src[away], m[away] - src[away] * block] = cap + e * c + slot[away]
        sent += int(away.sum())
    arrays = dict(send=send, take=take, ok=ok)
    if back:
        arrays.update(back=ret, home=home)
    return {prefix + k: v for k, v in arrays.items()}, sent


def _gather(blk, recv, ex, prefix):
    """A part's items: its own device's rows and those received (`_exchange`)."""
    return jnp.concatenate([blk, recv.reshape(-1, blk.shape[1])])[ex[prefix + "take"]]


def _exchange(blks, ex, prefixes, axis):
    """The rows of several row blocks that other parts need, sent by one all_to_all:
    [received rows [D, C, w] of each block]."""
    out = [b[ex[q + "send"]] for b, q in zip(blks, prefixes)]
    widths = np.cumsum([o.shape[1] for o in out])[:-1]
    recv = jax.lax.all_to_all(jnp.concatenate(out, 1), axis, 0, 0)
    return jnp.split(recv, widths, 1)


def _stack(tables):
    """Per-part topologies -> one of [D, ...] arrays (rows padded with -1 where the parts'
    sizes differ: edges, the node-face table's width)."""

    def stack(*arrs):
        arrs = [np.asarray(a) for a in arrs]
        shape = np.max([a.shape for a in arrs], 0)
        full = np.full((len(arrs), *shape), -1 if arrs[0].dtype.kind == "i" else 0, arrs[0].dtype)
        for i, a in enumerate(arrs):
            full[(i, *[slice(0, s) for s in a.shape])] = a
        return full

    return jax.tree.map(stack, *tables)


def detect(p: ShardedPlan, slave_points, master_points, self_points=False) -> Contacts:
    """The sharded detection (called by arraycontact_jax.detect / detect_self, under jit)."""
    n_dev, axis = p.n_devices, p.axis
    b_s, b_m = p.blocks
    n_pts = p.master.points.shape[0]
    if master_points.ndim != 2 or master_points.shape != (n_pts, 3):
        raise ValueError(
            f"master_points must have shape {(n_pts, 3)} (the plan's master), got "
            f"{master_points.shape}"
        )
    if not self_points and (slave_points.ndim != 2 or slave_points.shape[1] != 3):
        raise ValueError(f"slave_points must have shape [n, 3], got {slave_points.shape}")
    if not self_points and slave_points.shape[0] != p.n_slaves:
        raise ValueError(
            f"slave_points must have the plan's {p.n_slaves} rows (its partition), got "
            f"{slave_points.shape[0]}"
        )
    xm = jnp.pad(master_points, ((0, n_dev * b_m - n_pts), (0, 0)))
    if self_points:
        xs = jnp.zeros((n_dev * b_s, 3), master_points.dtype)  # the slaves are master nodes
    else:
        xs = jnp.pad(slave_points, ((0, n_dev * b_s - p.n_slaves), (0, 0)))
    self_contact = p.local.static.self_contact
    spec = P(axis)
    # Rows that are no multiple of the devices come replicated (JAX shards rows only in equal
    # blocks): each part takes its items from them, and only the other side is exchanged.
    everywhere, rep_m = p.replicated
    rep_s = everywhere and not self_contact  # (self-contact's slaves are master points)

    def body(topo, ex, s_in, m_in):
        topo = jax.tree_util.tree_map(lambda a: a[0], topo)
        ex = jax.tree_util.tree_map(lambda a: a[0], ex)
        me = jax.lax.axis_index(axis)
        m_blk = jax.lax.dynamic_slice_in_dim(m_in, me * b_m, b_m) if rep_m else m_in
        s_blk = jax.lax.dynamic_slice_in_dim(s_in, me * b_s, b_s) if rep_s else s_in
        sides = [("m_", m_blk)] if not rep_m else []
        sides += [("s_", s_blk)] if not (self_contact or rep_s) else []
        recv = {}
        if sides:
            got = _exchange([b for _, b in sides], ex, [q for q, _ in sides], axis)
            recv = {q: r for (q, _), r in zip(sides, got)}
        ref_m = ex["m_ref"].astype(m_blk.dtype)
        if rep_m:
            x_m = m_in[jnp.maximum(ex["node_ids"], 0)]
        else:
            x_m = _gather(m_blk, recv["m_"], ex, "m_")
        x_m = jnp.where(ex["m_ok"][:, None], x_m, ex["m_pad"].astype(x_m.dtype))
        if self_contact:
            s = x_m[topo.slave_nodes]
        else:
            s = s_in[ex["s_rows"]] if rep_s else _gather(s_blk, recv["s_"], ex, "s_")
            s = jnp.where(ex["s_ok"][:, None], s, ex["nowhere"].astype(s.dtype))
        fields, counts = local_detect(p.local, topo, s, x_m)
        # Global ids of the answer.
        face = jnp.where(fields["face"] >= 0, ex["face_ids"][jnp.maximum(fields["face"], 0)], -1)
        node = fields["master_node"]
        node = jnp.where(node >= 0, ex["node_ids"][jnp.maximum(node, 0)], -1)
        answer = {k: fields[k] for k in _FIELDS + (("finer",) if self_contact else ())}
        answer.update(face=face, master_node=node)
        # Motion since the plan (halo check): the slaves this device holds, its master rows.
        dm = jnp.where(ex["m_used"], _norm(jax.lax.stop_gradient(m_blk) - ref_m), 0)
        motion = [jnp.max(dm)]
        if not self_contact:  # (a self-contact slave's motion is its node's)
            ds = _norm(jax.lax.stop_gradient(s_blk) - ex["s_ref"].astype(s_blk.dtype))
            motion.append(jnp.max(jnp.where(ex["s_used"], ds, 0)))
        counts["halo_motion"] = jnp.stack(motion)
        blk, counts = (_everywhere if everywhere else _home)(answer, ex, axis, counts)
        motion = counts.pop("halo_motion")
        counts["halo_motion"] = motion[-1] + p.lebesgue * motion[0]
        return blk, counts

    fields, counts = jax.shard_map(
        body,
        mesh=p.mesh,
        in_specs=(spec, spec, P() if rep_s else spec, P() if rep_m else spec),
        out_specs=(P() if everywhere else spec, P()),
        # The one-device stages build their while_loop carries from constants; the counts
        # are every device's largest (sent to all), hence the same on every device.
        check_vma=False,
    )(p.local.topology, p.exchange, xs, xm)
    n = p.n_slaves
    fields = {k: v[:n] for k, v in fields.items()}
    slave_ids = (
        jnp.asarray(p.master.nodes.astype(np.int32))
        if self_contact
        else jnp.arange(n, dtype=jnp.int32)
    )
    return contacts_of(fields, slave_ids, p, counts, p.capacity)


def _norm(v):
    return jnp.sqrt(jnp.sum(v * v, -1))


def _packed(fields, rows, counts, dt):
    """[R, w] rows of every field (rows: an index into their [cap, ...] arrays, or None:
    all), int and bool values as floats split in two 16-bit halves (exact in float32, whose
    integers end at 2^24), then the counts in extra rows of the same width: ([R + extra, w],
    R)."""

    def halves(a):
        a = a.astype(jnp.int32)
        return [(a // 65536).astype(dt), (a % 65536).astype(dt)]

    cols = []
    for k in sorted(fields):
        a = fields[k] if rows is None else fields[k][rows]
        a = a.reshape(a.shape[0], -1)
        cols += [a.astype(dt)] if a.dtype.kind == "f" else halves(a)
    vals = jnp.concatenate(cols, -1)
    r, w = vals.shape
    parts = [jnp.asarray(counts[k]).reshape(-1) for k in sorted(counts)]
    flat = jnp.concatenate(
        [h for a in parts for h in (halves(a) if a.dtype.kind in "iu" else [a.astype(dt)])]
    )
    extra = -(-flat.shape[0] // w)
    flat = jnp.pad(flat, (0, extra * w - flat.shape[0])).reshape(extra, w)
    return jnp.concatenate([vals, flat]), r


def _counts_of(got, counts):
    """The largest over devices of `counts` from their packed rows got [D, ...] (`_packed`)."""
    out, col = {}, 0
    for k in sorted(counts):
        a = jnp.asarray(counts[k])
        m = a.size
        if a.dtype.kind in "iu":
            v = got[:, col : col + m].astype(a.dtype) * 65536
            v = v + got[:, col + m : col + 2 * m].astype(a.dtype)
            col += 2 * m
        else:
            v = got[:, col : col + m].astype(a.dtype)
            col += m
        out[k] = jnp.max(v, 0).reshape(a.shape)
    return out


def _fields_of(rows, fields):
    """The fields (dtypes and row shapes as `fields`) from packed rows [R, w] (`_packed`)."""
    out, col = {}, 0
    for k in sorted(fields):
        a = fields[k]
        m = int(np.prod(a.shape[1:], dtype=int))
        if a.dtype.kind == "f":
            v = rows[:, col : col + m]
            col += m
        else:
            hi = rows[:, col : col + m].astype(jnp.int32)
            v = hi * 65536 + rows[:, col + m : col + 2 * m].astype(jnp.int32)
            col += 2 * m
        out[k] = v.reshape((rows.shape[0],) + a.shape[1:]).astype(a.dtype)
    return out


def _float_dtype(fields):
    return next(v.dtype for v in fields.values() if v.dtype.kind == "f")


def _home(fields, ex, axis, counts):
    """A part's answer (fields: a dict of [cap, ...] arrays) back to the devices holding its
    slaves' rows: the same dict of [b_s, ...] blocks (`_gather` reversed), and the largest of
    every device's `counts` (a dict of int or float arrays).

    Only the rows another device holds travel: packed into one float array with the counts
    as extra rows (`_packed`), one all_to_all (no collective of their own: each collective
    waits for every device, so each one costs the devices' skew). Each field then reads its
    rows from its own part's array or the received ones in one gather. (Packing every row of
    the part, as this did first, cost a detection of 2^20 slaves a device several passes
    over 80 bytes a row.)"""
    back = ex["s_back"]  # [D, C]: the part's rows each device gets
    d, c = back.shape
    send, _ = _packed(fields, back.reshape(-1), counts, _float_dtype(fields))
    w = send.shape[-1]
    extra = send[d * c :]
    send = jnp.concatenate(
        [send[: d * c].reshape(d, c, w), jnp.broadcast_to(extra, (d,) + extra.shape)], 1
    )
    recv = jax.lax.all_to_all(send, axis, 0, 0)
    out_counts = _counts_of(recv[:, c:].reshape(d, -1), counts)
    got = _fields_of(recv[:, :c].reshape(d * c, w), fields)
    return {k: jnp.concatenate([fields[k], got[k]])[ex["s_home"]] for k in fields}, out_counts


def _everywhere(fields, ex, axis, counts):
    """As `_home`, for a plan whose rows are not a whole number of blocks a device (JAX
    shards an array's rows only in equal blocks): every row on every device (replicated), by
    one all_gather of each part's packed answer, where XLA made one all_gather a field of the
    sharded blocks' result. `ex["s_all"]` [rows]: each row's slot in the gathered parts."""
    send, r = _packed(fields, None, counts, _float_dtype(fields))
    got = jax.lax.all_gather(send, axis)  # [D, r + extra, w]
    out_counts = _counts_of(got[:, r:].reshape(got.shape[0], -1), counts)
    rows = got[:, :r].reshape(-1, got.shape[-1])[ex["s_all"]]
    return _fields_of(rows, fields), out_counts
