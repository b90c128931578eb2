"""The master/slave surface: validated node coordinates and connectivity plus cached topology."""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from ._elements import NODES_PER_FACE, Element, get_element, interpolate
from ._xp import lead, segment_sum


def _dot(a, b):
    """The dot product over the last axis of 3 (written out: NumPy's reductions over a short
    axis are 5-20x slower than the sum of the three products)."""
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2]


def _unit(v, xp=np):
    # Zero for a zero vector, without a NaN in the value or (under JAX) the gradient.
    n2 = _dot(v, v)[..., None]
    ok = n2 > 0
    return xp.where(ok, v / xp.sqrt(xp.where(ok, n2, 1)), 0 * v)


# Geometry derived from node coordinates, written against an array namespace: the NumPy
# pipeline caches it on the Surface; the JAX plan/detect recomputes it from moving coordinates.


def face_normals(element, xe, xp=np):
    """Unit normal at the centre of each face with nodes xe [F, nn, 3] (zero if degenerate)."""
    if element.name == "tri3":
        return _unit(xp.cross(xe[:, 1] - xe[:, 0], xe[:, 2] - xe[:, 0]), xp)
    if element.name == "quad4":
        # At the centre, x_xi x x_eta = (x2 - x0) x (x3 - x1) / 8: the diagonals' cross product.
        return _unit(xp.cross(xe[:, 2] - xe[:, 0], xe[:, 3] - xe[:, 1]), xp)
    xi = xp.zeros(xe.shape[:1] + (2,), xe.dtype) + lead(xp, xp.asarray(element.centre, xe.dtype), 2)
    _, dx = interpolate(element, xe, xi, xp)
    return _unit(xp.cross(dx[..., 0], dx[..., 1]), xp)


def face_bounds(element, xe, xp=np):
    """Centre c and radius r of a ball holding each face: |x(xi) - c| <= r for all xi.

    c is the mean of the nodes; r = lebesgue * max_i |x_i - c| is rigorous for curved faces
    because x(xi) - c = sum_i N_i(xi) (x_i - c)."""
    nn = xe.shape[1]
    c = sum(xe[:, i] for i in range(nn)) / nn  # loops over the nodes: reductions over an
    d2 = None  # axis of 3-9 are slow on NumPy
    for i in range(nn):
        e = _dot(xe[:, i] - c, xe[:, i] - c)
        d2 = e if d2 is None else xp.maximum(d2, e)
    return c, element.lebesgue * xp.sqrt(xp.where(d2 > 0, d2, 0 * d2))


def control_points(element, xe):
    """The Bernstein control points (a list of [F, 3]) of quadratic faces with nodes xe
    [F, nn, 3] (tri6, quad8, quad9), whose convex hull holds the face: the corners; for each
    edge a - m - b (its mid node m: node n_corners + e), 2 m - (a + b) / 2; on quads the centre's,
    4 x_c - (sum of the mid nodes) + (sum of the corners) / 4 (the tensor product of the 1-D
    transform (a, m, b) -> (a, 2 m - (a + b) / 2, b)), where quad8's x_c is its value at the
    centre, (sum of the mid nodes) / 2 - (sum of the corners) / 4 (its shape space lies in
    quad9's)."""
    k = element.n_corners
    ends = [xe[:, e] for e in range(k)]
    edges = [2.0 * xe[:, k + e] - 0.5 * (ends[e] + ends[(e + 1) % k]) for e in range(k)]
    out = ends + edges
    if k == 4:
        mids, corners = sum(xe[:, k + e] for e in range(k)), sum(ends)
        if element.nodes_per_face == 9:
            out.append(4.0 * xe[:, 8] - mids + 0.25 * corners)
        else:
            out.append(mids - 0.75 * corners)
    return out


