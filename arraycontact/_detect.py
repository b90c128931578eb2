"""`detect`: the pipeline of DESIGN section 2 behind one call, and the NumPy back end.

`build_grids` (stage 2) and `run_stages` (stages 3-5) are written against an array namespace;
the NumPy back end calls them eagerly (capacities sized from the data, grids built once, slaves
in chunks to bound memory), the JAX back end under `jax.jit` with planned capacities.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np

from . import _closest_node, _grid, _projection, _select, _sweep
from ._contacts import Contacts, Counts, Feature, Status, SweptContacts
from ._elements import get_element
from ._grid import FACING_TOL
from ._normals import face_normal
from ._prepare import Prepared, default_d_max, ordered, prepare, slaves_in_box
from ._surface import (
    Surface,
    _dot,
    face_boxes,
    face_normals,
    mesh_sizes,
    node_normals,
    normal_boxes,
    validate_points,
)
from ._xp import expand, norm, segment_min

MODES = ("exact", "node")
BACKENDS = ("numpy", "jax", "warp")
#: Equal distances within TIE_RTOL * longest master edge are ties (see _select). In float32 the
#: band stays above rounding in distance differences and, with that rounding, under the 1e-5
#: of the longest edge promised for the distance (a tie may pick a face that far from the
#: closest).
TIE_RTOL = {np.dtype(np.float64): 1e-10, np.dtype(np.float32): 5e-6}
#: KKT tolerance of the Newton projections, in natural coordinates. For a slave on a face or
#: within about 1e-9 edges of it the distance is first order in the error of xi: float64's
#: 1e-10 left distance errors up to 2.4e-10 of the longest edge there (tri6; quad4 1.7e-11),
#: above the 1e-12 promised (tests/test_detect.py, slaves on and just off the surface). At
#: 1e-12 they are rounding (1e-16), and no projection ran out of iterations; each projection
#: works in its face's frame, so rounding stays far below it. float32's 1e-4 likewise left up
#: to 1.7e-4 of the longest edge there (tri6; quad4 5e-5) against the 1e-5 promised; a last
#: Newton step near the face (closest_point_face) meets it for 1-5 % of the detection on an
#: H200, where a tolerance of 3e-6 cost tri6 75 % and quad9 22 %.
KKT_TOL = {np.dtype(np.float64): 1e-12, np.dtype(np.float32): 1e-4}
ITERATIONS = {"quad4": 12, "tri6": 20, "quad8": 20, "quad9": 20}
#: Self-contact: local mesh sizes within this relative difference are "as fine" (seed 000
#: section 3, item 5; the `finer` flag).
SIZE_RTOL = 1e-4
#: Self-contact: at most this many faces around the closest obtuse node are projected for the
#: first bound of the face search (any admissible face bounds the answer: a subset suffices).
BOUND_FACES = 12


@dataclass(frozen=True)
class Static:
    """What shapes and code paths depend on (hashable: a jit static argument)."""

    element: str
    mode: str
    node_levels: tuple  # the trees' level sizes (static shapes)
    face_levels: tuple
    iterations: int
    passing_by: bool  # node mode on an open master: the boundary test of eqs. (12)-(13)
    self_contact: bool = False  # the slaves are the master's own nodes (detect_self)
    bound_faces: int = 0  # self-contact: faces around the closest node giving the first bound

    @classmethod
    def of(cls, master: Surface, mode: str, prep: Prepared, self_contact=False) -> "Static":
        """The static configuration of detecting on `master` in `mode` with `prep`'s trees."""
        return cls(
            element=master.element.name,
            mode=mode,
            node_levels=prep.node_levels,
            face_levels=prep.face_levels,
            iterations=ITERATIONS.get(master.element.name, 0),
            passing_by=mode == "node" and not master.closed,
            self_contact=self_contact,
            bound_faces=min(int(np.diff(master.node_faces[0]).max()), BOUND_FACES)
            if self_contact
            else 0,
        )


class Master(NamedTuple):
    """The master as the stages read it: connectivity (int32, global ids, fixed for a plan's
    life) and geometry in the local frame (float, from the coordinates of the call; None in a
    plan's topology, filled under jit by `master_geometry`). One definition for the NumPy
    back end (host arrays), the JAX plans (a pytree of device arrays; a sharded plan's leaves
    are stacked [D, ...]) and the JAX detection. n: master points, F: faces, k: nodes a face,
    E: edges; N', F': the nodes and faces in the trees."""

    faces: Any  # [F, k] node ids
    node_ids: Any  # [N'] the node tree's items, in Morton order
    face_ids: Any  # [F'] the face tree's items, in Morton order
    face_edges: Any  # [F, edges a face] edge ids
    edge_faces: Any  # [E, 2] the faces of each edge (-1: a boundary edge)
    nf_offsets: Any  # [n + 1] node -> faces (CSR offsets into nf_ids)
    nf_ids: Any  # [sum of node degrees] face ids
    prev_node: Any  # [n] boundary nodes: the neighbours along the boundary (-1 elsewhere)
    next_node: Any
    prev_face: Any  # [n] and the boundary faces between them
    next_face: Any
    on_boundary: Any  # [n] bool
    slave_nodes: Any = None  # JAX plans, self-contact: [slaves] the slaves' node ids
    node_groups: Any = None  # the trees' slots per level (_grid.grouping; None: consecutive)
    face_groups: Any = None
    node_faces: Any = None  # JAX plans: [n, w] node -> faces padded with -1 (vertex normals)
    node_live: Any = None  # sharded plans: [N'] false on padding items (empty boxes)
    face_live: Any = None  # [F']
    nodes_x: Any = None  # [n, 3] coordinates in the local frame
    node_normals: Any = None  # [n, 3] pseudo-normals
    prev_normal: Any = None  # [n, 3] boundary nodes: the normals of prev_face, next_face
    next_normal: Any = None
    concave: Any = None  # [n] bool: the boundary turns inwards at the node


