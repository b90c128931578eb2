"""Set-up in Warp: the master's topology on the plan's device, built like the detection by
sorts, scans and a thread per item, so that a plan does not wait for the host's NumPy topology
(arraycontact._surface: about 1.9 s at 2^20 nodes a surface on the 2-core machine, 3-4 s on the
H100 machine's host).

The tables equal the Surface's, row for row (tests/test_warp.py checks them):
- face_edges [F, k], edge_faces [E, 2]: the keys min(a, b) 2^32 + max(a, b) of every (face,
  local edge) in the order of a stable sort (a counting sort by min(a, b), each node's few entries
  then sorted by a thread); an edge's faces come in face order, and its id is the rank of its
  key, the Surface's order. Allocated for F k edges (the count is not known before the sort):
  rows past the last edge are never read.
- node_faces (offsets [n + 1], ids): a counting sort of the faces by node, each node's faces
  then sorted by a thread. (The threads' insertion sorts cost the square of a node's faces:
  nothing on finite-element meshes, whose nodes have a few; a fan of 10^4 faces round one
  node would take about 10^8 steps of one thread.)
- prev/next node and face of each node (arraycontact._select.boundary_topology): the edges of
  one face, oriented as in that face, split at their mid node. Where several boundary edges
  leave one node (a pinch), the last in face order wins, as NumPy's assignment does, so the
  answer does not depend on the order the threads run in.
- nodes: the used node ids, ascending (a scan of the use counts).
Scalars, read back once: the used node count, whether every edge has two faces (closed), the
longest edge (seed 000 eq. 2), the face radii's largest and tenth percentile (the plan's
rounding slack and refit margin) and the box of the used nodes, in float64 whatever the plan's
dtype (the percentile, a margin, from float32 radii). A Surface's topology on a device is made
once and kept while the Surface lives.
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import warp as wp

from arraycontact._surface import Surface, validate_points

from ._parts import concurrently, load

wp.set_module_options({"enable_backward": False})

#: Items a thread reduces before its one atomic update (a float atomic on one address from
#: every thread serialises).
CHUNK = 64
#: The edge keys' halves: two 32-bit fields of an int64 (node and face ids are int32), each a
#: shift or a mask away (an int64 division a key before: `_edge_segments` 1.75 -> 1.45 ms at
#: 2^16 on the CPU).
LOW = wp.constant(wp.int64(0xFFFFFFFF))
#: A (face, local edge) as v = 4 f + le (every element has at most 4 edges): the face and the
#: edge a shift and a mask away, in the order of (f, le) as f k + le was (a division by k an
#: entry before: `_edge_tables` 3.4-3.7 -> 2.6-2.7 ms at 2^16 on the CPU).
EDGE_BITS = 2
EDGE_MASK = (1 << EDGE_BITS) - 1


@wp.kernel
def _count_edges(
    faces: wp.array2d(dtype=int), ends: wp.array2d(dtype=int), uses: wp.array(dtype=int)
):
    """Face f: each local edge counted at its smaller corner."""
    f = wp.tid()
    for le in range(ends.shape[0]):
        wp.atomic_add(uses, wp.min(faces[f, ends[le, 0]], faces[f, ends[le, 1]]), 1)


@wp.kernel
def _count_nodes(faces: wp.array2d(dtype=int), uses: wp.array(dtype=int)):
    f = wp.tid()
    for c in range(faces.shape[1]):
        wp.atomic_add(uses, faces[f, c], 1)


@wp.kernel
def _scatter_edges(
    faces: wp.array2d(dtype=int),
    ends: wp.array2d(dtype=int),
    offsets: wp.array(dtype=int),
    cursor: wp.array(dtype=int),
    pairs: wp.array(dtype=wp.int64),
):
    """Face f: each local edge v = 4 f + le (EDGE_BITS) into its smaller corner's segment as
    the pair (larger corner) 2^32 + v, in any order (_edge_segments sorts them)."""
    f = wp.tid()
    k = ends.shape[0]
    for le in range(k):
        a = faces[f, ends[le, 0]]
        b = faces[f, ends[le, 1]]
        lo = wp.min(a, b)
        pair = (wp.int64(wp.max(a, b)) << wp.int64(32)) | wp.int64((f << EDGE_BITS) + le)
        pairs[offsets[lo] + wp.atomic_add(cursor, lo, 1)] = pair


@wp.kernel
def _scatter_nodes(
    faces: wp.array2d(dtype=int),
    offsets: wp.array(dtype=int),
    cursor: wp.array(dtype=int),
    ids: wp.array(dtype=int),
):
    """Face f into each of its nodes' segments, in any order (_face_segments sorts them)."""
    f = wp.tid()
    for c in range(faces.shape[1]):
        i = faces[f, c]
        ids[offsets[i] + wp.atomic_add(cursor, i, 1)] = f