def face_boxes(element, xe, xp=np):
    """A box [lo, hi] holding each face with nodes xe [F, nn, 3]. Per axis, with m and w the
    middle and half-width of the nodes' range, x(xi) - m = sum_i N_i (x_i - m), so
    |x(xi) - m| <= lebesgue w: the nodes' box itself for linear faces (lebesgue 1), for curved
    ones cut by the ball's cube and the box of the Bernstein control points (`control_points`:
    the tightest of the three, as the Warp kernels' face_bounds)."""
    a, b = xp.min(xe, 1), xp.max(xe, 1)
    if element.linear:
        return a, b
    m, w = 0.5 * (a + b), 0.5 * element.lebesgue * (b - a)
    c, r = face_bounds(element, xe, xp)
    lo, hi = xp.maximum(m - w, c - r[:, None]), xp.minimum(m + w, c + r[:, None])
    cp = control_points(element, xe)
    clo, chi = cp[0], cp[0]
    for p in cp[1:]:
        clo, chi = xp.minimum(clo, p), xp.maximum(chi, p)
    return xp.maximum(lo, clo), xp.minimum(hi, chi)


def normal_boxes(element, xe, xp=np):
    """Per face, a box [lo, hi] [F, 3] holding unit vectors whose convex hull, up to positive
    factors, holds the face's normal x_xi x x_eta at every point: a face is nowhere facing a
    direction n (n . normal >= 0 everywhere) when the box's smallest dot product with n is not
    negative (self-contact's pruning, which must never drop an admissible face).

    tri3: the one normal. quad4: x_xi x x_eta is affine in (xi, eta) (the xi eta term is
    x_xi's b x b = 0), so the hull of its four corner values holds it. tri6: x_xi and x_eta
    are affine, each in the hull of its corner values A_j, B_k, so the normal is in the hull of
    the nine A_j x B_k. quad8, quad9: on the control net P_ij (`control_points`; i along xi, j
    along eta), x_xi = sum B1_i B2_j 2 (P_(i+1)j - P_ij) and x_eta = sum B2_k B1_l 2
    (P_k(l+1) - P_kl) over Bernstein bases, so x_xi x x_eta is a combination with non-negative
    weights of the 36 cross products of those differences."""
    if element.name == "tri3":
        n = _unit(xp.cross(xe[:, 1] - xe[:, 0], xe[:, 2] - xe[:, 0]), xp)
        return n, n
    if element.name == "quad4":
        gens = [
            _unit(xp.cross(xe[:, (c + 1) % 4] - xe[:, c], xe[:, (c - 1) % 4] - xe[:, c]), xp)
            for c in range(4)
        ]
    elif element.name == "tri6":
        corners = lead(xp, xp.asarray(element.nodes[:3], xe.dtype), 3)
        xi = xp.zeros((xe.shape[0], 3, 2), xe.dtype) + corners
        _, dx = interpolate(element, xe[:, None], xi, xp)
        gens = [
            _unit(xp.cross(dx[:, j, :, 0], dx[:, k, :, 1]), xp) for j in range(3) for k in range(3)
        ]
    else:
        cp = control_points(element, xe)
        net = [[cp[0], cp[7], cp[3]], [cp[4], cp[8], cp[6]], [cp[1], cp[5], cp[2]]]  # [i][j]
        a = [net[i + 1][j] - net[i][j] for i in range(2) for j in range(3)]
        b = [net[k][j + 1] - net[k][j] for k in range(3) for j in range(2)]
        gens = [_unit(xp.cross(u, v), xp) for u in a for v in b]
    lo, hi = gens[0], gens[0]
    for g in gens[1:]:
        lo, hi = xp.minimum(lo, g), xp.maximum(hi, g)
    return lo, hi


def min_dot(n, lo, hi):
    """The smallest n . v over v in the box [lo, hi] (per row, arrays [..., 3])."""
    return 0.5 * (_dot(n, lo + hi) - _dot(abs(n), hi - lo))


def mesh_sizes(element, faces, points, xp=np):
    """Local mesh sizes: per face the mean length of its edges (corner to corner), per node
    the mean of that over the faces around it (zero for unused nodes). Self-contact's `finer`
    flag and node mode compare them (seed 000 section 3, item 5)."""
    k = element.n_corners
    h = 0.0
    for c in range(k):
        d = points[faces[:, (c + 1) % k]] - points[faces[:, c]]
        h = h + xp.sqrt(_dot(d, d))
    h_face = h / k
    nn = faces.shape[1]
    total = segment_sum(xp, xp.repeat(h_face, nn), faces.reshape(-1), points.shape[0])
    count = segment_sum(xp, xp.ones(faces.size, h_face.dtype), faces.reshape(-1), points.shape[0])
    return h_face, total / xp.where(count > 0, count, 1)