class Scalars(NamedTuple):
    """A scene's constants (floats, or 0-d arrays of the detection's dtype under jit)."""

    d_max: Any  # the search distance
    tie: Any  # equal distances within this are ties (TIE_RTOL * longest edge)
    slack: Any  # rounding slack of the pruning tests (never of the answer)
    tol: Any  # KKT tolerance of the projections, natural coordinates


class Grids(NamedTuple):
    """Stage 2's trees (`_grid.Tree`) and, for self-contact, the local mesh sizes."""

    node: Any
    face: Any = None  # exact mode
    sizes: Any = None  # self-contact: (per face [F], per node [n]) (mesh_sizes)


def master_topology(master: Surface, prep: Prepared) -> Master:
    """Connectivity and topology of the master, int32 arrays keyed by global ids; the nodes and
    faces that take part are prep's."""
    offsets, ids = master.node_faces
    prev_node, next_node, prev_face, next_face, on = _select.boundary_topology(master)
    ints = [
        master.faces,
        prep.node_ids,
        prep.face_ids,
        master.face_edges,
        master.edge_faces,
        offsets,
        ids,
        prev_node,
        next_node,
        prev_face,
        next_face,
    ]
    return Master(
        *(np.asarray(v).astype(np.int32) for v in ints),
        on_boundary=on,
        node_groups=prep.node_groups,
        face_groups=prep.face_groups,
    )


def master_geometry(xp, element, topo: Master, nodes_x, normals=None) -> Master:
    """`topo` with what detection needs from the master's coordinates `nodes_x` (local frame):
    node pseudo-normals (or the given `normals`), boundary normals. Computed on the host once
    by the NumPy back end, inside the jitted step from moving coordinates by the JAX
    plan/detect."""
    element = get_element(element)
    if normals is None:
        normals = node_normals(element, topo.faces, nodes_x, xp)
    xe = nodes_x[topo.faces]
    prev_n, next_n, concave = _select.boundary_geometry(
        xp,
        nodes_x,
        topo.prev_node,
        topo.next_node,
        topo.prev_face,
        topo.next_face,
        face_normals(element, xe, xp),
    )
    return topo._replace(
        nodes_x=nodes_x,
        node_normals=normals,
        prev_normal=prev_n,
        next_normal=next_n,
        concave=concave,
    )


def master_arrays(master: Surface, prep: Prepared, dtype) -> Master:
    """Master topology and geometry in the local frame (float `dtype`), on the host. The node
    normals are the Surface's cached ones (they do not depend on the frame)."""
    topo = master_topology(master, prep)
    prev_n, next_n, concave = _select.boundary_geometry(
        np,
        master.points,
        topo.prev_node,
        topo.next_node,
        topo.prev_face,
        topo.next_face,
        master.face_normals,
    )
    return topo._replace(
        nodes_x=(master.points - prep.origin).astype(dtype),
        node_normals=master.node_normals.astype(dtype),
        prev_normal=prev_n.astype(dtype),
        next_normal=next_n.astype(dtype),
        concave=concave,
    )


def scalars(prep: Prepared, master: Surface, dtype, longest_edge=None) -> Scalars:
    eps = float(np.finfo(dtype).eps)
    longest = master.longest_edge if longest_edge is None else longest_edge
    tie = TIE_RTOL[np.dtype(dtype)] * longest
    return Scalars(
        d_max=prep.d_max,
        tie=tie,
        slack=tie + 16 * eps * (prep.extent + prep.d_max + prep.r_max),
        tol=KKT_TOL[np.dtype(dtype)],
    )


class _Laps:
    """Wall time per stage, summed over chunks (eager back ends only)."""

    def __init__(self):
        self.times, self.t = {}, time.perf_counter()

    def __call__(self, name):
        t = time.perf_counter()
        self.times[name] = self.times.get(name, 0.0) + t - self.t
        self.t = t


def build_grids(xp, st: Static, m: Master) -> Grids:
    """Stage 2: the trees of the master nodes (points) and, in exact mode, of the faces (their
    boxes), over node_ids and face_ids in the Morton order `prepare` gave them. Self-contact:
    with the normal boxes of the items (a node's pseudo-normal, a face's normal_boxes) and
    the local mesh sizes (mesh_sizes)."""
    element = get_element(st.element)
    x = m.nodes_x[m.node_ids]
    nodes_n = None
    if st.self_contact:
        n = m.node_normals[m.node_ids]
        nodes_n = (n, n)
    lo, hi = _inert(xp, m.node_live, x, x)
    grids = Grids(_grid.build(xp, m.node_ids, lo, hi, x, nodes_n, m.node_groups))
    if st.mode == "exact":
        xe = m.nodes_x[m.faces[m.face_ids]]
        lo, hi = _inert(xp, m.face_live, *face_boxes(element, xe, xp))
        faces_n = normal_boxes(element, xe, xp) if st.self_contact else None
        face = _grid.build(xp, m.face_ids, lo, hi, xe[:, 0], faces_n, m.face_groups)
        grids = grids._replace(face=face)
    if st.self_contact:
        grids = grids._replace(sizes=mesh_sizes(element, m.faces, m.nodes_x, xp))
    return grids