@wp.func
def _sort_run(a: wp.array(dtype=Any), lo: int, hi: int):
    """a[lo:hi] ascending in place (a node's handful of entries: insertion sort)."""
    for j in range(lo + 1, hi):
        p = a[j]
        q = j
        while q > lo and a[q - 1] > p:
            a[q] = a[q - 1]
            q -= 1
        a[q] = p


@wp.kernel
def _edge_segments(
    offsets: wp.array(dtype=int),
    keys: wp.array(dtype=wp.int64),
    vals: wp.array(dtype=int),
):
    """Node i's edges, given as _scatter_edges' pairs, sorted by (larger corner, face, local
    edge) and written over them as the keys i 2^32 + larger corner, with the values 4 f + le:
    the order of a stable sort of every edge's key."""
    i = wp.tid()
    _sort_run(keys, offsets[i], offsets[i + 1])
    for j in range(offsets[i], offsets[i + 1]):
        p = keys[j]
        keys[j] = (wp.int64(i) << wp.int64(32)) | (p >> wp.int64(32))
        vals[j] = int(p & LOW)


@wp.kernel
def _face_segments(offsets: wp.array(dtype=int), ids: wp.array(dtype=int)):
    """Node i's faces ascending."""
    i = wp.tid()
    _sort_run(ids, offsets[i], offsets[i + 1])


@wp.kernel
def _heads(keys: wp.array(dtype=wp.int64), heads: wp.array(dtype=int)):
    t = wp.tid()
    h = int(1)
    if t > 0:
        if keys[t] == keys[t - 1]:
            h = 0
    heads[t] = h


@wp.kernel
def _edge_tables(
    faces: wp.array2d(dtype=int),
    ends: wp.array2d(dtype=int),
    keys: wp.array(dtype=wp.int64),
    vals: wp.array(dtype=int),
    ranks: wp.array(dtype=int),
    count: int,
    face_edges: wp.array2d(dtype=int),
    edge_faces: wp.array2d(dtype=int),
    starts: wp.array(dtype=int),
    edges: wp.array2d(dtype=int),
    odd: wp.array(dtype=int),
    win_next: wp.array(dtype=int),
    win_prev: wp.array(dtype=int),
):
    """Sorted entry t: its face's edge id; at an edge's first entry, where it starts, its
    corners (ascending), its (up to two) faces, whether it has other than two (odd[0]) and,
    for an edge of one face, its claim on its nodes' boundary neighbours (the largest
    face-order index wins)."""
    t = wp.tid()
    v = vals[t]
    f = v >> EDGE_BITS
    e = ranks[t] - 1
    face_edges[f, v & EDGE_MASK] = e
    head = t == 0
    if t > 0:
        head = keys[t] != keys[t - 1]
    if head:
        two = False
        if t + 1 < count:
            two = keys[t + 1] == keys[t]
        three = False
        if t + 2 < count:
            three = keys[t + 2] == keys[t]
        starts[e] = t
        # (the key is lo 2^32 + hi: no read of the (scattered) faces)
        edges[e, 0] = int(keys[t] >> wp.int64(32))
        edges[e, 1] = int(keys[t] & LOW)
        edge_faces[e, 0] = f
        edge_faces[e, 1] = -1
        if two:
            edge_faces[e, 1] = vals[t + 1] >> EDGE_BITS
        if three or not two:
            wp.atomic_add(odd, 0, 1)
        if not two:
            le = v & EDGE_MASK
            a = faces[f, ends[le, 0]]
            b = faces[f, ends[le, 1]]
            wp.atomic_max(win_next, a, v)
            wp.atomic_max(win_prev, b, v)
            if ends.shape[1] == 3:  # the mid node: after a, before b
                mid = faces[f, ends[le, 2]]
                wp.atomic_max(win_next, mid, v)
                wp.atomic_max(win_prev, mid, v)