def corner_normal(element, dx, corner, xp=np):
    """A face's unit normal times its interior angle at a corner, from the tangents dx
    [..., 3, 2] at that corner (`corner`: an int or int array over the leading axes): the
    terms of the angle-weighted node pseudo-normal (Baerentzen & Aanaes)."""
    k = element.n_corners
    nodes = xp.asarray(element.nodes, dx.dtype)
    # Tangents along the two corner edges, in the natural-coordinate directions of the edges
    # leaving the corner.
    e1 = lead(xp, (nodes[(corner + 1) % k] - nodes[corner])[..., None, :], dx.ndim)
    e2 = lead(xp, (nodes[(corner - 1) % k] - nodes[corner])[..., None, :], dx.ndim)
    t1, t2 = xp.sum(dx * e1, -1), xp.sum(dx * e2, -1)
    w = xp.arctan2(xp.sqrt(xp.sum(xp.cross(t1, t2) ** 2, -1)), xp.sum(t1 * t2, -1))
    return _unit(xp.cross(dx[..., 0], dx[..., 1]), xp) * w[..., None]


def _cross(u, v):
    """u x v of vectors given as their three components."""
    return [u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0]]


def _dot_columns(u, v):
    """u . v of vectors given as their three components."""
    return u[0] * v[0] + u[1] * v[1] + u[2] * v[2]


def _unit_columns(v):
    """`_unit` of vectors given as their three components (NumPy), the same arithmetic."""
    n2 = _dot_columns(v, v)
    ok = n2 > 0
    s = np.sqrt(np.where(ok, n2, 1))
    return [np.where(ok, c / s, 0 * c) for c in v]


def _corner_term(x, i, xp=np):
    """Corner i's term of a linear face's node pseudo-normal, x[node][axis] the face nodes'
    coordinates: with straight edges the tangents at a corner are its two edges and the
    normal there is their cross product (x_xi x x_eta up to a positive factor), here times
    the interior angle over its length (zero if degenerate)."""
    nn = len(x)
    cur, nxt, prv = x[i], x[(i + 1) % nn], x[(i - 1) % nn]
    t1 = [nxt[a] - cur[a] for a in range(3)]
    t2 = [prv[a] - cur[a] for a in range(3)]
    n = _cross(t1, t2)
    s2 = xp.sqrt(_dot_columns(n, n))
    w = xp.arctan2(s2, _dot_columns(t1, t2))
    w = w / xp.where(s2 > 0, s2, 1)
    return [c * w for c in n]


def node_normals(element, faces, points, xp=np):
    """Angle-weighted pseudo-normal at each node [n_points, 3] (zero for unused nodes).

    At a corner, each face contributes its normal there times its interior angle, which gives
    the correct inside/outside sign for points whose closest feature is that vertex
    (Baerentzen & Aanaes). Mid-edge and centre nodes take the plain sum of face normals."""
    e = element
    nf, nn = faces.shape
    if e.linear:
        # Written per coordinate on 1-D arrays (gathers and arithmetic on [F, 3] slices of
        # [F, nn, 3] were 3x slower on NumPy).
        x = [[points[:, a][faces[:, c]] for a in range(3)] for c in range(nn)]
        out = [0.0, 0.0, 0.0]
        for c in range(nn):
            term = _corner_term(x, c, xp)
            for a in range(3):
                out[a] = out[a] + segment_sum(xp, term[a], faces[:, c], points.shape[0])
        return _unit(xp.stack(out, -1), xp)
    xn = xp.asarray(e.nodes, points.dtype)
    xi = xp.zeros((nf, nn, 2), points.dtype) + xn[None]
    xe = points[faces]
    _, dx = interpolate(e, xe[:, None], xi, xp)  # [nf, nn, 3, 2]
    k = e.n_corners
    terms = [corner_normal(e, dx[:, c], c, xp) for c in range(k)]
    terms += [_unit(xp.cross(dx[:, c, :, 0], dx[:, c, :, 1]), xp) for c in range(k, nn)]
    n = xp.stack(terms, 1)  # [nf, nn, 3]
    out = segment_sum(xp, n.reshape(-1, 3), faces.reshape(-1), points.shape[0])
    return _unit(out, xp)