def _inert(xp, live, lo, hi):
    """Boxes of the items in tree order; where `live` [n] is false (a sharded plan's padding)
    an empty box (lo > hi), which no search enters and no parent box grows by."""
    if live is None:
        return lo, hi
    big = _grid._empty(lo.dtype)
    return xp.where(live[:, None], lo, big), xp.where(live[:, None], hi, -big)


def run_stages(
    xp,
    st: Static,
    sc: Scalars,
    m: Master,
    grids: Grids,
    slave_x,
    capacity: dict,
    lap=None,
    search=None,
    slave_ids=None,
):
    """Stages 3-5 for slaves `slave_x` (local frame). Returns per-slave outputs and counts.
    search: what runs the tree searches of stages 3-4 (`closest_node`, `candidate_faces`):
    by default the level-by-level queries of _closest_node and _projection (NumPy); the JAX
    back end passes its per-slave scans (arraycontact_jax._grid). slave_ids (self-contact):
    the slaves' node ids on the master."""
    lap = lap or (lambda name: None)
    node_search = search.closest_node if search else _closest_node.closest_node
    face_search = search.candidate_faces if search else _projection.candidate_faces
    element = get_element(st.element)
    n = slave_x.shape[0]
    tie = sc.tie
    node_grid = grids.node
    own = None
    if st.self_contact:
        own = (slave_ids, m.node_normals[slave_ids], m.node_normals)
    # 3. closest node
    node, dn, counts = node_search(
        xp,
        node_grid,
        m.nodes_x,
        slave_x,
        d_max=sc.d_max,
        tie=tie,
        slack=sc.slack,
        capacity=capacity or None,
        self_contact=own,
    )
    lap("closest_node")
    # 4. candidate faces and projections
    if st.mode == "exact":
        face_grid = grids.face
        if own is None:
            rho = xp.minimum(dn, sc.d_max) + sc.slack
        else:
            rho = self_reach(xp, st, sc, m, own, slave_x, node)
        kw = dict(slack=sc.slack, capacity=capacity or None)
        measure = getattr(search, "candidate_distances", None)
        if own is None and element.name == "tri3" and measure is not None:
            slave, face, valid, d, n_pairs = measure(
                xp, face_grid, slave_x, rho, m.nodes_x, m.faces, **kw
            )
        else:
            slave, face, valid, n_pairs = face_search(
                xp, face_grid, slave_x, rho, normal=None if own is None else own[1], **kw
            )
            measure = None
        counts.update(n_pairs)
        # (the JAX search's pairs: K slots a slave, in slave order)
        slots = slave.shape[0] // max(n, 1) if getattr(search, "SLOTS", False) else None
        if measure is not None:
            # Triangles, the JAX search: it measured every slot's distance, so only the slot
            # the tie rule picks is projected (K = 12-36 slots a slave had been, 5-8 of them
            # real: the projections and their reductions took 1.6 ms at 2^20 on an H100).
            pick, has = _select.select_closest(xp, n, slave, face, valid, d, tie, slots)
            slave, face, valid, slots = xp.arange(n, dtype=np.int32), face[pick], has, 1
    else:
        # Node mode: the faces attached to the closest node (seed 000 section 2.2).
        has_node = node >= 0
        nd = xp.maximum(node, 0)
        deg = xp.where(has_node, m.nf_offsets[nd + 1] - m.nf_offsets[nd], 0)
        seg, rank, valid, n_att = expand(xp, deg, capacity.get("attached"))
        slave = seg
        face = m.nf_ids[xp.where(valid, m.nf_offsets[nd[seg]] + rank, 0)]
        counts.update(attached=n_att)
        slots = None
    lap("candidates")
    args = (xp, element, slave_x, m.nodes_x, m.faces, slave, face)
    if element.name != "tri3":
        # Curved faces' projections are iterative: only valid pairs are projected and, in
        # exact mode, only those that may hold the closest point (within the tie band,
        # rounding included). (Self-contact and node mode keep every valid pair: a nearer
        # pair may turn out inadmissible, a farther one be the face the node projects on.)
        if st.mode == "exact" and own is None:
            lo, hi = _projection.distance_bounds(*args)
            best = segment_min(xp, xp.where(valid, hi, np.inf), slave, n, slots=slots)
            valid = valid & (lo <= best[slave] + 2 * sc.slack)
        # (JAX: projected as many slaves' worth of pairs at a time, about 3 rounds on rough
        # quad4 surfaces, whose slaves keep 2.7 of their 8 candidate slots)
        room = max(n, 1)
        projected = _projection.project_kept(
            *args, valid, room, iterations=st.iterations, tol=sc.tol
        )
    else:
        projected = _projection.project(*args, iterations=st.iterations, tol=sc.tol)
    xi, point, diff, feature, local, conv = projected
    if own is not None:
        valid = valid & _admissible(xp, element, m, own, slave, face, xi, st.mode)
    lap("projection")
    # 5. selection and classification
    dist = norm(xp, diff)
    status = xp.zeros(n, dtype=np.int32) + int(Status.OK)
    if st.mode == "exact":
        pick, has = _select.select_closest(xp, n, slave, face, valid, dist, tie, slots)
        active = has & (dist[pick] <= sc.d_max)
    else:
        onface = valid & (feature == int(Feature.FACE))
        pick_p, has_p = _select.select_closest(xp, n, slave, face, onface, dist, tie)
        pick_b, has_b = _select.select_closest(xp, n, slave, face, valid, dist, tie)
        pick = xp.where(has_p, pick_p, pick_b)
        blind = ~has_p & has_b
        if st.passing_by:
            inside = _select.proximal(
                xp,
                slave_x,
                nd,
                m.nodes_x,
                m.prev_node,
                m.next_node,
                m.prev_normal,
                m.next_normal,
                m.concave,
            )
            passing = blind & m.on_boundary[nd] & ~inside
        else:
            passing = blind & False
        active = (has_p | blind) & ~passing
        status = xp.where(blind, int(Status.BLIND_SPOT), status)
        status = xp.where(passing, int(Status.PASSING_BY), status)
        if own is not None:
            # Seed 000 section 3, item 5: the node with the coarser local mesh is the
            # master; as fine, the element stands where a projection exists, and else the
            # smaller node id is the slave.
            h_node = grids.sizes[1]
            h_i, h_j = h_node[slave_ids], h_node[nd]
            coarser = h_i > h_j * (1 + SIZE_RTOL)
            finer = h_i * (1 + SIZE_RTOL) < h_j
            master_side = active & (coarser | (~finer & ~has_p & (slave_ids > nd)))
            active = active & ~master_side
            status = xp.where(master_side, int(Status.MASTER_SIDE), status)
    face_out = face[pick]
    gap, dist_out, normal = _select.classify(
        xp,
        element,
        m.nodes_x,
        m.faces,
        m.face_edges,
        m.edge_faces,
        m.node_normals,
        face_out,
        xi[pick],
        diff[pick],
        feature[pick],
        local[pick],
        tie,
    )
    status = xp.where(active & ~conv[pick], int(Status.NOT_CONVERGED), status)
    kept = active | (status == int(Status.PASSING_BY)) | (status == int(Status.MASTER_SIDE))
    status = xp.where(kept, status, int(Status.OUT_OF_RANGE))
    lap("select")
    if own is not None:
        h_face, h_node = grids.sizes
        out_finer = active & (h_node[slave_ids] <= h_face[face_out] * (1 + SIZE_RTOL))
    out = dict(
        active=active,
        face=face_out,
        xi=xi[pick],
        point=point[pick],
        gap=gap,
        distance=dist_out,
        normal=normal,
        feature=feature[pick],
        master_node=node,
        status=status,
        local=local[pick],
    )
    if own is not None:
        out["finer"] = out_finer
    return out, counts