@wp.func
def _neighbour(faces: wp.array2d(dtype=int), ends: wp.array2d(dtype=int), v: int, i: int, far: int):
    """Node i's neighbour along the boundary edge v (4 face + local edge) towards the edge's
    end `far` (1: next, 0: previous), and the edge's face; (i, -1) for v < 0. A quadratic
    edge a - mid - b: a's next and b's previous are mid, mid's are a and b."""
    node = i
    face = int(-1)
    if v >= 0:
        face = v >> EDGE_BITS
        le = v & EDGE_MASK
        node = faces[face, ends[le, far]]
        if ends.shape[1] == 3 and i == faces[face, ends[le, 1 - far]]:
            node = faces[face, ends[le, 2]]
    return node, face


@wp.kernel
def _boundary(
    faces: wp.array2d(dtype=int),
    ends: wp.array2d(dtype=int),
    win_next: wp.array(dtype=int),
    win_prev: wp.array(dtype=int),
    next_node: wp.array(dtype=int),
    next_face: wp.array(dtype=int),
    prev_node: wp.array(dtype=int),
    prev_face: wp.array(dtype=int),
):
    """Each node's boundary neighbours from the edges that won its claims (itself and -1 off
    the boundary)."""
    i = wp.tid()
    node, face = _neighbour(faces, ends, win_next[i], i, 1)
    next_node[i] = node
    next_face[i] = face
    node, face = _neighbour(faces, ends, win_prev[i], i, 0)
    prev_node[i] = node
    prev_face[i] = face


@wp.kernel
def _used(uses: wp.array(dtype=int), flags: wp.array(dtype=int)):
    i = wp.tid()
    flags[i] = wp.where(uses[i] > 0, 1, 0)


@wp.kernel
def _compact(uses: wp.array(dtype=int), ranks: wp.array(dtype=int), nodes: wp.array(dtype=int)):
    i = wp.tid()
    if uses[i] > 0:
        nodes[ranks[i] - 1] = i


@wp.func
def _ball(points: wp.array(dtype=wp.vec3d), faces: wp.array2d(dtype=int), f: int):
    """Face f's centre (arraycontact._surface.face_bounds': its nodes' mean, summed in their
    order) and the largest squared distance of a node from it."""
    nn = faces.shape[1]
    c = wp.vec3d()
    for a in range(nn):
        c += points[faces[f, a]]
    c = c / wp.float64(nn)
    r2 = wp.float64(0.0)
    for a in range(nn):
        r2 = wp.max(r2, wp.length_sq(points[faces[f, a]] - c))
    return c, r2


@wp.func
def _ball_corners(points: wp.array(dtype=wp.vec3d), faces: wp.array2d(dtype=int), f: int):
    """A tri3 or quad4 face's `_ball` (the same sums) and the largest squared distance between
    two of its nodes, each node read once (the loops read each three to seven times: the
    plan's scalar chain on the CPU)."""
    nn = faces.shape[1]
    x0 = points[faces[f, 0]]
    x1 = points[faces[f, 1]]
    x2 = points[faces[f, 2]]
    x3 = x2
    c = x0 + x1 + x2
    e2 = wp.max(wp.length_sq(x0 - x1), wp.max(wp.length_sq(x0 - x2), wp.length_sq(x1 - x2)))
    if nn == 4:
        x3 = points[faces[f, 3]]
        c = c + x3
        e2 = wp.max(e2, wp.max(wp.length_sq(x0 - x3), wp.length_sq(x1 - x3)))
        e2 = wp.max(e2, wp.length_sq(x2 - x3))
    c = c / wp.float64(nn)
    r2 = wp.max(wp.length_sq(x0 - c), wp.length_sq(x1 - c))
    r2 = wp.max(r2, wp.max(wp.length_sq(x2 - c), wp.length_sq(x3 - c)))
    return c, r2, e2