#: Faces a block of `Surface._linear`.
BLOCK = 16384
#: Faces from which `Surface.prepare` makes its tables in threads.
PREPARE_IN_THREADS = 8192
#: The Surface's cached tables that depend on its faces alone (`Surface.with_points`).
_CONNECTIVITY = (
    "nodes",
    "node_faces",
    "_edge_table",
    "boundary_edges",
    "boundary_nodes",
    "closed",
    "connectivity_key",
)


class ConnectivityKey:
    """What a surface and the surfaces `with_points` makes from it share (a weak-referable
    token): a back end keys its tables of the connectivity alone by it."""


def in_threads(fn, items) -> list:
    """[fn(item) for item in items], the items in threads of their own (as many as the cores,
    the first free thread taking the next item): host NumPy work, which releases the GIL in
    its sorts, gathers and arithmetic."""
    items = list(items)
    if len(items) < 2:
        return [fn(q) for q in items]
    with ThreadPoolExecutor(min(len(items), os.cpu_count() or 1)) as pool:
        return list(pool.map(fn, items))


def _stable_order(keys, end):
    """np.argsort(keys, kind="stable") of non-negative int keys below `end`.

    Keys that mostly ascend already (a structured mesh's edges in face order: fewer than a
    quarter smaller than the key 64 places before) go to NumPy's own stable sort, a timsort
    that merges their runs (2-2.5 ms for 2^16-node meshes' 390k edge keys, against 5-10 ms
    by radix passes). Others, by least significant digit first radix passes of 16 bits:
    NumPy's stable argsort of uint16 is a counting sort (6-28 ms where timsort takes 15-40
    on gmsh meshes' or shuffled keys)."""
    keys = np.asarray(keys)
    if len(keys) > 64 and np.count_nonzero(keys[64:] < keys[:-64]) < (len(keys) - 64) / 4:
        return np.argsort(keys, kind="stable")
    order = None
    for shift in range(0, max(int(end) - 1, 1).bit_length(), 16):
        k = keys if order is None else keys[order]
        digit = ((k >> shift) & 0xFFFF).astype(np.uint16)
        o = np.argsort(digit, kind="stable")
        order = o if order is None else order[o]
    return order


def bounds(x):
    """The per-axis minimum and maximum of points x [n, 3], column by column (NumPy's
    x.min(0) over rows of three is 20x slower)."""
    return (
        np.array([x[:, i].min() for i in range(3)]),
        np.array([x[:, i].max() for i in range(3)]),
    )


def in_box(x, lo, hi):
    """Which points x [n, 3] lie in the box [lo, hi] (per column, as `bounds`)."""
    return (
        (x[:, 0] >= lo[0])
        & (x[:, 0] <= hi[0])
        & (x[:, 1] >= lo[1])
        & (x[:, 1] <= hi[1])
        & (x[:, 2] >= lo[2])
        & (x[:, 2] <= hi[2])
    )


def validate_points(points, what="points", copy=True) -> np.ndarray:
    """float64 [n, 3] read-only copy of `points`, or a ValueError naming what is wrong.
    copy=False, for a caller that only reads it: `points` itself where it is float64 already
    (2^20 points: a 24 MB copy less)."""
    a = np.asarray(points)
    if a.dtype == object or a.dtype.kind not in "iuf":
        raise ValueError(f"{what} must be a real numeric array, got dtype {a.dtype}")
    if a.ndim != 2 or a.shape[1] != 3:
        raise ValueError(f"{what} must have shape [n, 3], got {a.shape}")
    a = np.array(a, dtype=np.float64) if copy else np.asarray(a, dtype=np.float64)
    if not np.isfinite(a).all():  # the row only on failure: a reduction over rows is slow
        bad = ~np.isfinite(a).all(1)
        raise ValueError(f"{what} row {int(np.argmax(bad))} is not finite: {a[np.argmax(bad)]}")
    if copy:
        a.setflags(write=False)
    return a