def self_reach(xp, st: Static, sc: Scalars, m: Master, own, slave_x, node):
    """Self-contact's first reach of the face search. The closest node bounds nothing here (it
    need not lie on a face that counts), but any admissible face does: the faces around the
    closest obtuse node (up to st.bound_faces of them), projected and tested as the search
    will, give min(d_max, the nearest admissible one) + slack. On a fold that faces itself
    this keeps the candidates to the faces near the answer (JAX: the K slots a slave)."""
    element = get_element(st.element)
    n = slave_x.shape[0]
    k = st.bound_faces
    nd = xp.maximum(node, 0)
    start = m.nf_offsets[nd]
    deg = xp.where(node >= 0, m.nf_offsets[nd + 1] - start, 0)
    rank = xp.arange(k, dtype=start.dtype)[None, :]
    valid = (rank < deg[:, None]).reshape(-1)
    face = m.nf_ids[xp.where(valid, (start[:, None] + rank).reshape(-1), 0)]
    slave = xp.repeat(xp.arange(n), k)
    xi, _, diff, _, _, _ = _projection.project(
        xp,
        element,
        slave_x,
        m.nodes_x,
        m.faces,
        slave,
        face,
        iterations=st.iterations,
        tol=sc.tol,
    )
    ok = valid & _admissible(xp, element, m, own, slave, face, xi, "exact")
    d = xp.where(ok, norm(xp, diff), np.inf).reshape(n, k)
    return xp.minimum(xp.min(d, 1), sc.d_max) + sc.slack


def _admissible(xp, element, m, own, slave, face, xi, mode):
    """Self-contact (seed 000 section 3, item 4, applied to faces): a candidate face counts
    when it does not hold the slave's node and its normal at the closest point faces the
    slave's normal (n_i . n_f(xi) < -FACING_TOL; node mode keeps the faces of the obtuse
    closest node as they are, only those holding the slave's node drop)."""
    ids, normal, _ = own
    fn = m.faces[face]
    ok = ~xp.any(fn == ids[slave][:, None], -1)
    if mode == "exact":
        nf = face_normal(element, m.nodes_x[fn], xi, xp)
        ok = ok & (_dot(normal[slave], nf) < -FACING_TOL)
    return ok


def _slaves(slave):
    if isinstance(slave, Surface):
        return slave.points[slave.nodes], slave.nodes
    x = validate_points(slave, "slave", copy=False)
    return x, np.arange(len(x))


def _empty(n, ids, d_max, counts=None, timings=None, **answered) -> Contacts:
    return Contacts(
        active=np.zeros(n, bool),
        face=np.full(n, -1, np.int64),
        xi=np.full((n, 2), np.nan),
        point=np.full((n, 3), np.nan),
        gap=np.full(n, np.nan),
        distance=np.full(n, np.nan),
        normal=np.full((n, 3), np.nan),
        feature=np.full(n, int(Feature.NONE), np.int32),
        master_node=np.full(n, -1, np.int64),
        status=np.full(n, int(Status.OUT_OF_RANGE), np.int32),
        slave_ids=np.asarray(ids),
        d_max=float(d_max),
        counts=counts or Counts(),
        timings=timings or {},
        **answered,
    )