@wp.kernel
def _face_scalars(
    points: wp.array(dtype=wp.vec3d),
    faces: wp.array2d(dtype=int),
    lebesgue: wp.float64,
    radii: wp.array(dtype=wp.float32),
    ids: wp.array(dtype=int),
    out: wp.array(dtype=wp.float64),
    contiguous: int,
):
    """Faces t, t + T, ... (T threads; contiguous = 1, for the CPU's cache: faces t CHUNK,
    t CHUNK + 1, ...): each face's radius in float32 (to sort: a tenth percentile needs no
    more) and, where ids has room for them (a GPU's sort), the face ids; then one atomic
    update of the largest squared node distance within a face (out[0]), the largest radius
    (out[1]) and the box of the faces' balls (out[8:11] lo, out[11:14] hi)."""
    t = wp.tid()
    n_threads = (faces.shape[0] + CHUNK - 1) // CHUNK
    nn = faces.shape[1]
    l2 = wp.float64(0.0)
    r_max = wp.float64(0.0)
    lo = wp.vec3d(wp.float64(1.0e300))
    hi = wp.vec3d(wp.float64(-1.0e300))
    for j in range(CHUNK):
        f = wp.where(contiguous == 1, t * CHUNK + j, t + j * n_threads)
        if f < faces.shape[0]:
            c = wp.vec3d()
            r2 = wp.float64(0.0)
            if nn == 3 or nn == 4:
                c, r2, e2 = _ball_corners(points, faces, f)
                l2 = wp.max(l2, e2)
            else:
                c, r2 = _ball(points, faces, f)
                for a in range(nn):
                    for b in range(a + 1, nn):
                        l2 = wp.max(l2, wp.length_sq(points[faces[f, a]] - points[faces[f, b]]))
            r = lebesgue * wp.sqrt(r2)
            radii[f] = wp.float32(r)
            if f < ids.shape[0]:
                ids[f] = f
            r_max = wp.max(r_max, r)
            lo = wp.min(lo, c - wp.vec3d(r, r, r))
            hi = wp.max(hi, c + wp.vec3d(r, r, r))
    wp.atomic_max(out, 0, l2)
    wp.atomic_max(out, 1, r_max)
    for a in range(3):
        wp.atomic_min(out, 8 + a, lo[a])
        wp.atomic_max(out, 11 + a, hi[a])


@wp.kernel
def _balls(
    points: wp.array(dtype=wp.vec3d),
    faces: wp.array2d(dtype=int),
    lebesgue: wp.float64,
    centres: wp.array(dtype=wp.vec3d),
    radii: wp.array(dtype=wp.float64),
):
    f = wp.tid()
    c, r2 = _ball(points, faces, f)
    centres[f] = c
    radii[f] = lebesgue * wp.sqrt(r2)


@wp.kernel
def _box(
    points: wp.array(dtype=wp.vec3d),
    uses: wp.array(dtype=int),
    masked: int,
    out: wp.array(dtype=wp.float64),
    bad: wp.array(dtype=int),
):
    """Points t, t + T, ...: the box of the finite ones (masked = 1: of those with uses > 0),
    into out[2:5] (lo) and out[5:8] (hi), and the count of rows not finite into bad[0]."""
    t = wp.tid()
    n_threads = (points.shape[0] + CHUNK - 1) // CHUNK
    lo = wp.vec3d(wp.float64(1.0e300))
    hi = wp.vec3d(wp.float64(-1.0e300))
    not_finite = int(0)
    for j in range(CHUNK):
        i = t + j * n_threads
        if i < points.shape[0]:
            x = points[i]
            if not (wp.isfinite(x[0]) and wp.isfinite(x[1]) and wp.isfinite(x[2])):
                not_finite += 1
            elif masked == 0 or uses[i] > 0:
                lo = wp.min(lo, x)
                hi = wp.max(hi, x)
    for a in range(3):
        wp.atomic_min(out, 2 + a, lo[a])
        wp.atomic_max(out, 5 + a, hi[a])
    if not_finite > 0:
        wp.atomic_add(bad, 0, not_finite)


@wp.kernel
def _iota(out: wp.array(dtype=int)):
    i = wp.tid()
    out[i] = i


def iota(n: int, size: int, device):
    """An int array of `size` whose first n entries are 0 .. n - 1 (the rest uninitialised)."""
    out = wp.empty(size, dtype=int, device=device)
    wp.launch(_iota, n, outputs=[out], device=device)
    return out