def _validate_faces(faces, n_points) -> np.ndarray:
    f = np.asarray(faces)
    if f.dtype == object or f.dtype.kind not in "iuf":
        raise ValueError(f"faces must be an integer array, got dtype {f.dtype}")
    if f.ndim != 2:
        raise ValueError(f"faces must have shape [n_faces, nodes_per_face], got {f.shape}")
    if f.dtype.kind == "f":
        bad = ~(np.isfinite(f) & (f == np.round(f))).all(1)
        if bad.any():
            r = int(np.argmax(bad))
            raise ValueError(f"faces row {r} holds a non-integral node id: {f[r]}")
    f = f.astype(np.int64)
    if f.size and (f.min() < 0 or f.max() >= n_points):
        bad = ((f < 0) | (f >= n_points)).any(1)
        r = int(np.argmax(bad))
        raise ValueError(f"faces row {r} references a node outside [0, {n_points}): {f[r]}")
    # Repeated nodes by comparing columns pairwise (at most 36 comparisons of 1-D arrays: 5x
    # faster than sorting each row at 2^20 nodes).
    cols = [f[:, i] for i in range(f.shape[1])]
    bad = np.zeros(len(f), bool)
    for i in range(len(cols)):
        for j in range(i + 1, len(cols)):
            bad |= cols[i] == cols[j]
    if bad.any():
        r = int(np.argmax(bad))
        raise ValueError(f"faces row {r} repeats a node: {f[r]}")
    f.setflags(write=False)
    return f