#: The fields of a row that only active (or passing-by) slaves fill.
_KEPT = ("face", "xi", "point", "gap", "distance", "normal", "feature")


def assemble(
    n, ids, rows, origin, out, d_max, counts, timings, answered, blanked=False
) -> Contacts:
    """Scatter the outputs of the slaves in the box (their rows; points in the local frame
    at `origin`) into a full Contacts record (global frame, float64). blanked: the back end
    wrote the empty row's values where a slave has no answer (Warp's kernels do)."""
    c = _empty(n, ids, d_max)
    active = np.asarray(out["active"], bool)
    status = np.asarray(out["status"])
    every = len(rows) == n  # every slave in the box (rows = 0 .. n - 1): no scatter
    at = slice(None) if every else rows
    c.active[at] = active
    c.status[at] = status
    c.master_node[at] = np.asarray(out["master_node"])
    keep = None if blanked else active | (status == int(Status.PASSING_BY))
    for k in _KEPT:
        v = np.asarray(out[k])
        dst = getattr(c, k)
        if keep is None:  # one copy a field (a scatter where some slaves are out of the box)
            dst[at] = v
        elif every:
            np.copyto(dst, v, where=keep.reshape((n,) + (1,) * (v.ndim - 1)))
        else:
            dst[rows[keep]] = v[keep]
        if k == "point":
            dst += origin  # NaN rows stay NaN
    if "finer" in out:
        finer = np.zeros(n, bool)
        finer[rows] = np.asarray(out["finer"], bool)
        answered = {**answered, "finer": finer}
    return Contacts(**{**c.__dict__, "counts": counts, "timings": timings, **answered})


def _run_numpy(slave_x, master, prep, st, dtype, chunk=1 << 15, slave_ids=None):
    m = master_arrays(master, prep, dtype)
    sc = scalars(prep, master, dtype)
    x = (slave_x[prep.slave_rows] - prep.origin).astype(dtype)
    ids = None if slave_ids is None else slave_ids[prep.slave_rows].astype(np.int32)
    lap = _Laps()
    grids = build_grids(np, st, m)
    lap("grid")
    outs, totals = [], {}
    for i in range(0, len(x), chunk):
        part = None if ids is None else ids[i : i + chunk]
        o, cnt = run_stages(np, st, sc, m, grids, x[i : i + chunk], {}, lap, slave_ids=part)
        outs.append(o)
        for k, v in cnt.items():
            totals[k] = totals.get(k, 0) + int(v)
    out = {k: np.concatenate([o[k] for o in outs]) for k in outs[0]}
    return out, totals, {k: None for k in totals}, lap.times


def check_options(master, mode, d_max, displacement, dtype, longest_edge=None):
    """Validated (d_max, dtype) of a detection, or a ValueError naming the bad option.
    longest_edge: the master's, when the caller has it (made on a device)."""
    if not isinstance(master, Surface):
        raise ValueError("master must be an arraycontact.Surface")
    if mode not in MODES:
        raise ValueError(f"mode must be one of {MODES}, got {mode!r}")
    dtype = np.dtype(np.float64 if dtype is None else dtype)
    if dtype not in TIE_RTOL:
        raise ValueError(f"dtype must be float32 or float64, got {dtype}")
    if d_max is None:
        return default_d_max(master, displacement, longest_edge), dtype
    if not (np.isscalar(d_max) and np.isfinite(d_max) and d_max > 0):
        raise ValueError(f"d_max must be a positive finite number, got {d_max}")
    return float(d_max), dtype


def detect(
    slave, master, *, backend="auto", mode="exact", d_max=None, displacement=None, dtype=None
) -> Contacts:
    """Closest point on `master` of every slave node.

    slave: [n, 3] coordinates or a Surface (its nodes are the slaves). master: a Surface.
    mode: "exact" (the exact closest point over faces, edges and vertices within d_max) or
    "node" (seed 000: closest node, projections on its faces, blind spots, passing-by nodes).
    d_max: search radius; default: the longest master edge, raised to 2 max|displacement|.
    backend: "auto" (default: Warp, on a visible CUDA GPU or else on the CPU, when it imports;
    else NumPy), "numpy", "jax" or "warp". The answer's `backend`, `device` and `dtype` say
    which ran. dtype: float64 (default, on every back end) or float32 for the computation
    (inputs are always read in float64 and moved to a local frame first)."""
    t0 = time.perf_counter()
    backend = _backend(backend)
    _host_tables(master, backend)
    longest = _longest_edge(master, backend, d_max)
    d_max, dtype = check_options(master, mode, d_max, displacement, dtype, longest)
    slave_x, ids = _slaves(slave)
    return _detect(slave_x, ids, master, backend, mode, d_max, dtype, None, t0)