def _scalars(device):
    """out[0:2] (maxima, from 0), out[2:5] and out[5:8], out[8:11] and out[11:14] (two boxes,
    from empty), bad[0] (a count)."""
    empty = [*[1e300] * 3, *[-1e300] * 3]
    out = wp.array([0.0, 0.0, *empty, *empty], dtype=wp.float64, device=device)
    return out, wp.zeros(1, dtype=int, device=device)


def device_points(a, what: str, device):
    """Points [n, 3] on `device` in float64 and their box (lo, hi), checked there: a
    ValueError as validate_points's when a row is not finite (or the array is not [n, 3] of
    real numbers). The host only checks the shape and copies."""
    x = np.asarray(a)
    if x.dtype == object or x.dtype.kind not in "iuf" or x.ndim != 2 or x.shape[1] != 3:
        validate_points(x, what)  # raises, naming what is wrong
    xd = wp.array(np.ascontiguousarray(x, np.float64), dtype=wp.vec3d, device=device)
    out, bad = _scalars(device)
    n = len(x)
    wp.launch(_box, -(-n // CHUNK), inputs=[xd, bad, 0], outputs=[out, bad], device=device)
    if int(bad.numpy()[0]):
        validate_points(x, what)  # raises, naming the first row that is not finite
    s = out.numpy()
    return xd, s[2:5].copy(), s[5:8].copy()


@dataclass(eq=False)
class Topology:
    """A master's tables on one device (int32 arrays) and its scalars (host)."""

    faces: wp.array  # [F, nodes per face]
    face_edges: wp.array  # [F, k]
    edge_faces: wp.array  # [F k, 2]: rows past the number of edges unused
    nf_offsets: wp.array  # [n + 1]
    nf_ids: wp.array  # [F nodes per face]
    prev_node: wp.array
    next_node: wp.array
    prev_face: wp.array
    next_face: wp.array
    nodes: wp.array  # the used node ids, ascending
    n_nodes: int
    points: wp.array  # float64, as the Surface's
    lebesgue: float  # the element's (face_balls)
    edge_starts: wp.array  # [F k]: where each edge's entries start in the sorted keys
    edges: wp.array  # [F k, 2]: each edge's corners, ascending
    n_edges: int
    closed: bool
    longest_edge: float
    r_max: float
    r_small: float  # the tenth percentile of the face radii (np.quantile's, in float32)
    node_box: tuple  # (lo, hi) of the used nodes
    ball_box: tuple  # (lo, hi) of the faces' balls
    balls: tuple = None  # face_balls' (centres, radii), once made
    uses: wp.array = None  # [n + 1] each point's faces (the used nodes' box)


#: Surface -> {device: Topology}: a Surface is immutable, so its tables on a device are made
#: once (as the Surface caches its own), for every plan of it there.
_CACHE = weakref.WeakKeyDictionary()
#: Surface.connectivity_key -> {device: Topology}: the last one made of that connectivity,
#: whose tables of the connectivity alone a surface of the same faces on other points (a
#: deformed configuration: Surface.with_points) shares; only its geometry is made again.
_BY_CONNECTIVITY = weakref.WeakKeyDictionary()


def master_scalars(master: Surface, device=None):
    """(longest edge, box lo, box hi) of the master from its topology on `device` (made
    there on first use): the box of its used nodes, or of its faces' balls where faces are
    curved (they may bulge past their nodes)."""
    topo = topology(master, device)
    box = topo.node_box if master.element.linear else topo.ball_box
    return topo.longest_edge, box[0], box[1]


def topology(master: Surface, device) -> Topology:
    """The master's topology on `device`, made on first use (launches, then one read of the
    scalars); on a surface whose connectivity has one there already, its geometry alone."""
    device = wp.get_device(device)
    per_device = _CACHE.setdefault(master, {})
    if device.alias not in per_device:
        same = _BY_CONNECTIVITY.setdefault(master.connectivity_key, {})
        known = same.get(device.alias)
        t = _topology(master, device) if known is None else _geometry(master, device, known)
        per_device[device.alias] = same[device.alias] = t
    return per_device[device.alias]


def _tenth(radii, rows, nf: int, device) -> float:
    """The tenth percentile of radii[:nf] (float32; np.quantile's linear interpolation): a
    partial sort on the CPU, a radix sort on a GPU (radii and rows [2 nf]: its scratch)."""
    q = 0.1 * (nf - 1)
    i0 = int(np.floor(q))
    i1 = min(i0 + 1, nf - 1)
    if device.is_cuda:
        wp.utils.radix_sort_pairs(radii, rows, nf)
        r0, r1 = radii[i0 : i1 + 1].numpy()[[0, -1]]
    else:
        r = np.partition(radii.numpy()[:nf], [i0, i1])
        r0, r1 = r[i0], r[i1]
    return float(r0 + (q - i0) * (r1 - r0))


def _topology(master: Surface, device) -> Topology:
    e = master.element
    n = len(master.points)
    nf, nn = master.faces.shape
    k = e.n_corners
    if k > 1 << EDGE_BITS:
        raise ValueError(f"{e.name}: {k} edges a face, the topology takes at most 4")
    m = nf * k
    # Scratch and tables that the kernels write whole (or read only where written) are left
    # uninitialised; counters start at zero.
    empty = lambda *shape: wp.empty(shape, dtype=int, device=device)  # noqa: E731
    zeros = lambda size: wp.zeros(size, dtype=int, device=device)  # noqa: E731

    def run(kernel, threads, *args):
        wp.launch(kernel, threads, inputs=args, device=device)

    faces = wp.array(master.faces.astype(np.int32), dtype=int, device=device)
    ends = wp.array(e.edge_nodes, dtype=int, device=device)
    points = wp.array(master.points, dtype=wp.vec3d, device=device)
    out, bad = _scalars(device)
    t = {}  # what each chain makes

    # Three independent chains of launches (on the CPU run at once, one thread each).
    def edge_chain():
        # A counting sort of each (face, local edge) into its smaller corner's segment, each
        # segment then sorted by a thread (no radix sort: two were a third of the CPU's
        # topology); the ranks of the distinct keys; the tables.
        uses, offsets = zeros(n + 1), empty(n + 1)
        run(_count_edges, nf, faces, ends, uses)
        wp.utils.array_scan(uses, offsets, inclusive=False)
        # (the keys overwrite the pairs they come from: 3 MB less to touch at 2^16 nodes, where
        # the plan of a Surface on memory new to the process pays about 1 us a 4 KB page)
        keys, vals = wp.empty(m, dtype=wp.int64, device=device), empty(m)
        run(_scatter_edges, nf, faces, ends, offsets, zeros(n), keys)
        run(_edge_segments, n, offsets, keys, vals)
        ranks = t["ranks"] = empty(m)
        run(_heads, m, keys, ranks)
        wp.utils.array_scan(ranks, ranks, inclusive=True)
        t["face_edges"], t["edge_faces"] = empty(nf, k), empty(m, 2)
        t["edge_starts"], t["edges"], t["odd"] = empty(m), empty(m, 2), zeros(1)
        win_next = wp.full(n, -1, dtype=int, device=device)
        win_prev = wp.full(n, -1, dtype=int, device=device)
        tables = [t[a] for a in ("face_edges", "edge_faces", "edge_starts", "edges", "odd")]
        run(_edge_tables, m, faces, ends, keys, vals, ranks, m, *tables, win_next, win_prev)
        for a in ("prev_node", "next_node", "prev_face", "next_face"):
            t[a] = empty(n)
        neighbours = [t[a] for a in ("next_node", "next_face", "prev_node", "prev_face")]
        run(_boundary, n, faces, ends, win_next, win_prev, *neighbours)

    def node_chain():
        # Node -> faces by a counting sort, each node's faces sorted by a thread; the used
        # nodes and their box.
        uses, offsets = zeros(n + 1), empty(n + 1)
        run(_count_nodes, nf, faces, uses)
        wp.utils.array_scan(uses, offsets, inclusive=False)
        t["nf_offsets"], t["nf_ids"] = offsets, empty(nf * nn)
        run(_scatter_nodes, nf, faces, offsets, zeros(n), t["nf_ids"])
        run(_face_segments, n, offsets, t["nf_ids"])
        flags = t["flags"] = empty(n)
        run(_used, n, uses, flags)
        wp.utils.array_scan(flags, flags, inclusive=True)
        t["nodes"] = empty(n)
        run(_compact, n, uses, flags, t["nodes"])
        run(_box, -(-n // CHUNK), points, uses, 1, out, bad)
        t["uses"] = uses

    def scalar_chain():
        t["r_small"] = _face_scalars_of(points, faces, e, out, device)

    load(_count_edges, device)  # once, before threads launch its kernels
    concurrently(device, edge_chain, node_chain, scalar_chain)
    n_nodes = int(t["flags"][n - 1 : n].numpy()[0]) if n else 0
    n_edges = int(t["ranks"][m - 1 : m].numpy()[0])
    return Topology(
        faces=faces,
        **{a: t[a] for a in ("face_edges", "edge_faces", "nf_offsets", "nf_ids", "nodes")},
        **{a: t[a] for a in ("prev_node", "next_node", "prev_face", "next_face")},
        n_nodes=n_nodes,
        points=points,
        lebesgue=e.lebesgue,
        edge_starts=t["edge_starts"],
        edges=t["edges"],
        n_edges=n_edges,
        closed=int(t["odd"].numpy()[0]) == 0,
        **_read_scalars(out, t["r_small"]),
        uses=t["uses"],
    )


def _face_scalars_of(points, faces, e, out, device) -> float:
    """The longest edge, the largest radius, the box of the faces' balls into out, and the
    tenth percentile of their radii (the balls themselves: face_balls, for those who read
    them; 4 MB at 2^16 nodes that a plan would touch for nothing)."""
    nf = faces.shape[0]
    cuda = device.is_cuda
    radii = wp.empty(2 * nf if cuda else nf, dtype=wp.float32, device=device)
    rows = wp.empty(2 * nf if cuda else 0, dtype=int, device=device)  # (the CPU: a partition)
    scalars = (points, faces, wp.float64(e.lebesgue), radii, rows, out, int(not cuda))
    wp.launch(_face_scalars, -(-nf // CHUNK), inputs=scalars, device=device)
    return _tenth(radii, rows, nf, device)


def _read_scalars(out, r_small) -> dict:
    s = out.numpy()
    return dict(
        longest_edge=float(np.sqrt(s[0])),
        r_max=float(s[1]),
        r_small=r_small,
        node_box=(s[2:5].copy(), s[5:8].copy()),
        ball_box=(s[8:11].copy(), s[11:14].copy()),
    )


def _geometry(master: Surface, device, known: Topology) -> Topology:
    """The topology of `master` where `known` is one of its connectivity on other points:
    its tables shared, the geometry made (the face scalars and the used nodes' box: the
    edge and node chains are most of a topology's time)."""
    points = wp.array(master.points, dtype=wp.vec3d, device=device)
    out, bad = _scalars(device)
    box = (points, known.uses, 1, out, bad)
    wp.launch(_box, -(-len(master.points) // CHUNK), inputs=box, device=device)
    r_small = _face_scalars_of(points, known.faces, master.element, out, device)
    return replace(known, points=points, balls=None, **_read_scalars(out, r_small))


@wp.func
def spread21(v: wp.int64):
    """The low 21 bits of v moved to every third bit (arraycontact._grid._spread)."""
    x = v & wp.int64(0x1FFFFF)
    x = (x | (x << wp.int64(32))) & wp.int64(0x1F00000000FFFF)
    x = (x | (x << wp.int64(16))) & wp.int64(0x1F0000FF0000FF)
    x = (x | (x << wp.int64(8))) & wp.int64(0x100F00F00F00F00F)
    x = (x | (x << wp.int64(4))) & wp.int64(0x10C30C30C30C30C3)
    x = (x | (x << wp.int64(2))) & wp.int64(0x1249249249249249)
    return x


@wp.kernel
def _morton64(
    x: wp.array(dtype=wp.vec3d),
    ids: wp.array(dtype=int),
    lo: wp.vec3d,
    scale: wp.float64,
    keys: wp.array(dtype=wp.int64),
    order: wp.array(dtype=int),
):
    """arraycontact._grid.morton_order's key of x[ids[t]] (the same float64 operations)."""
    t = wp.tid()
    p = x[ids[t]] - lo
    key = wp.int64(0)
    for a in range(3):
        c = wp.clamp(wp.floor(p[a] * scale), wp.float64(0.0), wp.float64(2097151.0))
        key = key | (spread21(wp.int64(c)) << wp.int64(a))
    keys[t] = key
    order[t] = t


def morton_order(x, ids, n: int, lo, extent: float, device, keys_too=False):
    """arraycontact._grid.morton_order of the rows x[ids[:n]] (x: float64 on the device) on
    the device: positions into ids, as a host array (one stable radix sort); keys_too: also
    their sorted keys (arraycontact._grid.morton_keys'), as a host array."""
    keys = wp.empty(2 * max(n, 1), dtype=wp.int64, device=device)
    order = wp.empty(2 * max(n, 1), dtype=int, device=device)
    scale = (1 << 21) / max(float(extent), np.finfo(float).tiny)
    lo = wp.vec3d(*[float(v) for v in lo])
    wp.launch(
        _morton64, n, inputs=[x, ids, lo, wp.float64(scale)], outputs=[keys, order], device=device
    )
    wp.utils.radix_sort_pairs(keys, order, n, end_bit=63)
    if keys_too:
        return order[:n].numpy(), keys[:n].numpy()
    return order[:n].numpy()


@wp.kernel
def _padded(offsets: wp.array(dtype=int), ids: wp.array(dtype=int), table: wp.array2d(dtype=int)):
    i, j = wp.tid()
    a = offsets[i]
    table[i, j] = wp.where(j < offsets[i + 1] - a, ids[a + j], -1)


def face_balls(t: Topology, device):
    """Each face's ball, arraycontact._surface.face_bounds' in float64: (centres [F] vec3d,
    radii [F]), made on first use."""
    if t.balls is None:
        nf = t.faces.shape[0]
        c = wp.empty(nf, dtype=wp.vec3d, device=device)
        r = wp.empty(nf, dtype=wp.float64, device=device)
        if nf:
            wp.launch(
                _balls, nf, inputs=[t.points, t.faces, wp.float64(t.lebesgue), c, r], device=device
            )
        t.balls = (c, r)
    return t.balls


def node_face_table(t: Topology, n_points: int, max_valence: int, device):
    """[n_points, V] the faces of each node padded with -1 (V: the largest valence), as
    arraycontact_jax._gradients.padded_node_faces; None when V exceeds max_valence."""
    v = int(np.diff(t.nf_offsets.numpy()).max()) if n_points else 0
    if v > max_valence:
        return None
    table = wp.empty((n_points, max(v, 1)), dtype=int, device=device)
    wp.launch(_padded, table.shape, inputs=[t.nf_offsets, t.nf_ids], outputs=[table], device=device)
    return table


def fill_surface(master: Surface, device) -> Topology:
    """The device's topology of `master`, with its exact tables copied into the Surface's own
    cache (nodes, node_faces, the edge table, closed, node_box: equal to what its NumPy
    properties compute, tests/test_warp.py checks them), so that host code reading them (the
    JAX plan) does not compute them again. Float results (longest edge, face balls) are left
    to the caller: on a GPU they may differ from NumPy's in the last bit."""
    t = topology(master, device)
    d = master.__dict__
    if "_edge_table" not in d:
        e, m = t.n_edges, len(master.faces) * master.element.n_corners
        starts = t.edge_starts[:e].numpy().astype(np.int64)
        d["_edge_table"] = (
            t.edges[:e].numpy().astype(np.int64),
            t.face_edges.numpy().astype(np.int64),
            t.edge_faces[:e].numpy().astype(np.int64),
            np.diff(np.r_[starts, m]),
        )
    if "node_faces" not in d:
        d["node_faces"] = (
            t.nf_offsets.numpy().astype(np.int64),
            t.nf_ids.numpy().astype(np.int64),
        )
    d.setdefault("nodes", t.nodes[: t.n_nodes].numpy().astype(np.int64))
    d.setdefault("closed", bool(t.closed))
    d.setdefault("node_box", t.node_box)
    return t


__all__ = [
    "Topology",
    "device_points",
    "face_balls",
    "fill_surface",
    "iota",
    "morton_order",
    "node_face_table",
    "spread21",
    "topology",
]