@dataclass(frozen=True, eq=False, init=False)
class Surface:
    """A surface mesh: `points` [n_nodes, 3], `faces` [n_faces, nodes_per_face], `element`.

    Node ids are global: `points` may hold nodes no face uses (a volume mesh's interior), and
    `nodes` lists those that faces use. Immutable; derived data is computed once on first use.
    """

    points: np.ndarray
    faces: np.ndarray
    element: Element

    def __init__(self, points, faces, element=None):
        p = validate_points(points)
        f = _validate_faces(faces, len(p))
        if element is None:
            if f.shape[1] not in NODES_PER_FACE:
                raise ValueError(f"no element has {f.shape[1]} nodes per face")
            element = NODES_PER_FACE[f.shape[1]]
        e = get_element(element)
        if f.shape[1] != e.nodes_per_face:
            raise ValueError(
                f"element {e.name!r} has {e.nodes_per_face} nodes per face, faces have {f.shape[1]}"
            )
        object.__setattr__(self, "points", p)
        object.__setattr__(self, "faces", f)
        object.__setattr__(self, "element", e)

    def __repr__(self):
        return (
            f"Surface({self.element.name}, {self.n_faces} faces, {len(self.nodes)} nodes, "
            f"{'closed' if self.closed else 'open'})"
        )

    def with_points(self, points) -> "Surface":
        """The same connectivity on new coordinates (a deformed configuration). The tables
        of the connectivity alone that this surface has made (edges, node-face table,
        boundary) are shared, not made again: only the geometry is new."""
        s = Surface(points, self.faces, self.element)
        if len(s.points) == len(self.points):
            for name in _CONNECTIVITY:
                if name in self.__dict__:  # (where cached_property keeps its value)
                    s.__dict__[name] = self.__dict__[name]
        return s

    @property
    def n_faces(self) -> int:
        return len(self.faces)

    def prepare(self) -> "Surface":
        """Compute what the NumPy and JAX back ends read from the surface (its topology and
        its face and node geometry) in threads: NumPy releases the GIL in its sorts and
        arithmetic, and the edges, the geometry and the node-face table share no
        intermediate. On two cores, 2^16 rough nodes: 69 -> 37 ms in two chains, 1.1-1.5x
        less again in three. Returns self (everything cached)."""
        # Three chains on the cores' threads, the longest first; on two cores the node-face
        # table goes to the first free thread (it balances them: the edges take twice the
        # geometry's time on gmsh meshes, whose unsorted keys take radix passes, and as long
        # on structured ones).
        chains = [
            ("nodes", "_edge_table", "boundary_nodes", "closed"),
            ("longest_edge", "face_normals", "face_bounds", "node_normals"),
            ("node_faces",),
        ]
        if self.n_faces < PREPARE_IN_THREADS:  # (a thread costs more than they take)
            for name in sum(chains, ()):
                getattr(self, name)
            return self
        in_threads(lambda c: [getattr(self, a) for a in c], chains)
        return self

    @cached_property
    def connectivity_key(self) -> ConnectivityKey:
        """The same object for this surface and every surface `with_points` makes from it
        once this one was asked (the same faces on as many points)."""
        return ConnectivityKey()

    @cached_property
    def nodes(self) -> np.ndarray:
        """Sorted ids of the nodes used by faces."""
        return np.flatnonzero(np.bincount(self.faces.ravel(), minlength=len(self.points)))

    @cached_property
    def node_faces(self) -> tuple[np.ndarray, np.ndarray]:
        """CSR node -> faces over all point ids: the faces of node i are
        ids[offsets[i]:offsets[i + 1]]."""
        flat = self.faces.ravel()
        order = _stable_order(flat, len(self.points))
        ids = order // self.faces.shape[1]
        offsets = np.concatenate([[0], np.cumsum(np.bincount(flat, minlength=len(self.points)))])
        return offsets, ids

    @cached_property
    def _edge_table(self):
        k = self.element.n_corners
        # Local edge i runs from corner i to corner i + 1 (mod k) in every element: the
        # corners' block and its columns rolled (a quarter of the time of take() on them).
        c = self.faces[:, :k]
        a, b = c.ravel(), np.concatenate([c[:, 1:], c[:, :1]], 1).ravel()
        # One int64 key per edge (sorted corner pair): a 1-D unique is much faster than rows.
        lo, hi = np.minimum(a, b), np.maximum(a, b)
        n = max(len(self.points), 1)
        # One stable sort of the keys gives the unique edges, each local edge's edge id, and
        # the faces of each edge in face order.
        keys = lo * n + hi
        order = _stable_order(keys, n * n)
        sk = keys[order]
        new = np.empty(len(sk), bool)  # where a key starts (none if no faces)
        new[:1] = True
        np.not_equal(sk[1:], sk[:-1], out=new[1:])
        first = np.flatnonzero(new)
        counts = np.diff(np.r_[first, len(sk)])
        inverse = np.empty(len(sk), np.int64)
        inverse[order] = np.repeat(np.arange(len(first)), counts)
        at = order[first]
        edges = np.stack([lo[at], hi[at]], -1)
        face_edges = inverse.reshape(-1, k)
        # Up to two faces per edge; a non-manifold edge (3+ faces) keeps its first two.
        second = order[np.minimum(first + 1, len(sk) - 1)] // k
        edge_faces = np.stack([at // k, np.where(counts >= 2, second, -1)], -1)
        return edges, face_edges, edge_faces, counts

    @property
    def edges(self) -> np.ndarray:
        """Unique edges as sorted corner pairs [n_edges, 2]."""
        return self._edge_table[0]

    @property
    def face_edges(self) -> np.ndarray:
        """Edge id of each local edge of each face [n_faces, n_corners]."""
        return self._edge_table[1]

    @property
    def edge_faces(self) -> np.ndarray:
        """The (up to two) faces sharing each edge [n_edges, 2], -1 where there is none."""
        return self._edge_table[2]

    @property
    def edge_counts(self) -> np.ndarray:
        return self._edge_table[3]

    @cached_property
    def boundary_edges(self) -> np.ndarray:
        """Edges used by one face, oriented as in that face [n, 2 or 3] (corners, then mid node)."""
        en = self.element.edge_nodes
        face_local = np.nonzero(self.edge_counts[self.face_edges] == 1)
        return self.faces[face_local[0][:, None], en[face_local[1]]].reshape(-1, en.shape[1])

    @cached_property
    def boundary_nodes(self) -> np.ndarray:
        return np.unique(self.boundary_edges)

    @cached_property
    def node_box(self) -> tuple[np.ndarray, np.ndarray]:
        """The box (lo, hi) of the nodes that faces use."""
        return bounds(self.points[self.nodes])

    @cached_property
    def closed(self) -> bool:
        return bool(self.n_faces) and bool((self.edge_counts == 2).all())

    @cached_property
    def _linear(self):
        """Linear faces' (tri3, quad4) geometry in one pass over blocks of BLOCK faces: unit
        normals [F, 3], ball centres [F, 3] and radii [F], the squared longest edge, and
        each face corner's pseudo-normal term [nn, 3, F] (`node_normals`). Written per
        coordinate on 1-D arrays (3x faster on NumPy than [F, nn, 3] slices), a block at a
        time so that its temporaries stay in the core's cache (the whole face list at once
        ran 3x slower at 2^16 nodes). Each face's arithmetic is that of the functions above,
        in the same order."""
        f, nn, nf = self.faces, self.faces.shape[1], self.n_faces
        axes = [np.ascontiguousarray(self.points[:, a]) for a in range(3)]
        normals, centres = np.empty((nf, 3)), np.empty((nf, 3))
        radii, terms = np.empty(nf), np.empty((nn, 3, nf))
        longest = 0.0
        for lo in range(0, nf, BLOCK):
            hi = min(lo + BLOCK, nf)
            x = [[ax[f[lo:hi, i]] for ax in axes] for i in range(nn)]
            d = {
                (i, j): [x[j][a] - x[i][a] for a in range(3)]
                for i in range(nn)
                for j in range(i + 1, nn)
            }
            longest = max([longest] + [float(_dot_columns(v, v).max()) for v in d.values()])
            c = [sum(x[i][a] for i in range(nn)) / nn for a in range(3)]
            d2 = None
            for i in range(nn):
                e = [x[i][a] - c[a] for a in range(3)]
                e = _dot_columns(e, e)
                d2 = e if d2 is None else np.maximum(d2, e)
            centres[lo:hi] = np.stack(c, -1)
            radii[lo:hi] = self.element.lebesgue * np.sqrt(np.where(d2 > 0, d2, 0 * d2))
            if nn == 4:  # face_normals' closed form: the diagonals' (x2 - x0) x (x3 - x1)
                normals[lo:hi] = np.stack(_unit_columns(_cross(d[0, 2], d[1, 3])), -1)
                terms[:, :, lo:hi] = [_corner_term(x, i) for i in range(nn)]
            else:
                # A triangle's normal is the same at its three corners, (x1 - x0) x (x2 - x0)
                # (face_normals'), its length that of each corner's edges' cross product.
                n = _cross(d[0, 1], d[0, 2])
                s2 = np.sqrt(_dot_columns(n, n))
                u = _unit_columns(n)
                normals[lo:hi] = np.stack(u, -1)
                m = [[-v for v in d[0, 1]], [-v for v in d[0, 2]], [-v for v in d[1, 2]]]
                corners = ((d[0, 1], d[0, 2]), (d[1, 2], m[0]), (m[1], m[2]))  # (t1, t2)
                for i, (t1, t2) in enumerate(corners):
                    w = np.arctan2(s2, _dot_columns(t1, t2))
                    terms[i, :, lo:hi] = [c * w for c in u]
        return normals, centres, radii, longest, terms

    @cached_property
    def longest_edge(self) -> float:
        """The largest distance between two nodes of one face (seed 000, eq. 2)."""
        if self.n_faces == 0:
            return 0.0
        if self.element.linear:
            return self._linear[3] ** 0.5
        xe = self.points[self.faces]
        i, j = np.triu_indices(xe.shape[1], 1)
        return float(np.sqrt(_dot(xe[:, i] - xe[:, j], xe[:, i] - xe[:, j]).max()))

    @cached_property
    def face_normals(self) -> np.ndarray:
        """Unit outward normal at each face's centre (zero for a degenerate face)."""
        if self.element.linear:
            return self._linear[0]
        return face_normals(self.element, self.points[self.faces])

    @cached_property
    def face_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Centre and radius of a ball holding each face (see `face_bounds`)."""
        if self.element.linear:
            return self._linear[1], self._linear[2]
        return face_bounds(self.element, self.points[self.faces])

    @cached_property
    def node_normals(self) -> np.ndarray:
        """Angle-weighted pseudo-normal at each node (see `node_normals`)."""
        if not self.element.linear:
            return node_normals(self.element, self.faces, self.points)
        terms, n = self._linear[4], len(self.points)
        out = [0.0, 0.0, 0.0]
        for i in range(self.faces.shape[1]):
            for a in range(3):
                out[a] = out[a] + segment_sum(np, terms[i, a], self.faces[:, i], n)
        return np.stack(_unit_columns(out), -1)