def detect_self(surface, *, backend="auto", mode="exact", d_max=None, dtype=None) -> Contacts:
    """Self-contact and contact between the bodies of one surface (seed 000 section 3): every
    node used by the faces is a slave, every face a master; rows as in `detect` with the
    surface as slave (`slave_ids` are the node ids).

    Exact mode: for node i with pseudo-normal n_i (Surface.node_normals), a face is admissible
    when it does not hold node i and its normal at its own closest point to x_i faces the
    node, n_i . n_f(xi*) < 0; the answer is the closest admissible face within d_max (feature,
    gap, normal and ties as in `detect`). `master_node` is the closest node j != i with
    n_i . n_j <= 0 (item 4). Both tests take a margin of FACING_TOL = 1e-6 (unit normals), so
    that perpendicular normals, whose dot product is rounding noise, are decided alike
    everywhere: a perpendicular face does not face the node, a perpendicular node is obtuse
    (an element whose Jacobian vanishes at the closest point has no normal there: such
    inverted elements are outside this rule).

    Node mode, seed 000 as published: that closest node, the projections on its faces, and
    the pair's master side chosen by local mesh density (item 5): a node whose mesh is
    coarser than its closest node's, or as fine with no projection and the larger id, gets
    status MASTER_SIDE (the element is the other node's row). `finer` flags the rows whose
    node's local mesh (mesh_sizes: the mean edge length of the faces around it) is at least
    as fine as the face's: keep those to have one node-to-segment element per pair, from the
    finer side.

    Thin structures (seed 000 Fig. 11): the back side of a plate of thickness t lies at
    distance t behind a node, facing away from the node's side, so its normal is opposite to
    the node's and it is admissible: it is reported (with gap -t, as a penetration) whenever
    t <= d_max and nothing closer is. Nothing local tells it from a real contact partner at
    that distance. Keep d_max below the smallest thickness (seed 000 section 3 limits it by
    twice the thickness for its node-to-node test; with exact closest points the back side is
    already at t)."""
    t0 = time.perf_counter()
    if not isinstance(surface, Surface):
        raise ValueError("surface must be an arraycontact.Surface")
    backend = _backend(backend)
    _host_tables(surface, backend)
    longest = _longest_edge(surface, backend, d_max)
    d_max, dtype = check_options(surface, mode, d_max, None, dtype, longest)
    ids = surface.nodes
    return _detect(surface.points[ids], ids, surface, backend, mode, d_max, dtype, ids, t0)


def _backend(backend):
    from ._backends import resolve

    if backend not in BACKENDS + ("auto",):
        raise ValueError(f"backend must be 'auto' or one of {BACKENDS}, got {backend!r}")
    return resolve(backend)


def _host_tables(master, backend):
    """The Surface's host tables, which the NumPy and JAX back ends read, made at once
    (Surface.prepare: topology and geometry in two threads)."""
    if backend != "warp" and isinstance(master, Surface) and master.n_faces:
        master.prepare()


def _longest_edge(master, backend, d_max):
    """The default d_max's longest edge from the Warp back end's device topology (which its
    detection makes anyway), so that a Warp call makes none of the Surface's host tables."""
    if backend != "warp" or d_max is not None or not isinstance(master, Surface):
        return None
    if master.n_faces == 0:
        return 0.0
    from ._backends import load

    return load("warp").master_scalars(master)[0]


def _detect(slave_x, ids, master, backend, mode, d_max, dtype, self_ids, t0) -> Contacts:
    from ._backends import load

    n = len(slave_x)
    answered = dict(backend=backend, dtype=dtype.name)
    if self_ids is not None:
        answered["finer"] = np.zeros(n, bool)
    if backend == "warp":
        # The Warp back end builds its trees on its device from its own topology: only the box
        # cut is made here (none of the Surface's NumPy tables).
        warp = load("warp")
        cut = None
        if n and master.n_faces:
            _, m_lo, m_hi = warp.master_scalars(master)
            cut = slaves_in_box(slave_x, m_lo, m_hi, float(d_max))
        rows, origin = (None, None) if cut is None else (cut[0], np.zeros(3))
    else:
        prep = prepare(slave_x, master, float(d_max), dtype)
        rows, origin = (None, None) if prep is None else (prep.slave_rows, prep.origin)
    t1 = time.perf_counter()
    if rows is None:  # the boxes do not meet: no grid, no contact
        return _empty(n, ids, d_max, timings={"prepare": t1 - t0, "total": t1 - t0}, **answered)
    if backend == "warp":
        x = slave_x if len(rows) == n else slave_x[rows]  # rows: all, or a few
        out, answered["device"], in_box = warp.run_one_shot(
            x, master, d_max, dtype, mode, self_ids is not None
        )
        count, cap, laps = {}, {}, {}
    else:
        st = Static.of(master, mode, prep, self_contact=self_ids is not None)
        if backend == "numpy":
            out, count, cap, laps = _run_numpy(slave_x, master, prep, st, dtype, slave_ids=self_ids)
            answered["device"] = "cpu"
        else:
            out, count, cap, answered["device"] = load(backend).run_one_shot(
                slave_x, master, prep, st, dtype, slave_ids=self_ids
            )
            laps = {}
        in_box = len(prep.node_ids), len(prep.face_ids)
    t2 = time.perf_counter()
    counts = Counts(
        slaves_in_box=len(rows),
        master_nodes_in_box=in_box[0],
        master_faces_in_box=in_box[1],
        count=count,
        capacity=cap,
    )
    timings = {"prepare": t1 - t0, **laps, "detect": t2 - t1, "total": t2 - t0}
    # (Warp's kernels blank the rows without an answer: 4.1 -> 2.4 ms of a 66 ms one call,
    # graded_1000 at 2^16 on the CPU, whose 6 slaves out of the box made every field a scatter
    # of the answered rows)
    blanked = backend == "warp"
    return assemble(n, ids, rows, origin, out, d_max, counts, timings, answered, blanked)


# --- swept detection ---------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class SweptSetup:
    """What every back end's swept detection starts from (host, float64): the slaves and
    faces whose boxes over the step meet, the local frame, and the faces' capture boxes."""

    slave_rows: np.ndarray  # slaves whose segment meets the faces' capture boxes' box
    face_ids: np.ndarray  # faces whose capture box meets the slaves' segments' box, Morton
    origin: np.ndarray  # local frame origin (float64)
    lo: np.ndarray  # capture boxes of face_ids [m, 3] (local frame, grown: capture_pads)
    hi: np.ndarray
    rel: float  # a segment grows by rel times its length (capture_pads)
    groups: tuple = ()  # the face tree's slots per level (_grid.grouping)


def capture_boxes(element, xe0, xe1, xp=np):
    """A box holding each face over the step (seed 004's capture box): x(xi, t) = (1 - t)
    x(xi, 0) + t x(xi, 1) lies in the box around the face's boxes at both ends."""
    lo0, hi0 = face_boxes(element, xe0, xp)
    lo1, hi1 = face_boxes(element, xe1, xp)
    return xp.minimum(lo0, lo1), xp.maximum(hi0, hi1)


def swept_setup(x0, x1, master: Surface, m1, dtype) -> SweptSetup | None:
    e = master.element
    lo, hi = capture_boxes(e, master.points[master.faces], m1[master.faces])
    s_lo, s_hi = np.minimum(x0, x1), np.maximum(x0, x1)
    scale = max(np.abs(np.r_[lo, hi, s_lo, s_hi]).max(), np.finfo(float).tiny)
    # A pair is a contact when the node comes within SPACE_RTOL of the face (relative to the
    # pair's size, plus rounding): the boxes and segments are grown by that, so no such pair
    # is left out.
    rel, rounding = _sweep.capture_pads(dtype)
    lo, hi = _sweep.grown_boxes(lo, hi, rel, rounding * scale)
    grow = rel * np.linalg.norm(x1 - x0, axis=-1, keepdims=True)
    s_lo, s_hi = s_lo - grow, s_hi + grow
    if len(x0) == 0 or len(lo) == 0:
        return None
    box_lo = np.maximum(s_lo.min(0), lo.min(0))
    box_hi = np.minimum(s_hi.max(0), hi.max(0))
    if (box_lo > box_hi).any():
        return None
    rows = np.nonzero(((s_lo <= box_hi) & (s_hi >= box_lo)).all(1))[0]
    fids = np.nonzero(((lo <= box_hi) & (hi >= box_lo)).all(1))[0]
    if len(rows) == 0 or len(fids) == 0:
        return None
    origin = box_lo if np.dtype(dtype) == np.float32 else np.zeros(3)
    extent = float((box_hi - box_lo).max())
    fids, groups = ordered(fids, 0.5 * (lo[fids] + hi[fids]), box_lo, extent)
    return SweptSetup(rows, fids, origin, lo[fids] - origin, hi[fids] - origin, rel, groups)


def _swept_inputs(slave_x0, slave_x1, master, master_x1):
    if not isinstance(master, Surface):
        raise ValueError("master must be an arraycontact.Surface")
    m1 = validate_points(master_x1, "master_x1")
    if m1.shape != master.points.shape:
        raise ValueError(
            f"master_x1 must have the master's shape {master.points.shape}, got {m1.shape}"
        )
    if isinstance(slave_x0, Surface):
        x1 = validate_points(slave_x1, "slave_x1")
        if x1.shape != slave_x0.points.shape:
            raise ValueError(
                f"slave_x1 must have the slave surface's shape {slave_x0.points.shape}, "
                f"got {x1.shape}"
            )
        ids = slave_x0.nodes
        return slave_x0.points[ids], x1[ids], ids, m1
    x0, x1 = validate_points(slave_x0, "slave_x0"), validate_points(slave_x1, "slave_x1")
    if x0.shape != x1.shape:
        raise ValueError(f"slave_x0 {x0.shape} and slave_x1 {x1.shape} differ in shape")
    return x0, x1, np.arange(len(x0)), m1


def _swept_numpy(x0, x1, master, m1, su: SweptSetup, dtype, chunk=1 << 13):
    """Capture boxes in the size-adaptive tree, the slaves' segments as balls around their
    midpoints, the certified search on every pair they give, the earliest per slave."""
    e = master.element
    o = su.origin
    p0 = (x0[su.slave_rows] - o).astype(dtype)
    p1 = (x1[su.slave_rows] - o).astype(dtype)
    faces = master.faces
    lap = _Laps()
    lo, hi = su.lo.astype(dtype), su.hi.astype(dtype)
    tree = _grid.build(np, su.face_ids, lo, hi, lo, groups=su.groups)
    lap("grid")
    # The ball around the segment grown by rel times its length.
    mid, half = 0.5 * (p0 + p1), (0.5 + su.rel) * norm(np, p1 - p0)
    slaves, fids = [], []
    for i in range(0, len(p0), chunk):
        s, entry, _, _ = _grid.query(
            np, tree, mid[i : i + chunk], half[i : i + chunk], 0.0, shrink=False
        )
        slaves.append(s + i)
        fids.append(tree.ids[entry])
    slave, face = np.concatenate(slaves), np.concatenate(fids)
    lap("broad phase")
    xe0 = (master.points[faces[face]] - o).astype(dtype)
    xe1 = (m1[faces[face]] - o).astype(dtype)
    toi = np.full(len(slave), np.inf, dtype)
    where = np.full((len(slave), 2), np.nan, dtype)
    conv = np.ones(len(slave), bool)
    visits = 0
    for i in range(0, len(slave), chunk):
        k = slice(i, i + chunk)
        toi[k], where[k], conv[k], v = _sweep.roots(e, xe0[k], xe1[k], p0[slave[k]], p1[slave[k]])
        visits += int(v.sum())
    lap("search")
    pick, first = _sweep.select(slave, face, toi, len(p0), _sweep.T_TOL[np.dtype(dtype)])
    k = pick[pick >= 0]
    rows = np.nonzero(pick >= 0)[0]
    xi = _sweep.natural(e, where[k, 0], where[k, 1])
    point, normal, vn = _sweep.impact(e, xe0[k], xe1[k], p0[rows], p1[rows], first[rows], xi)
    out = dict(
        rows=rows,
        face=face[k],
        toi=first[rows],
        xi=xi,
        point=point,
        normal=normal,
        normal_velocity=vn,
        feature=_sweep.feature_of(e, xi, _sweep.FEATURE_TOL[np.dtype(dtype)]),
        converged=conv[k],
    )
    lap("select")
    return out, {"pairs": len(slave), "visits": visits}, lap.times


def detect_swept(
    slave_x0,
    slave_x1,
    master,
    master_x1,
    *,
    backend="auto",
    dtype=None,
    static=False,
    d_max=None,
) -> SweptContacts:
    """The first contact of every slave node with the master over a step (seed 004's capture
    boxes and velocity-based check), every node moving linearly in time, t in [0, 1].

    slave_x0, slave_x1: the slaves at the start and the end ([n, 3] each, or slave_x0 a Surface
    and slave_x1 its points at the end: its used nodes are the slaves). master: a Surface at
    the start; master_x1: its points at the end. Returns SweptContacts: hit, toi (the earliest
    t at which the node lies on a face), face, xi, feature, point, normal, normal_velocity.

    Conservative and certified (_sweep): no crossing is missed; toi is never after the exact
    first contact and at most T_TOL before it (1e-6 of the step in float64, 1e-4 in float32),
    unless the node grazes a face, coming within the contact tolerance of it before touching
    it (delta + margin of _sweep.pair_frame: about 1e-9 of the pair's size in float64, 3.8e-5
    in float32, where the rounding margin sets it): then toi is that earlier time. Ties: among
    faces whose toi is within T_TOL of the earliest, the smallest face id (toi stays the
    earliest). static=True: also the end-of-step closest points (`detect` at t = 1, with d_max)
    in `.static`."""
    from ._backends import load, resolve

    t0 = time.perf_counter()
    x0, x1, ids, m1 = _swept_inputs(slave_x0, slave_x1, master, master_x1)
    dtype = np.dtype(np.float64 if dtype is None else dtype)
    if dtype not in TIE_RTOL:
        raise ValueError(f"dtype must be float32 or float64, got {dtype}")
    if backend not in BACKENDS + ("auto",):
        raise ValueError(f"backend must be 'auto' or one of {BACKENDS}, got {backend!r}")
    backend = resolve(backend)
    su = swept_setup(x0, x1, master, m1, dtype)
    t1 = time.perf_counter()
    n = len(x0)
    t_tol = _sweep.T_TOL[dtype]
    res = dict(
        hit=np.zeros(n, bool),
        toi=np.full(n, np.inf),
        face=np.full(n, -1, np.int64),
        xi=np.full((n, 2), np.nan),
        point=np.full((n, 3), np.nan),
        normal=np.full((n, 3), np.nan),
        feature=np.full(n, int(Feature.NONE), np.int32),
        normal_velocity=np.full(n, np.nan),
        status=np.full(n, int(Status.OUT_OF_RANGE), np.int32),
    )
    count, laps, device = {}, {}, "cpu"
    if su is not None:
        if backend == "numpy":
            out, count, laps = _swept_numpy(x0, x1, master, m1, su, dtype)
        else:
            out, count, device = load(backend).run_swept(x0, x1, master, m1, su, dtype)
        r = su.slave_rows[out["rows"]]
        res["hit"][r] = True
        res["toi"][r] = out["toi"]
        res["face"][r] = out["face"]
        res["xi"][r] = out["xi"]
        res["point"][r] = np.asarray(out["point"], float) + su.origin
        res["normal"][r] = out["normal"]
        res["feature"][r] = out["feature"]
        res["normal_velocity"][r] = out["normal_velocity"]
        res["status"][r] = np.where(out["converged"], int(Status.OK), int(Status.NOT_CONVERGED))
    t2 = time.perf_counter()
    end = None
    if static:
        end = detect(x1, master.with_points(m1), backend=backend, d_max=d_max, dtype=dtype)
    t3 = time.perf_counter()
    return SweptContacts(
        **res,
        slave_ids=np.asarray(ids),
        t_tol=t_tol,
        static=end,
        counts=Counts(
            slaves_in_box=0 if su is None else len(su.slave_rows),
            master_faces_in_box=0 if su is None else len(su.face_ids),
            count=count,
        ),
        timings={
            "prepare": t1 - t0,
            **laps,
            "detect": t2 - t1,
            "static": t3 - t2,
            "total": t3 - t0,
        },
        backend=backend,
        device=device,
        dtype=dtype.name,
    )
