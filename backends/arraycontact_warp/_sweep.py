"""Swept detection in Warp: the certified search of arraycontact._sweep (read its docstring for
the method and its guarantee) as `@wp.func`s, the faces' capture boxes in the size-adaptive
tree (_grid), and one kernel a slave that walks the tree with its segment (_grid.Segment) and
searches every face whose capture box the segment meets, keeping the earliest contact.

The search of a pair is depth first over boxes of (s, w, t), stepping to the next pending box
by the path's split axes (no stack in local memory); faces are searched one after the other,
each bounded by the earliest contact found so far plus the tie band (boxes that start later
cannot matter). A triangle's search starts from a slab of time around the first root of its
coplanarity cubic (_narrow); so Warp's toi may differ from NumPy's within t_tol (another box
sequence), with the same guarantee."""

from __future__ import annotations

from typing import Any

import warp as wp

from arraycontact._sweep import CONTRACTIONS, DEPTH, ROUND, VISITS

from ._geometry import (
    EDGE,
    FACE,
    VERTEX,
    Element,
    FaceNodes,
    Quads,
    Triangles,
    _corner_weights,
    _row,
    coefficients,
    face_nodes,
    is_bilinear,
    make_struct,
    polynomial,
    set_node,
    shape,
    straight,
    unit_cross,
)
from ._grid import (
    Grid,
    Segment,
    W,
    children,
    descend,
    enters,
    entry,
    item_hi,
    item_id,
    item_lo,
    item_world,
    meets,
    morton_key,
    next_pending,
    slot,
    write_item,
)
from ._prepare import face_bounds
from ._real import EPS, real, vec2, vec3, vec4

wp.set_module_options({"enable_backward": False, "max_unroll": 1})

#: A budget of boxes no search reaches (a search stops at VISITS boxes a slab).
ALL_BOXES = 1 << 30

#: The tie band's faces a slave keeps (faces within t_tol of its earliest contact).
BAND = 8
BandF = wp.types.vector(length=BAND, dtype=int)
BandT = wp.types.vector(length=BAND, dtype=real)
BandX = wp.types.matrix(shape=(BAND, 2), dtype=real)
Box6 = wp.types.vector(length=6, dtype=real)


@wp.func
def _natural(el: Triangles, s: real, w: real):
    return vec2(s, w)


@wp.func
def _natural(el: Quads, s: real, w: real):  # noqa: F811 (a Warp overload)
    return vec2(real(2.0) * s - real(1.0), real(2.0) * w - real(1.0))


@wp.func
def _natural(el: Any, s: real, w: real):  # noqa: F811
    if el.n_corners == 3:
        return vec2(s, w)
    return vec2(real(2.0) * s - real(1.0), real(2.0) * w - real(1.0))


@wp.func
def _outside(q: Any, b: Box6):
    """arraycontact._sweep.outside: wholly past a triangle's diagonal."""
    return _pair_tri(q) and b[0] + b[2] > real(1.0)


@wp.func
def _ab(el: Triangles, xa: FaceNodes, va: FaceNodes, p: vec3, v: vec3, xi: vec2):
    """A(xi) = x(xi) at t = 0 less the node, B(xi) = the face point's motion less the node's."""
    n0 = real(1.0) - xi[0] - xi[1]
    a = n0 * _row(xa, 0) + xi[0] * _row(xa, 1) + xi[1] * _row(xa, 2) - p
    b = n0 * _row(va, 0) + xi[0] * _row(va, 1) + xi[1] * _row(va, 2) - v
    return a, b


@wp.func
def _ab(el: Any, xa: FaceNodes, va: FaceNodes, p: vec3, v: vec3, xi: vec2):  # noqa: F811
    a = -p
    b = -v
    if is_bilinear(el):  # the loop below written out (_geometry._corner_weights)
        n0, n1, n2, n3 = _corner_weights(xi)
        a = a + n0 * xa.x0 + n1 * xa.x1 + n2 * xa.x2 + n3 * xa.x3
        b = b + n0 * va.x0 + n1 * va.x1 + n2 * va.x2 + n3 * va.x3
        return a, b
    # Other faces: xa and va hold their monomials' coefficients (_pair: `coefficients`), on
    # which an evaluation is a fixed polynomial, not nn shape functions of n_mono terms each
    # (Warp's CPU device, a closing step of the rough surfaces at 2^12, one `detect_swept`:
    # tri6 157 -> 71 ms, quad8 279 -> 92 ms, quad9 396 -> 103 ms, the same hits).
    return a + polynomial(xa, xi), b + polynomial(va, xi)


@wp.func
def _grade(el: Triangles):
    return 2


@wp.func
def _grade(el: Any):  # noqa: F811
    if straight(el):
        return 2
    return 3


@wp.func
def _bernstein(f: FaceNodes, g: int, i0: int, stride: int):
    """Rows i0, i0 + stride, i0 + 2 stride of f (values at an axis's ends and middle) to
    degree-2 Bernstein coefficients (arraycontact._sweep._bernstein)."""
    f0 = _row(f, i0)
    fm = _row(f, i0 + stride)
    f1 = _row(f, i0 + 2 * stride)
    return set_node(f, i0 + stride, real(2.0) * fm - real(0.5) * (f0 + f1))


@wp.struct
class TriPair:
    """A (node, tri3 face) pair in its frame: F = a + xi e1 + eta e2 + t (b + xi u1 + eta u2);
    the face normals at both ends of the step, the rounding margin and contact tolerance."""

    a: vec3
    e1: vec3
    e2: vec3
    b: vec3
    u1: vec3
    u2: vec3
    n0: vec3
    n1: vec3
    margin: real
    delta: real
    g: vec4  # the coplanarity cubic on [0, 1] (_coplanarity) and its rounding bound
    g_margin: real
    r: int  # the face's corner at the origin (_corner_shift)


#: A (node, face) pair of any element in its frame: face nodes xa at t = 0 and their motion
#: va, the node's p and v; as TriPair's the rest. One struct per element struct (el's type).
_CURVED_PAIR_FIELDS = {
    "xa": FaceNodes,
    "va": FaceNodes,
    "p": vec3,
    "v": vec3,
    "n0": vec3,
    "n1": vec3,
    "margin": real,
    "delta": real,
    "r": int,  # a triangle's corner at the origin (_corner_shift); 0 for quads
    "band": int,  # 1: a bilinear quad, h1 and h2 set (_band)
    "h1": vec4,
    "h2": vec4,
    "h_margin": real,
}
CurvedPair = make_struct(
    "CurvedPair", {"el": Element, **_CURVED_PAIR_FIELDS}, "A pair of any element.", __name__
)
#: quad4's (its functions specialised on Quads: no curved-face code, as the static scans)
QuadPair = make_struct(
    "QuadPair", {"el": Quads, **_CURVED_PAIR_FIELDS}, "A pair of a quad4 face.", __name__
)


@wp.func
def _new_pair(el: Element):
    return CurvedPair()


@wp.func
def _new_pair(el: Quads):  # noqa: F811 (a Warp overload)
    return QuadPair()


@wp.func
def _cos2(a: vec3, b: vec3):
    den = wp.dot(a, a) * wp.dot(b, b)
    if den > real(0.0):
        return wp.dot(a, b) * wp.dot(a, b) / den
    return real(1.0)


@wp.func
def _corner_shift(a: vec3, b: vec3, c: vec3):
    """arraycontact._sweep.corner_shift: the corner of (a, b, c) whose edges are nearest
    orthogonal, the first of equals (the search's (s, w) start there)."""
    ca = _cos2(b - a, c - a)
    cb = _cos2(c - b, a - b)
    cc = _cos2(a - c, b - c)
    if ca <= cb and ca <= cc:
        return 0
    if cb <= cc:
        return 1
    return 2


@wp.func
def _from_corner(a: vec3, b: vec3, c: vec3, r: int):
    """A triangle's corners (a, b, c) in the order that starts at corner r."""
    if r == 1:
        return b, c, a
    if r == 2:
        return c, a, b
    return a, b, c


@wp.func
def _node(f: int, i: int, r: int, faces: wp.array2d(dtype=int)):
    """Node i of face f's order from corner r (arraycontact._sweep.SHIFTS; r = 0: the face's
    own order, the only one of quads, whose nodes past the sixth the shift's arithmetic
    would wrap)."""
    if r == 0:
        return faces[f, i]
    if i < 3:
        return faces[f, (i + r) % 3]
    return faces[f, 3 + (i - 3 + r) % 3]


@wp.func
def _unshift(xi: vec2, r: int):
    """(s, w) of the order from corner r in the face's own (arraycontact._sweep.unshifted)."""
    u = real(1.0) - xi[0] - xi[1]
    if r == 1:
        return vec2(u, xi[0])
    if r == 2:
        return vec2(xi[1], u)
    return xi


@wp.func
def _scale(x: vec3, s: real):
    return wp.max(s, wp.max(wp.abs(x[0]), wp.max(wp.abs(x[1]), wp.abs(x[2]))))


@wp.func
def _pair(
    el: Triangles,
    x0: wp.array(dtype=vec3),
    x1: wp.array(dtype=vec3),
    faces: wp.array2d(dtype=int),
    f: int,
    s0: vec3,
    s1: vec3,
    space_rtol: real,
):
    """Face f and the node moving from s0 to s1 as a pair, the face's corner r at t = 0 the
    origin (_corner_shift)."""
    # (each corner read once: this runs for every pair the GPU searches)
    c0, c1, c2 = x0[faces[f, 0]], x0[faces[f, 1]], x0[faces[f, 2]]
    r = _corner_shift(c0, c1, c2)
    o, y1, y2 = _from_corner(c0, c1, c2, r)
    p1, x1f1, x1f2 = _from_corner(x1[faces[f, 0]], x1[faces[f, 1]], x1[faces[f, 2]], r)
    q = TriPair()
    q.r = r
    q.a = o - s0
    q.e1 = y1 - o
    q.e2 = y2 - o
    v0 = p1 - o
    q.b = v0 - (s1 - s0)
    q.u1 = x1f1 - o - q.e1 - v0
    q.u2 = x1f2 - o - q.e2 - v0
    sc = _scale(q.e1, _scale(q.e2, _scale(v0, real(0.0))))
    sc = _scale(q.e1 + q.u1 + v0, _scale(q.e2 + q.u2 + v0, sc))
    sc = _scale(s0 - o, _scale(s1 - o, sc))
    q.n0 = wp.normalize(wp.cross(q.e1, q.e2))
    q.n1 = wp.normalize(wp.cross(q.e1 + q.u1, q.e2 + q.u2))
    q.margin = real(ROUND) * EPS * sc
    q.delta = wp.max(space_rtol * sc, real(4.0) * q.margin)
    g, gm = _coplanarity(q.e1, x1f1 - p1, q.e2, x1f2 - p1, q.a, p1 - s1)
    q.g = g
    q.g_margin = gm
    return q


@wp.func
def _motion(q: Any, xb: FaceNodes, o: vec3, s0: vec3, s1: vec3, sc: real, space_rtol: real):
    """A pair's node in the frame at o, its face's end normals (xa in q, xb at t = 1), its
    rounding margin and contact tolerance (sc: the face nodes' largest coordinate so far)."""
    q.p = s0 - o
    q.v = s1 - s0
    sc = _scale(q.p, _scale(q.p + q.v, sc))
    q.n0 = _normal(q.el, q.xa, q.el.centre)
    q.n1 = _normal(q.el, xb, q.el.centre)
    q.margin = real(ROUND) * EPS * sc
    q.delta = wp.max(space_rtol * sc, real(4.0) * q.margin)
    return q


# quad4's pair set-up and box test written out on the node fields, in the generic code's
# arithmetic and order (the same answers bit for bit): the generic loops pick each node's
# field at run time, which a GPU thread pays in selects (as the static scans' quad4 code).
@wp.func
def _pair(  # noqa: F811 (a Warp overload)
    el: Quads,
    x0: wp.array(dtype=vec3),
    x1: wp.array(dtype=vec3),
    faces: wp.array2d(dtype=int),
    f: int,
    s0: vec3,
    s1: vec3,
    space_rtol: real,
):
    i0, i1, i2, i3 = faces[f, 0], faces[f, 1], faces[f, 2], faces[f, 3]
    o = x0[i0]
    a0, a1, a2, a3 = x0[i0] - o, x0[i1] - o, x0[i2] - o, x0[i3] - o
    b0, b1, b2, b3 = x1[i0] - o, x1[i1] - o, x1[i2] - o, x1[i3] - o
    sc = _scale(a0, _scale(b0, real(0.0)))
    sc = _scale(a1, _scale(b1, sc))
    sc = _scale(a2, _scale(b2, sc))
    sc = _scale(a3, _scale(b3, sc))
    xa = FaceNodes()
    xa.x0 = a0
    xa.x1 = a1
    xa.x2 = a2
    xa.x3 = a3
    va = FaceNodes()
    va.x0 = b0 - a0
    va.x1 = b1 - a1
    va.x2 = b2 - a2
    va.x3 = b3 - a3
    xb = FaceNodes()
    xb.x0 = b0
    xb.x1 = b1
    xb.x2 = b2
    xb.x3 = b3
    q = QuadPair()
    q.el = el
    q.r = 0
    q.xa = xa
    q.va = va
    return _band(_motion(q, xb, o, s0, s1, sc, space_rtol), xb)


@wp.func
def _pair(  # noqa: F811 (a Warp overload)
    el: Any,
    x0: wp.array(dtype=vec3),
    x1: wp.array(dtype=vec3),
    faces: wp.array2d(dtype=int),
    f: int,
    s0: vec3,
    s1: vec3,
    space_rtol: real,
):
    r = int(0)
    if el.n_corners == 3:
        r = _corner_shift(x0[faces[f, 0]], x0[faces[f, 1]], x0[faces[f, 2]])
    o = x0[_node(f, 0, r, faces)]
    q = _new_pair(el)
    q.el = el
    q.r = r
    xb = FaceNodes()
    sc = real(0.0)
    for i in range(el.nn):
        a = x0[_node(f, i, r, faces)] - o
        b = x1[_node(f, i, r, faces)] - o
        q.xa = set_node(q.xa, i, a)
        q.va = set_node(q.va, i, b - a)
        xb = set_node(xb, i, b)
        sc = _scale(a, _scale(b, sc))
    q = _motion(q, xb, o, s0, s1, sc, space_rtol)
    q.band = 0
    if is_bilinear(el):
        q = _band(q, xb)
    q.xa = coefficients(el, q.xa)  # (what _ab reads: a bilinear face's nodes kept)
    q.va = coefficients(el, q.va)
    return q


@wp.func
def _band(q: Any, xb: FaceNodes):
    """A bilinear quad's twist band. With c its centroid, n = d1 x d2 (its diagonals) and w =
    (x0 - x1 + x2 - x3) / 4, corners 0 and 2 lie at height w . n above the plane through c
    normal to n and corners 1 and 3 as far below, so every point of the face has
    |(x - c) . n| <= |w . n|, and a node on it |g| <= |tau| with g = (p - c) . n, tau = w . n:
    h1 = g + tau and h2 = g - tau, cubics in t (det(d1, d2, p - c +- w), _coplanarity), of
    opposite signs or zero. Their margin holds the factors' rounding (two more operations than
    _coplanarity's, doubled) and the search's contact tolerance delta (a node within delta of
    the face: |g| <= |tau| + 1.8 delta |n|, |n| <= 3 ne^2)."""
    a0, a1, a2, a3 = q.xa.x0, q.xa.x1, q.xa.x2, q.xa.x3
    b0, b1, b2, b3 = xb.x0, xb.x1, xb.x2, xb.x3
    e0 = q.p - real(0.25) * (a0 + a1 + a2 + a3)
    e1 = q.p + q.v - real(0.25) * (b0 + b1 + b2 + b3)
    w0 = real(0.25) * (a0 - a1 + a2 - a3)
    w1 = real(0.25) * (b0 - b1 + b2 - b3)
    h1, m1 = _coplanarity(a2 - a0, b2 - b0, a3 - a1, b3 - b1, e0 + w0, e1 + w1)
    h2, m2 = _coplanarity(a2 - a0, b2 - b0, a3 - a1, b3 - b1, e0 - w0, e1 - w1)
    ne = wp.max(wp.max(_inf(a2 - a0), _inf(b2 - b0)), wp.max(_inf(a3 - a1), _inf(b3 - b1)))
    q.band = 1
    q.h1 = h1
    q.h2 = h2
    q.h_margin = real(2.0) * wp.max(m1, m2) + real(6.0) * q.delta * ne * ne
    return q


@wp.func
def _f(q: TriPair, s: real, w: real, t: real):
    """F at (s, w, t)."""
    return q.a + s * q.e1 + w * q.e2 + t * (q.b + s * q.u1 + w * q.u2)


@wp.func
def _f(q: Any, s: real, w: real, t: real):  # noqa: F811
    a, b = _ab(q.el, q.xa, q.va, q.p, q.v, _natural(q.el, s, w))
    return a + t * b


@wp.struct
class Jac:
    """Bounds of F's Jacobian over a box, a column (derivative along s, w, t) at a time."""

    s_lo: vec3
    s_hi: vec3
    w_lo: vec3
    w_hi: vec3
    t_lo: vec3
    t_hi: vec3


@wp.struct
class Hull:
    """A box's control points summed up: their box (lo, hi) and their range along the face
    normals at both ends of the step (q0, q1: (lo, hi) pairs)."""

    lo: vec3
    hi: vec3
    q0: vec2
    q1: vec2


@wp.func
def _hull_start():
    h = Hull()
    h.lo = vec3(real(3.0e38))
    h.hi = vec3(real(-3.0e38))
    h.q0 = vec2(real(3.0e38), real(-3.0e38))
    h.q1 = vec2(real(3.0e38), real(-3.0e38))
    return h


@wp.func
def _take(h: Hull, f: vec3, n0: vec3, n1: vec3):
    h.lo = wp.min(h.lo, f)
    h.hi = wp.max(h.hi, f)
    a = wp.dot(f, n0)
    b = wp.dot(f, n1)
    h.q0 = vec2(wp.min(h.q0[0], a), wp.max(h.q0[1], a))
    h.q1 = vec2(wp.min(h.q1[0], b), wp.max(h.q1[1], b))
    return h


@wp.func
def _inf(d: vec3):
    return wp.max(wp.abs(d[0]), wp.max(wp.abs(d[1]), wp.abs(d[2])))


@wp.func
def _verdict(h: Hull, margin: real, ds: real, dw: real, dt: real):
    """(excluded, hull extent, split axis) from the hull and the spreads."""
    out = h.q0[0] > margin or h.q0[1] < -margin or h.q1[0] > margin or h.q1[1] < -margin
    out = out or h.lo[0] > margin or h.lo[1] > margin or h.lo[2] > margin
    out = out or h.hi[0] < -margin or h.hi[1] < -margin or h.hi[2] < -margin
    extent = wp.max(h.hi[0] - h.lo[0], wp.max(h.hi[1] - h.lo[1], h.hi[2] - h.lo[2]))
    axis = int(0)
    if dw > ds:
        axis = 1
    if dt > wp.max(ds, dw):
        axis = 2
    return out, extent, axis


@wp.func
def _examine(q: TriPair, box: Box6):
    """arraycontact._sweep.examine (and the Jacobian's bounds) for one box of a triangle,
    written out: the control points are F's values at the box's 8 corners. Returns
    (excluded, hull extent, split axis, Jac)."""
    a00 = q.a + box[0] * q.e1 + box[2] * q.e2
    a10 = a00 + (box[1] - box[0]) * q.e1
    a01 = a00 + (box[3] - box[2]) * q.e2
    a11 = a10 + (box[3] - box[2]) * q.e2
    b00 = q.b + box[0] * q.u1 + box[2] * q.u2
    b10 = b00 + (box[1] - box[0]) * q.u1
    b01 = b00 + (box[3] - box[2]) * q.u2
    b11 = b10 + (box[3] - box[2]) * q.u2
    h = _hull_start()
    for e in range(2):
        t = box[4 + e]
        h = _take(h, a00 + t * b00, q.n0, q.n1)
        h = _take(h, a10 + t * b10, q.n0, q.n1)
        h = _take(h, a01 + t * b01, q.n0, q.n1)
        h = _take(h, a11 + t * b11, q.n0, q.n1)
    ds0 = q.e1 + box[4] * q.u1
    ds1 = q.e1 + box[5] * q.u1
    dw0 = q.e2 + box[4] * q.u2
    dw1 = q.e2 + box[5] * q.u2
    j = Jac()
    j.s_lo = wp.min(ds0, ds1)
    j.s_hi = wp.max(ds0, ds1)
    j.w_lo = wp.min(dw0, dw1)
    j.w_hi = wp.max(dw0, dw1)
    j.t_lo = wp.min(wp.min(b00, b10), wp.min(b01, b11))
    j.t_hi = wp.max(wp.max(b00, b10), wp.max(b01, b11))
    ds = (box[1] - box[0]) * wp.max(_inf(ds0), _inf(ds1))
    dw = (box[3] - box[2]) * wp.max(_inf(dw0), _inf(dw1))
    dt = (box[5] - box[4]) * wp.max(wp.max(_inf(b00), _inf(b10)), wp.max(_inf(b01), _inf(b11)))
    out, extent, axis = _verdict(h, q.margin, ds, dw, dt)
    return out, extent, axis, j


@wp.func
def _quad_rows(h: Hull, j: Jac, f00: vec3, f01: vec3, f10: vec3, f11: vec3, q: QuadPair, box: Box6):
    """One time end of _examine(QuadPair): F's control points at the box's four (s, w)
    corners (f_ij: s's i-th, w's j-th) into the hull, their differences into the Jacobian's
    bounds (as the generic loop takes them)."""
    h = _take(h, f00, q.n0, q.n1)
    h = _take(h, f01, q.n0, q.n1)
    h = _take(h, f10, q.n0, q.n1)
    h = _take(h, f11, q.n0, q.n1)
    ws = box[1] - box[0]
    ww = box[3] - box[2]
    d0 = f10 - f00
    d1 = f11 - f01
    ds = wp.max(_inf(d0), _inf(d1))
    j.s_lo = wp.min(j.s_lo, wp.min(real(1.0) * d0 / ws, real(1.0) * d1 / ws))
    j.s_hi = wp.max(j.s_hi, wp.max(real(1.0) * d0 / ws, real(1.0) * d1 / ws))
    d0 = f01 - f00
    d1 = f11 - f10
    dw = wp.max(_inf(d0), _inf(d1))
    j.w_lo = wp.min(j.w_lo, wp.min(real(1.0) * d0 / ww, real(1.0) * d1 / ww))
    j.w_hi = wp.max(j.w_hi, wp.max(real(1.0) * d0 / ww, real(1.0) * d1 / ww))
    return h, j, ds, dw


@wp.func
def _examine(q: QuadPair, box: Box6):  # noqa: F811 (a Warp overload)
    """_examine of a bilinear quad: its control points over a box are F at the box's four
    (s, w) corners, at both ends of its time (the generic code's 2 x 2 loop written out)."""
    el = q.el
    s1 = box[0] + (box[1] - box[0]) * real(1.0) * real(1.0)
    w1 = box[2] + (box[3] - box[2]) * real(1.0) * real(1.0)
    s0 = box[0] + (box[1] - box[0]) * real(0.0) * real(1.0)
    w0 = box[2] + (box[3] - box[2]) * real(0.0) * real(1.0)
    a00, b00 = _ab(el, q.xa, q.va, q.p, q.v, _natural(el, s0, w0))
    a01, b01 = _ab(el, q.xa, q.va, q.p, q.v, _natural(el, s0, w1))
    a10, b10 = _ab(el, q.xa, q.va, q.p, q.v, _natural(el, s1, w0))
    a11, b11 = _ab(el, q.xa, q.va, q.p, q.v, _natural(el, s1, w1))
    j = Jac()
    j.s_lo = vec3(real(3.0e38))
    j.s_hi = vec3(real(-3.0e38))
    j.w_lo = vec3(real(3.0e38))
    j.w_hi = vec3(real(-3.0e38))
    h = _hull_start()
    t = box[4]
    h, j, ds, dw = _quad_rows(
        h, j, a00 + t * b00, a01 + t * b01, a10 + t * b10, a11 + t * b11, q, box
    )
    t = box[5]
    h, j, ds2, dw2 = _quad_rows(
        h, j, a00 + t * b00, a01 + t * b01, a10 + t * b10, a11 + t * b11, q, box
    )
    ds = wp.max(ds, ds2)
    dw = wp.max(dw, dw2)
    dt = (box[5] - box[4]) * wp.max(wp.max(_inf(b00), _inf(b01)), wp.max(_inf(b10), _inf(b11)))
    j.t_lo = wp.min(wp.min(b00, b01), wp.min(b10, b11))
    j.t_hi = wp.max(wp.max(b00, b01), wp.max(b10, b11))
    out, extent, axis = _verdict(h, q.margin, ds, dw, dt)
    return out, extent, axis, j


@wp.func
def _examine(q: Any, box: Box6):  # noqa: F811 (a Warp overload)
    """arraycontact._sweep.examine for one box (and the Jacobian's bounds: the hull of the
    derivatives' Bernstein coefficients, differences of the control points)."""
    el = q.el
    g = _grade(el)
    a = FaceNodes()
    b = FaceNodes()
    h1 = real(1.0) / real(g - 1)
    for i in range(g):
        for jj in range(g):
            s = box[0] + (box[1] - box[0]) * real(i) * h1
            w = box[2] + (box[3] - box[2]) * real(jj) * h1
            ai, bi = _ab(el, q.xa, q.va, q.p, q.v, _natural(el, s, w))
            a = set_node(a, i * g + jj, ai)
            b = set_node(b, i * g + jj, bi)
    if g == 3:
        for jj in range(3):
            a = _bernstein(a, 3, jj, 3)
            b = _bernstein(b, 3, jj, 3)
        for i in range(3):
            a = _bernstein(a, 3, 3 * i, 1)
            b = _bernstein(b, 3, 3 * i, 1)
    j = Jac()
    j.s_lo = vec3(real(3.0e38))
    j.s_hi = vec3(real(-3.0e38))
    j.w_lo = vec3(real(3.0e38))
    j.w_hi = vec3(real(-3.0e38))
    j.t_lo = vec3(real(3.0e38))
    j.t_hi = vec3(real(-3.0e38))
    h = _hull_start()
    ds = real(0.0)
    dw = real(0.0)
    dt = real(0.0)
    for i in range(g):
        for jj in range(g):
            k = i * g + jj
            for e in range(2):
                f = _row(a, k) + box[4 + e] * _row(b, k)
                h = _take(h, f, q.n0, q.n1)
                if i + 1 < g:
                    d = _row(a, k + g) + box[4 + e] * _row(b, k + g) - f
                    ds = wp.max(ds, _inf(d))
                    d = real(g - 1) * d / (box[1] - box[0])
                    j.s_lo = wp.min(j.s_lo, d)
                    j.s_hi = wp.max(j.s_hi, d)
                if jj + 1 < g:
                    d = _row(a, k + 1) + box[4 + e] * _row(b, k + 1) - f
                    dw = wp.max(dw, _inf(d))
                    d = real(g - 1) * d / (box[3] - box[2])
                    j.w_lo = wp.min(j.w_lo, d)
                    j.w_hi = wp.max(j.w_hi, d)
            dt = wp.max(dt, (box[5] - box[4]) * _inf(_row(b, k)))
            j.t_lo = wp.min(j.t_lo, _row(b, k))
            j.t_hi = wp.max(j.t_hi, _row(b, k))
    out, extent, axis = _verdict(h, q.margin, ds, dw, dt)
    return out, extent, axis, j


@wp.func
def _mag(y: vec3, lo: vec3, hi: vec3, d: real):
    """max |d - (Y J)_ij| over the interval column [lo, hi] of J, for row y of Y."""
    yp = wp.max(y, vec3(real(0.0)))
    yn = wp.min(y, vec3(real(0.0)))
    a = wp.dot(yp, lo) + wp.dot(yn, hi)
    b = wp.dot(yp, hi) + wp.dot(yn, lo)
    return wp.max(wp.abs(d - a), wp.abs(d - b))


@wp.func
def _k_row(y: vec3, j: Jac, d: vec3, rr: vec3, mid: real, yf: real, margin: real):
    """Row l of Krawczyk's K, l K (d = l, y = l Y, mid = l m, yf = l Y F(m)): (lo, hi)."""
    rad = _mag(y, j.s_lo, j.s_hi, d[0]) * rr[0]
    rad += _mag(y, j.w_lo, j.w_hi, d[1]) * rr[1]
    rad += _mag(y, j.t_lo, j.t_hi, d[2]) * rr[2]
    ay = wp.abs(y[0]) + wp.abs(y[1]) + wp.abs(y[2])
    rad += real(4.0) * ay * margin + real(16.0) * EPS * (wp.abs(mid) + wp.abs(yf) + rad)
    return mid - yf - rad, mid - yf + rad


@wp.func
def _krawczyk(q: Any, box: Box6, j: Jac):
    """arraycontact._sweep.krawczyk for one box: (empty, inside, the box X & K, within)."""
    tri = _pair_tri(q)
    a = real(0.5) * (j.s_lo + j.s_hi)
    b = real(0.5) * (j.w_lo + j.w_hi)
    c = real(0.5) * (j.t_lo + j.t_hi)
    r0 = wp.cross(b, c)
    r1 = wp.cross(c, a)
    r2 = wp.cross(a, b)
    det = wp.dot(a, r0)
    unknown = not tri or box[1] + box[3] <= real(1.0)  # `within` when K says nothing
    if not (wp.abs(det) > real(0.0)):
        return False, False, box, unknown
    r0 = r0 / det
    r1 = r1 / det
    r2 = r2 / det
    mid = vec3(
        real(0.5) * (box[0] + box[1]), real(0.5) * (box[2] + box[3]), real(0.5) * (box[4] + box[5])
    )
    rr = vec3(
        real(0.5) * (box[1] - box[0]), real(0.5) * (box[3] - box[2]), real(0.5) * (box[5] - box[4])
    )
    f = _f(q, mid[0], mid[1], mid[2])
    one = real(1.0)
    zero = real(0.0)
    lo0, hi0 = _k_row(r0, j, vec3(one, zero, zero), rr, mid[0], wp.dot(r0, f), q.margin)
    lo1, hi1 = _k_row(r1, j, vec3(zero, one, zero), rr, mid[1], wp.dot(r1, f), q.margin)
    lo2, hi2 = _k_row(r2, j, vec3(zero, zero, one), rr, mid[2], wp.dot(r2, f), q.margin)
    lo3 = zero
    hi3 = zero
    if tri:  # s + w, well determined on a sliver where s and w are not
        y3 = r0 + r1
        lo3, hi3 = _k_row(y3, j, vec3(one, one, zero), rr, mid[0] + mid[1], wp.dot(y3, f), q.margin)
    if not (wp.isfinite(lo0 + hi0) and wp.isfinite(lo1 + hi1) and wp.isfinite(lo2 + hi2)):
        return False, False, box, unknown
    if not wp.isfinite(lo3 + hi3):
        return False, False, box, unknown
    empty = hi0 < box[0] or lo0 > box[1] or hi1 < box[2] or lo1 > box[3]
    empty = empty or hi2 < box[4] or lo2 > box[5]
    inside = lo0 > box[0] and hi0 < box[1] and lo1 > box[2] and hi1 < box[3]
    inside = inside and lo2 > box[4] and hi2 < box[5]
    out = Box6(
        wp.max(box[0], lo0),
        wp.min(box[1], hi0),
        wp.max(box[2], lo1),
        wp.min(box[3], hi1),
        wp.max(box[4], lo2),
        wp.min(box[5], hi2),
    )
    within = True
    if tri:
        empty = empty or lo3 > one or out[0] + out[2] > one
        within = hi3 <= one or out[1] + out[3] <= one
    return empty, inside, out, within


@wp.func
def _normal(el: Quads, x: FaceNodes, xi: vec2):
    """_normal of a quad4, its loop over the nodes written out (the same arithmetic)."""
    t0 = vec3(0.0)
    t1 = vec3(0.0)
    sf, d0, d1, h00, h01, h11 = shape(el, xi, 0)
    t0 += d0 * x.x0
    t1 += d1 * x.x0
    sf, d0, d1, h00, h01, h11 = shape(el, xi, 1)
    t0 += d0 * x.x1
    t1 += d1 * x.x1
    sf, d0, d1, h00, h01, h11 = shape(el, xi, 2)
    t0 += d0 * x.x2
    t1 += d1 * x.x2
    sf, d0, d1, h00, h01, h11 = shape(el, xi, 3)
    t0 += d0 * x.x3
    t1 += d1 * x.x3
    return unit_cross(t0, t1)


@wp.func
def _normal(el: Any, x: FaceNodes, xi: vec2):  # noqa: F811
    """The unit normal x_xi x x_eta at xi (zero where degenerate)."""
    t0 = vec3(0.0)
    t1 = vec3(0.0)
    for i in range(_nodes(el)):
        sf, d0, d1, h00, h01, h11 = _shape(el, xi, i)
        t0 += d0 * _row(x, i)
        t1 += d1 * _row(x, i)
    return unit_cross(t0, t1)


@wp.func
def _nodes(el: Triangles):
    return 3


@wp.func
def _nodes(el: Any):  # noqa: F811
    return el.nn


@wp.func
def _shape(el: Triangles, xi: vec2, i: int):
    """tri3's N_i and its derivatives (the layout of _geometry.shape)."""
    z = real(0.0)
    if i == 0:
        return real(1.0) - xi[0] - xi[1], real(-1.0), real(-1.0), z, z, z
    if i == 1:
        return xi[0], real(1.0), z, z, z, z
    return xi[1], z, real(1.0), z, z, z


@wp.func
def _shape(el: Any, xi: vec2, i: int):  # noqa: F811
    return shape(el, xi, i)


@wp.func
def _centre(el: Triangles):
    return vec2(real(1.0) / real(3.0), real(1.0) / real(3.0))


@wp.func
def _centre(el: Any):  # noqa: F811
    return el.centre


@wp.func
def _visit(q: Any, t_tol: real, box: Box6):
    """One box of the search: (0 none in it, 1 a contact at the returned box's earliest time,
    2 split it along the returned axis), the box (contracted when proven)."""
    out, extent, axis, jac = _examine(q, box)
    if out or _outside(q, box):
        return 0, box, axis
    empty, inside, kb, kin = _krawczyk(q, box, jac)
    if empty:
        return 0, box, axis
    if inside:
        # One zero proven: contract it to T_TOL in time and until it is known inside or
        # outside the domain (one still undecided is within K's radius of the diagonal).
        for _it in range(CONTRACTIONS):
            if kb[5] - kb[4] > t_tol or not kin:
                o2, e2, a2, j2 = _examine(q, kb)
                em2, in2, kb2, kin2 = _krawczyk(q, kb, j2)
                if em2:
                    return 0, box, axis
                kb = kb2
                kin = kin2
        return 1, kb, axis
    small = extent <= q.delta
    if small and box[5] - box[4] <= t_tol:
        return 1, box, axis
    if small:
        axis = 2
    return 2, box, axis


@wp.func
def _centre2(b: Box6):
    return vec2(real(0.5) * (b[0] + b[1]), real(0.5) * (b[2] + b[3]))


@wp.func
def _side(b: Box6, axis: int):
    """b's extent (lo, hi) along axis."""
    return b[2 * axis], b[2 * axis + 1]


@wp.func
def _along(b: Box6, axis: int, lo: real, hi: real):
    """b with its extent along axis replaced by [lo, hi]."""
    if axis == 0:
        return Box6(lo, hi, b[2], b[3], b[4], b[5])
    if axis == 1:
        return Box6(b[0], b[1], lo, hi, b[4], b[5])
    return Box6(b[0], b[1], b[2], b[3], lo, hi)


@wp.func
def _late(b: Box6, axis: int):
    """Whether b is the later half of its parent along axis: the boxes are dyadic ([k h,
    (k + 1) h], h = 2^-m: halving from the unit cube is exact while h >= MIN_WIDTH), so k's
    parity says which half (in reals: k passes 2^31 at the depths float64 reaches)."""
    lo, hi = _side(b, axis)
    half = real(0.5) * wp.floor(lo / (hi - lo) + real(0.5))
    return half != wp.floor(half)


#: Narrowest box side halved (smaller: a contact, conservatively, as when the depth runs out);
#: halving stays exact above it, which the backtracking of search relies on.
MIN_WIDTH = real(16.0) * EPS
#: The levels of search's path: DEPTH, the NumPy stack's size, in four words of 2-bit axes.
LEVELS = DEPTH


@wp.func
def _axis_at(w0: wp.uint64, w1: wp.uint64, w2: wp.uint64, w3: wp.uint64, d: int):
    """The split axis recorded at level d (2 bits a level, 32 levels a word)."""
    w = w0
    if d >= 96:
        w = w3
    elif d >= 64:
        w = w2
    elif d >= 32:
        w = w1
    return int((w >> wp.uint64(2 * (d % 32))) & wp.uint64(3))


@wp.func
def _with_axis(w: wp.uint64, d: int, axis: int):
    shift = wp.uint64(2 * (d % 32))
    return (w & ~(wp.uint64(3) << shift)) | (wp.uint64(axis) << shift)


@wp.func
def _det(a: vec3, b: vec3, c: vec3):
    return wp.dot(a, wp.cross(b, c))


@wp.func
def _coplanarity(a0: vec3, a1: vec3, b0: vec3, b1: vec3, c0: vec3, c1: vec3):
    """The Bernstein coefficients on [0, 1] of g(t) = det(E1, E2, D), with the face's edge
    vectors E1 = x1 - x0, E2 = x2 - x0 and D = x0 - the node, each linear in t (a0, a1: E1 at
    t = 0 and t = 1; b0, b1: E2's; c0, c1: D's), so g is zero when the node is in the face's
    plane, which a contact needs; by g's blossom (det is linear in each factor), and a bound
    on their rounding.

    The factors' end values are differences of the inputs at one time, so each coordinate is
    within 3 eps of its own factor's size (nE for the edges, nD for D; a factor computed
    through the pair frame's motion would carry the motion's size, which a small face far
    from a fast node magnifies). That moves a determinant by at most
    3 (sqrt 3)^3 (2 3 eps nE nE nD + 3 eps nE nE nD) < 47 eps nE^2 nD, the determinants'
    and the blossom's own arithmetic add below 25 eps nE^2 nD and the splits of the interval
    (_split: _narrow makes two) below 84 eps nE^2 nD: bounded here by 320 eps nE^2 nD."""
    third = real(1.0) / real(3.0)
    g = vec4(
        _det(a0, b0, c0),
        third * (_det(a1, b0, c0) + _det(a0, b1, c0) + _det(a0, b0, c1)),
        third * (_det(a0, b1, c1) + _det(a1, b0, c1) + _det(a1, b1, c0)),
        _det(a1, b1, c1),
    )
    ne = wp.max(wp.max(_inf(a0), _inf(a1)), wp.max(_inf(b0), _inf(b1)))
    nd = wp.max(_inf(c0), _inf(c1))
    return g, real(320.0) * EPS * ne * ne * nd


@wp.func
def _split(g: vec4, c: real):
    """The cubic's Bernstein coefficients on [0, c] and on [c, 1] (de Casteljau: convex
    combinations, whose rounding _coplanarity's bound holds)."""
    p01 = g[0] + c * (g[1] - g[0])
    p12 = g[1] + c * (g[2] - g[1])
    p23 = g[2] + c * (g[3] - g[2])
    p012 = p01 + c * (p12 - p01)
    p123 = p12 + c * (p23 - p12)
    mid = p012 + c * (p123 - p012)
    return vec4(g[0], p01, p012, mid), vec4(mid, p123, p23, g[3])


#: The time slab of a coplanar crossing that the box search gets: at most 2^-SLAB_BAND of
#: the step for a bilinear quad's band, 2^-SLAB_TRI for a triangle's cubic. A thinner slab leaves
#: Krawczyk's test less motion to bound (boxes a hit, Warp's CPU device at 2^14, 2^-6 ->
#: 2^-7 with SLABS 3 -> 5: rough tri3 4.48 -> 3.25, graded 14.0 -> 11.6, steep 7.06 -> 5.44);
#: a quad's band, whose sign change is not the crossing itself, took more slabs at 2^-8
#: (rough quad4 12.3 -> 21.2 boxes a hit), and triangles at 2^-8 (one H200, 2^20, 5 or 8
#: slabs) took rough tri3 3.24 -> 3.16 ms but graded 7.31 -> 7.97.
SLAB_BAND = 6
SLAB_TRI = 7
#: Slabs a pair may search before its search takes the whole step. The cubic has 3 roots,
#: but one that stays within its margin of zero (a node resting on the face's plane, as
#: graded's nodes do at the step's start) starts a slab again at each slab's end; with 3,
#: those pairs went on to the whole step (one H200, 2^20, graded 7.79 -> 7.30 ms with 5
#: slabs of 2^-7, rough tri3 3.54 -> 3.23, steep 2.85 -> 2.74; 8 and 12 slabs no faster).
SLABS = 5


@wp.func
def _same_side(g1: vec4, g2: vec4, m: real):
    """Whether the cubics of Bernstein coefficients g1 and g2 are both beyond m, one sign."""
    lo = wp.min(wp.min(g1[0], g1[1]), wp.min(g1[2], g1[3]))
    lo = wp.min(lo, wp.min(wp.min(g2[0], g2[1]), wp.min(g2[2], g2[3])))
    hi = wp.max(wp.max(g1[0], g1[1]), wp.max(g1[2], g1[3]))
    hi = wp.max(hi, wp.max(wp.max(g2[0], g2[1]), wp.max(g2[2], g2[3])))
    return lo > m or hi < -m


@wp.func
def _cubic(g: vec4, u: real):
    """The cubic of Bernstein coefficients g at u (power form)."""
    c1 = real(3.0) * (g[1] - g[0])
    c2 = real(3.0) * (g[2] - real(2.0) * g[1] + g[0])
    c3 = g[3] - real(3.0) * g[2] + real(3.0) * g[1] - g[0]
    return g[0] + u * (c1 + u * (c2 + u * c3))


@wp.func
def _narrowed(g1: vec4, g2: vec4, m: real, bound: real, start: real, level: int):
    """Where a pair's box search goes next, after [0, start] was searched, when a contact
    needs g1 and g2, cubics in t, to be of opposite signs or zero (a triangle: g1 = g2, its
    coplanarity cubic; a bilinear quad: its band, _band): (0, -) no contact in [start,
    bound), (1, a slab of time) or (2, the unit box). Nothing is left when both are beyond m
    with one sign over [start, 1] (certified by their Bernstein coefficients there);
    otherwise the first time either changes sign or comes within m, found numerically,
    picks a dyadic slab [lo, hi] (at most 2^-level of the step) around it and [start, lo] is
    certified free of it. On the slab the face's motion is nearly affine and Krawczyk's test
    decides almost every pair in one box (rough tri3 pairs at 2^12: 6.9 boxes a pair on the
    whole step, 1.4 on a slab of 2^-6).
    A node that crosses again after a slab (a turning face) gets the next slab. A grazing,
    coplanar motion or a crossing left uncertified: the unit box."""
    unit = Box6(real(0.0), real(1.0), real(0.0), real(1.0), real(0.0), real(1.0))
    if start > real(0.0):  # (start is dyadic: an exact split point)
        _done, g1 = _split(g1, start)
        _done2, g2 = _split(g2, start)
    if start >= wp.min(bound, real(1.0)) or _same_side(g1, g2, m):
        return 0, unit
    # The first sign change of either among 17 samples of [start, 1], then `level`
    # bisections: the crossing within 2^-(level + 4) of the rest of the step (u: its
    # parameter).
    n1 = g1[0] < real(0.0)
    n2 = g2[0] < real(0.0)
    u0 = real(0.0)
    found = int(0)
    if wp.abs(g1[0]) <= m or wp.abs(g2[0]) <= m or n1 != n2:
        found = 1
    j = int(1)
    while found == 0 and j <= 16:
        u1 = real(j) / real(16.0)
        f1 = _cubic(g1, u1)
        f2 = _cubic(g2, u1)
        if (f1 < real(0.0)) != n1 or (f2 < real(0.0)) != n2 or wp.min(wp.abs(f1), wp.abs(f2)) <= m:
            for _b in range(level):
                um = real(0.5) * (u0 + u1)
                if (_cubic(g1, um) < real(0.0)) != n1 or (_cubic(g2, um) < real(0.0)) != n2:
                    u1 = um
                else:
                    u0 = um
            found = 1
        else:
            u0 = u1
        j += 1
    if found == 0:
        return 2, unit
    # The slab: the deepest dyadic interval of at most 2^-level that holds the estimate
    # [u0, u0 + 2^-(level + 4)] with an eighth of its width to spare on each side (none at
    # the step's ends, nor at start, searched already: a root at rest contact, t = 0, is
    # common).
    rest = real(1.0) - start
    est = real(1.0) / real(1 << (level + 4))
    r = start + rest * (u0 + real(0.5) * wp.min(est, real(1.0) - u0))
    lo = real(0.0)
    k = level
    while k > 0:
        w = real(1.0) / real(1 << k)
        lo = wp.floor(r / w) * w
        spare = real(0.125) * w + rest * real(0.5) * est
        if (lo <= start or r - lo >= spare) and (lo + w >= real(1.0) or lo + w - r >= spare):
            break
        k -= 1
    if k == 0:
        return 2, unit
    if lo > start:
        # [start, lo] free of it: the cubics split at u a little past lo's (rounded up, so
        # the part certified covers [start, lo] whatever the division's rounding).
        c = wp.min((lo - start) / rest * (real(1.0) + real(4.0) * EPS), real(1.0))
        gap1, _after1 = _split(g1, c)
        gap2, _after2 = _split(g2, c)
        if not _same_side(gap1, gap2, m):
            return 2, unit
    if lo >= bound:
        return 0, unit
    return 1, Box6(real(0.0), real(1.0), real(0.0), real(1.0), lo, lo + real(1.0) / real(1 << k))


@wp.func
def _narrow(q: TriPair, bound: real, start: real):
    """_narrowed by the triangle's coplanarity cubic (_coplanarity), which a contact needs
    to be zero."""
    return _narrowed(q.g, q.g, q.g_margin, bound, start, SLAB_TRI)


@wp.func
def _narrow(q: Any, bound: real, start: real):  # noqa: F811 (a Warp overload)
    """_narrowed by a bilinear quad's band (_band); other faces: the unit box."""
    if q.band == 1:
        return _narrowed(q.h1, q.h2, q.h_margin, bound, start, SLAB_BAND)
    return 2, Box6(real(0.0), real(1.0), real(0.0), real(1.0), real(0.0), real(1.0))


@wp.func
def _far(q: TriPair, box: Box6):
    """Whether the node stays farther from the triangle than any contact the search reports,
    all over the time slab of `box`: a lower bound of the distance at the slab's middle tm
    (the distances to the face's plane and to each edge's half-space, which holds the
    triangle) less the slab's half width times the face's largest speed relative to the node
    (dF/dt = b + s u1 + w u2, largest at a corner). A contact the search reports has |F|
    within its tolerance (delta and the rounding margins, or a Krawczyk radius past the
    diagonal): the bound must beat that by a thousandth of the face's size, which also holds
    this test's own rounding. Most candidate pairs cross the face's plane away from the face
    (their node passes through its capture box): this spares them the box search, whose
    first box (the hull and Krawczyk's test) costs about three times this."""
    tm = real(0.5) * (box[4] + box[5])
    e1 = q.e1 + tm * q.u1
    e2 = q.e2 + tm * q.u2
    d = -(q.a + tm * q.b)  # the node from the face's corner at tm
    n = wp.cross(e1, e2)
    nn = wp.dot(n, n)
    ln = wp.sqrt(nn)
    if not (ln > real(0.0)):  # (a degenerate face: the search decides)
        return False
    ss = wp.dot(wp.cross(d, e2), n)  # the barycentric numerators (s, w, 1 - s - w) nn
    sw = wp.dot(wp.cross(e1, d), n)
    su = nn - ss - sw
    l1 = wp.length(e1)
    l2 = wp.length(e2)
    lo = wp.abs(wp.dot(d, n)) / ln
    lo = wp.max(lo, -ss / (ln * l2))
    lo = wp.max(lo, -sw / (ln * l1))
    lo = wp.max(lo, -su / (ln * wp.length(e2 - e1)))
    v = wp.max(wp.length(q.b), wp.max(wp.length(q.b + q.u1), wp.length(q.b + q.u2)))
    reach = real(0.5) * (box[5] - box[4]) * v
    slack = real(2.0) * (q.delta + real(4.0) * q.margin) + real(1.0e-3) * (l1 + l2)
    slack += real(256.0) * EPS * (wp.length(d) + l1 + l2 + reach)
    return lo - reach > slack  # (NaN, a degenerate face: false)


@wp.func
def _far(q: Any, box: Box6):  # noqa: F811 (a Warp overload)
    return False


@wp.func
def earliest(q: Any, bound: real, t_tol: real, budget: int, skim: int):
    """search on the slabs _narrow gives in turn (after SLABS of them, or when _narrow cannot
    certify the gap before the next, on the unit box), with search called from one place (it
    is inlined: each call site is a copy of it, which costs a GPU its instruction cache and
    registers). Same result and guarantee as search on the unit box. A search that would
    visit more than `budget` boxes stops with converged = -1 (pair_search defers it).
    skim = 1: a slab whose node stays far from the face all over it (`_far`) is not searched
    (the same answers; Warp's CPU device, 2^14: rough tri3 6-10 % faster, graded 5-8 %).
    The GPU's pair_search passes 0: not yet measured there, where code size has cost more
    than it saved before."""
    kind, node = _narrow(q, bound, real(0.0))
    best = real(3.0e38)
    where = vec2(real(0.5))
    conv = int(1)
    visits = int(0)
    slabs = int(1)
    while kind != 0:
        t = real(3.0e38)
        at = vec2(real(0.5))
        cv = int(1)
        n = int(0)
        if kind == 2 or skim == 0 or not _far(q, node):
            t, at, cv, n = search(q, node, bound, t_tol, budget - visits)
        visits += n
        if cv < 0:
            return best, where, cv, visits
        best = t
        where = at
        conv = cv
        if t < real(2.0) or kind == 2:
            kind = 0
        elif slabs == SLABS:
            node = Box6(real(0.0), real(1.0), real(0.0), real(1.0), real(0.0), real(1.0))
            kind = 2
        else:
            kind, node = _narrow(q, bound, node[5])
            slabs += 1
    return best, _unshift(where, q.r), conv, visits


@wp.func
def search(q: Any, node: Box6, bound: real, t_tol: real, budget: int):
    """The pair's earliest contact (arraycontact._sweep.roots for one pair) in the dyadic box
    `node` (the unit box, or a slab of time) before `bound`: (toi or 3e38, the contact box's
    centre (s, w), converged, boxes visited). q: TriPair, CurvedPair or QuadPair (_pair).

    The same depth-first order as roots' stack (the earlier half first, boxes that start at
    or after the earliest contact skipped), without the stack: a pending box is always the
    later sibling of a box on the path from the root, so the path's split axes (registers)
    and the current box are enough to step to the next one (the sibling, or up to the
    parent). No local memory a thread, which on a GPU was most of the search's time. More
    than `budget` boxes: stops with converged = -1, its answer unknown."""
    best = real(3.0e38)
    limit = bound
    where = vec2(real(0.5))
    converged = int(1)
    visits = int(0)
    d = int(0)
    w0 = wp.uint64(0)
    w1 = wp.uint64(0)
    w2 = wp.uint64(0)
    w3 = wp.uint64(0)
    going = int(1)
    while going == 1:
        # One call site: _visit is large (a curved pair's most of all) and is inlined.
        state, box, axis = _visit(q, t_tol, node)
        visits += 1
        if state == 2:
            lo, hi = _side(node, axis)
            if d + 1 >= LEVELS or hi - lo < MIN_WIDTH:
                state = 1  # no room: a contact, conservatively
                box = node
                converged = 0
            else:
                if d < 32:
                    w0 = _with_axis(w0, d, axis)
                elif d < 64:
                    w1 = _with_axis(w1, d, axis)
                elif d < 96:
                    w2 = _with_axis(w2, d, axis)
                else:
                    w3 = _with_axis(w3, d, axis)
                d += 1
                node = _along(node, axis, lo, real(0.5) * (lo + hi))  # the earlier half
        if state == 1 and box[4] < limit:
            best = box[4]
            limit = best
            where = _centre2(box)
        if state != 2:
            # The next pending box that starts before the limit: the later sibling of the
            # deepest earlier half on the path.
            going = int(0)
            if visits > VISITS and d > 0:
                # Over budget: the earliest pending box (never late), found on the way up.
                converged = 0
                while d > 0:
                    d -= 1
                    a = _axis_at(w0, w1, w2, w3, d)
                    lo, hi = _side(node, a)
                    if _late(node, a):
                        node = _along(node, a, real(2.0) * lo - hi, hi)
                    else:
                        sib = _along(node, a, hi, real(2.0) * hi - lo)
                        if sib[4] < limit:
                            best = sib[4]
                            limit = best
                            where = _centre2(sib)
                        node = _along(node, a, lo, real(2.0) * hi - lo)
            while d > 0 and going == 0:
                a = _axis_at(w0, w1, w2, w3, d - 1)
                lo, hi = _side(node, a)
                if _late(node, a):
                    node = _along(node, a, real(2.0) * lo - hi, hi)  # up to the parent
                    d -= 1
                else:
                    node = _along(node, a, hi, real(2.0) * hi - lo)  # the later sibling
                    if node[4] < limit:
                        going = int(1)
        if going == 1 and visits >= budget:
            return best, where, int(-1), visits
    return best, where, converged, visits


@wp.kernel
def capture_keys(
    first: int,
    x0: wp.array(dtype=vec3),
    x1: wp.array(dtype=vec3),
    faces: wp.array2d(dtype=int),
    lebesgue: real,
    world: wp.array(dtype=int),
    grid: Grid,
):
    """Each face's key: the Morton code of its capture box's centre (threads first + t, no
    atomics: on the CPU in parts)."""
    f = first + wp.tid()
    c0, r0, lo0, hi0 = face_bounds(x0, faces, f, lebesgue)
    c1, r1, lo1, hi1 = face_bounds(x1, faces, f, lebesgue)
    c = real(0.5) * (wp.min(lo0, lo1) + wp.max(hi0, hi1))
    grid.keys[f] = morton_key(c - grid.corner, world[f], grid.quantum, grid.bits)
    grid.sorted_ids[f] = f


@wp.kernel
def capture_gather(
    first: int,
    x0: wp.array(dtype=vec3),
    x1: wp.array(dtype=vec3),
    faces: wp.array2d(dtype=int),
    lebesgue: real,
    world: wp.array(dtype=int),
    pad_rel: real,
    pad_abs: real,
    grid: Grid,
    rebuild: wp.array(dtype=wp.int32),
    refit: int,
):
    """Each face's capture box (its boxes at both ends of the step, grown by pad_rel times
    its largest side plus pad_abs: arraycontact._sweep.capture_pads) in its slot (threads
    first + t). refit = 1: the order is the previous build's; rebuild[0] is raised when a
    box's centre (capture_keys') moved farther than grid.margin from where it was sorted."""
    k = first + wp.tid()
    f = grid.sorted_ids[k]
    c0, r0, lo0, hi0 = face_bounds(x0, faces, f, lebesgue)
    c1, r1, lo1, hi1 = face_bounds(x1, faces, f, lebesgue)
    lo = wp.min(lo0, lo1)
    hi = wp.max(hi0, hi1)
    c = real(0.5) * (lo + hi)
    if refit == 1:
        if wp.length(c - grid.centres[k]) > grid.margin:
            rebuild[0] = 1
    else:
        grid.centres[k] = c
    side = hi - lo
    pad = vec3(pad_rel * wp.max(side[0], wp.max(side[1], side[2])) + pad_abs)
    write_item(grid, slot(grid, k), lo - pad, f, hi + pad, world[f])


@wp.func
def _feature(el: Any, xi: vec2, tol: real):
    """FACE, EDGE or VERTEX from the domain's constraints active at xi (within tol)."""
    k = int(0)
    if _is_tri(el):
        if wp.abs(xi[0]) <= tol:
            k += 1
        if wp.abs(xi[1]) <= tol:
            k += 1
        if wp.abs(real(1.0) - xi[0] - xi[1]) <= tol:
            k += 1
    else:
        for c in range(2):
            if wp.abs(xi[c] - real(1.0)) <= tol:
                k += 1
            if wp.abs(xi[c] + real(1.0)) <= tol:
                k += 1
    if k == 0:
        return FACE
    if k == 1:
        return EDGE
    return VERTEX


@wp.func
def _pair_tri(q: TriPair):
    return True


@wp.func
def _pair_tri(q: Any):  # noqa: F811
    return _is_tri(q.el)


@wp.func
def _is_tri(el: Triangles):
    return True


@wp.func
def _is_tri(el: Quads):  # noqa: F811
    return False


@wp.func
def _is_tri(el: Any):  # noqa: F811
    return el.n_corners == 3


@wp.struct
class Out:
    """A swept detection's outputs, one row a slave (SWEPT_OUTPUTS in _detect)."""

    hit: wp.array(dtype=int)
    toi: wp.array(dtype=real)
    face: wp.array(dtype=int)
    xi: wp.array(dtype=vec2)
    point: wp.array(dtype=vec3)
    normal: wp.array(dtype=vec3)
    feature: wp.array(dtype=int)
    normal_velocity: wp.array(dtype=real)
    converged: wp.array(dtype=int)
    visits: wp.array(dtype=int)


@wp.func
def _write(
    i: int,
    el: Any,
    x0: wp.array(dtype=vec3),
    x1: wp.array(dtype=vec3),
    faces: wp.array2d(dtype=int),
    f: int,
    first: real,
    where: vec2,
    a: vec3,
    b: vec3,
    feature_tol: real,
    out: Out,
):
    """Slave i's contact: face f at time `first`, where (s, w) on it."""
    z = _natural(el, where[0], where[1])
    o = x0[faces[f, 0]]
    xa = face_nodes(x0, faces, f, o)
    xb = face_nodes(x1, faces, f, o)
    xt = FaceNodes()
    vf = vec3(0.0)
    for q in range(faces.shape[1]):
        xt = set_node(xt, q, _row(xa, q) + first * (_row(xb, q) - _row(xa, q)))
        n, d0, d1, h00, h01, h11 = _shape(el, z, q)
        vf += n * (_row(xb, q) - _row(xa, q))
    nrm = _normal(el, xt, z)
    out.hit[i] = 1
    out.toi[i] = first
    out.face[i] = f
    out.xi[i] = z
    out.point[i] = a + first * (b - a)
    out.normal[i] = nrm
    out.feature[i] = _feature(el, z, feature_tol)
    out.normal_velocity[i] = wp.dot(nrm, (b - a) - vf)


@wp.kernel
def swept_scan(
    grid: Grid,
    el: Any,
    x0: wp.array(dtype=vec3),
    x1: wp.array(dtype=vec3),
    faces: wp.array2d(dtype=int),
    s0: wp.array(dtype=vec3),
    s1: wp.array(dtype=vec3),
    slave_world: wp.array(dtype=int),
    shared: int,
    pad_rel: real,
    t_tol: real,
    space_rtol: real,
    feature_tol: real,
    lost: wp.array(dtype=int),
    start: int,
    out: Out,
):
    """Slave i's earliest contact over the step, for the slaves whose pairs did not fit the
    plan's pair list (lost[i] = 1; pair_fill), one thread a slave: the faces whose capture
    box meets its segment, each searched before the earliest contact so far plus t_tol; the
    tie band (faces within t_tol of the earliest) goes to the smallest face id. Thread t
    takes slave start + t."""
    i = start + wp.tid()
    if lost[i] == 0:
        return
    a = s0[i]
    b = s1[i]
    world = slave_world[i]
    s = real(0.5) * (a + b)
    seg = Segment()
    seg.a = a
    seg.d = b - a
    seg.pad = pad_rel * wp.length(b - a)
    reach = real(0.5) * wp.length(b - a) + seg.pad
    first = real(3.0e38)
    band_f = BandF()
    band_t = BandT()
    band_x = BandX()
    nb = int(0)
    conv = int(1)
    total = int(0)
    stack = wp.uint64(0)
    top = grid.root[0]
    k = top
    j = int(0)
    visit = int(1)
    while visit == 1:
        visit = 0
        box = entry(grid, k, j)
        if enters(s, world, shared, box, reach):
            if k == 1:
                for c in range(W):
                    kk = box.first + c
                    f = item_id(grid, kk)
                    if f >= 0:  # (not an empty slot)
                        near = meets(seg, item_lo(grid, kk), item_hi(grid, kk))
                        if near and shared == 0:
                            near = item_world(grid, kk) == world
                        if near:
                            pr = _pair(el, x0, x1, faces, f, a, b, space_rtol)
                            bound = real(3.0e38)
                            if first < real(2.0):
                                bound = first + t_tol
                            t, where, cv, n_vis = earliest(pr, bound, t_tol, ALL_BOXES, 1)
                            total += n_vis
                            if t < bound:
                                if cv == 0:
                                    conv = 0
                                first = wp.min(first, t)
                                # Keep the band: drop entries now later than first + t_tol.
                                m = int(0)
                                for q in range(nb):
                                    if band_t[q] <= first + t_tol:
                                        band_f[m] = band_f[q]
                                        band_t[m] = band_t[q]
                                        band_x[m, 0] = band_x[q, 0]
                                        band_x[m, 1] = band_x[q, 1]
                                        m += 1
                                nb = m
                                if nb < BAND:
                                    band_f[nb] = f
                                    band_t[nb] = t
                                    band_x[nb, 0] = where[0]
                                    band_x[nb, 1] = where[1]
                                    nb += 1
                                else:
                                    conv = 0  # more tied faces than kept
            else:
                mask, near_c = children(grid, s, world, shared, k, box.first, reach, 0, seg)
                if mask != 0:
                    stack, k, j = descend(stack, k, box.first, mask, near_c)
                    visit = 1
        if visit == 0:
            stack, k, j, visit = next_pending(grid, top, stack, k, j)
    out.visits[i] = total
    out.converged[i] = conv
    if nb == 0:
        out.hit[i] = 0
        out.face[i] = -1
        return
    pick = int(0)
    for q in range(nb):
        if band_f[q] < band_f[pick]:
            pick = q
    where = vec2(band_x[pick, 0], band_x[pick, 1])
    _write(i, el, x0, x1, faces, band_f[pick], first, where, a, b, feature_tol, out)


@wp.struct
class Pairs:
    """A swept detection's (slave, face) pairs, searched one thread a pair (swept_pairs): the
    list (slave -1: a slot not filled), each slave's count and first slot, and per pair the
    search's result (toi: 3e38 when none before the bound it had; (s, w); converged);
    per slave the earliest toi."""

    slave: wp.array(dtype=int)
    face: wp.array(dtype=int)
    count: wp.array(dtype=int)
    offset: wp.array(dtype=int)
    toi: wp.array(dtype=real)
    where: wp.array(dtype=vec2)
    conv: wp.array(dtype=int)
    first: wp.array(dtype=real)
    later: wp.array2d(dtype=int)  # the pairs pair_search deferred, a row a tier, and counts
    n_later: wp.array(dtype=int)
    window: wp.array(dtype=int)  # per slave, the first WINDOW faces pair_walk met
    more: wp.array(dtype=int)  # the slaves that met more, walked again, and their count
    n_more: wp.array(dtype=int)


#: Faces a slave's walk keeps (pair_walk's window): the densest swept scenes have 8 a slave
#: on average (graded 1:100, 2^16: 6.7 % of the slaves meet more).
WINDOW = 16


@wp.func
def _walk(
    grid: Grid,
    a: vec3,
    b: vec3,
    world: int,
    shared: int,
    pad_rel: real,
    faces: wp.array(dtype=int),
    at: int,
    lo: int,
    hi: int,
):
    """The count of faces whose capture box meets the segment a -> b (as swept_scan walks),
    the m-th of them written to faces[at + m] for lo <= m < hi (the walk's order: the same
    in every walk)."""
    s = real(0.5) * (a + b)
    seg = Segment()
    seg.a = a
    seg.d = b - a
    seg.pad = pad_rel * wp.length(b - a)
    reach = real(0.5) * wp.length(b - a) + seg.pad
    m = int(0)
    stack = wp.uint64(0)
    top = grid.root[0]
    k = top
    j = int(0)
    visit = int(1)
    while visit == 1:
        visit = 0
        box = entry(grid, k, j)
        if enters(s, world, shared, box, reach):
            if k == 1:
                for c in range(W):
                    kk = box.first + c
                    f = item_id(grid, kk)
                    if f >= 0:  # (not an empty slot)
                        near = meets(seg, item_lo(grid, kk), item_hi(grid, kk))
                        if near and shared == 0:
                            near = item_world(grid, kk) == world
                        if near:
                            if m >= lo and m < hi:
                                faces[at + m] = f
                            m += 1
            else:
                mask, near_c = children(grid, s, world, shared, k, box.first, reach, 0, seg)
                if mask != 0:
                    stack, k, j = descend(stack, k, box.first, mask, near_c)
                    visit = 1
        if visit == 0:
            stack, k, j, visit = next_pending(grid, top, stack, k, j)
    return m


@wp.kernel(cuda_max_registers=64)  # (a tree walk: 0.2-0.3 ms less at 2^20)
def pair_walk(
    grid: Grid,
    s0: wp.array(dtype=vec3),
    s1: wp.array(dtype=vec3),
    slave_world: wp.array(dtype=int),
    shared: int,
    pad_rel: real,
    start: int,
    pairs: Pairs,
):
    """Slave i's pair count and its first WINDOW faces; its earliest toi reset."""
    i = start + wp.tid()
    a, b, w = s0[i], s1[i], slave_world[i]
    pairs.count[i] = _walk(grid, a, b, w, shared, pad_rel, pairs.window, WINDOW * i, 0, WINDOW)
    pairs.first[i] = real(3.0e38)


@wp.kernel
def pair_fill(pairs: Pairs, lost: wp.array(dtype=int), visits: wp.array(dtype=int)):
    """Slave i's pairs into the list from its offset (the counts' prefix sum) when they fit:
    its window's, and those past it left to pair_more (pairs.more); else lost[i] = 1
    (swept_scan searches it) and its slots in the list, if any, unfilled."""
    i = wp.tid()
    at = pairs.offset[i]
    n = pairs.count[i]
    room = pairs.slave.shape[0]
    visits[i] = 0
    if at + n <= room:
        lost[i] = 0
        for m in range(n):
            pairs.slave[at + m] = i
        for m in range(wp.min(n, WINDOW)):
            pairs.face[at + m] = pairs.window[WINDOW * i + m]
        if n > WINDOW:
            pairs.more[wp.atomic_add(pairs.n_more, 0, 1)] = i
    else:
        lost[i] = 1
        for q in range(at, wp.min(at + n, room)):
            pairs.slave[q] = -1


@wp.kernel(cuda_max_registers=64)
def pair_more(
    grid: Grid,
    s0: wp.array(dtype=vec3),
    s1: wp.array(dtype=vec3),
    slave_world: wp.array(dtype=int),
    shared: int,
    pad_rel: real,
    pairs: Pairs,
    stride: int,
):
    """The faces past the window of the slaves in pairs.more, walked again (thread t takes
    entries t, t + stride, ...)."""
    j = wp.tid()
    while j < pairs.n_more[0]:
        i = pairs.more[j]
        at = pairs.offset[i]
        n = pairs.count[i]
        _walk(grid, s0[i], s1[i], slave_world[i], shared, pad_rel, pairs.face, at, WINDOW, n)
        j += stride


@wp.kernel
def pair_search(
    el: Any,
    x0: wp.array(dtype=vec3),
    x1: wp.array(dtype=vec3),
    faces: wp.array2d(dtype=int),
    s0: wp.array(dtype=vec3),
    s1: wp.array(dtype=vec3),
    t_tol: real,
    space_rtol: real,
    start: int,
    pairs: Pairs,
    visits: wp.array(dtype=int),
    budget: int,
    deferred: int,
    stride: int,
):
    """Pair k's earliest contact before its slave's earliest so far plus t_tol (the bound
    only prunes: whatever other pairs of the slave have found when this one reads it).
    Launch d (deferred) takes the filled slots (d = 0) or the pairs launch d - 1 deferred
    (pairs.later row d - 1); a search of more than `budget` boxes is deferred: the pair goes
    to row d, which the next launch searches again from its root. Thread t takes entries t,
    t + stride, ... (stride: the launch's size, a fraction of the list's: the list is sized
    for the densest scenes, and most scenes defer few pairs). On a GPU a warp's threads step
    together, so one long search (a hit: 10-20 boxes) held 31 short ones (a miss: 1-3); the
    later launches pack the long ones."""
    j = start + wp.tid()
    last = pairs.count.shape[0] - 1
    n = wp.min(pairs.offset[last] + pairs.count[last], pairs.slave.shape[0])  # filled slots
    if deferred >= 1:
        n = pairs.n_later[deferred - 1]
    while j < n:
        k = j
        if deferred >= 1:
            k = pairs.later[deferred - 1, j]
        i = pairs.slave[k]  # (-1: a slot left unfilled; j is below the filled ones)
        if i >= 0:
            pr = _pair(el, x0, x1, faces, pairs.face[k], s0[i], s1[i], space_rtol)
            bound = real(3.0e38)
            first = pairs.first[i]
            if first < real(2.0):
                bound = first + t_tol
            t, where, cv, n_vis = earliest(pr, bound, t_tol, budget, 0)
            if cv < 0:
                pairs.later[deferred, wp.atomic_add(pairs.n_later, deferred, 1)] = k
            else:
                wp.atomic_add(visits, i, n_vis)
                if t < bound:
                    pairs.toi[k] = t
                    pairs.where[k] = where
                    pairs.conv[k] = cv
                    wp.atomic_min(pairs.first, i, t)
                else:
                    pairs.toi[k] = real(3.0e38)
        j += stride


# The same kernel for triangles, capped at 96 registers in a module of its own: more threads
# resident hide the search's latency better than registers would (2^20, H100: graded 30.0 ->
# 20.2 ms, rough tri3 9.35 -> 6.87 ms; 64 spills: 22.9 and 7.5 ms). Curved and bilinear faces
# keep pair_search: capped at 96 their search spills (rough quad4 25.4 -> 35.3 ms).
pair_search_tri = wp.kernel(
    cuda_max_registers=96,
    module="unique",
    module_options={"enable_backward": False, "max_unroll": 1},
)(pair_search.func)


@wp.kernel
def pair_finish(
    el: Any,
    x0: wp.array(dtype=vec3),
    x1: wp.array(dtype=vec3),
    faces: wp.array2d(dtype=int),
    s0: wp.array(dtype=vec3),
    s1: wp.array(dtype=vec3),
    feature_tol: real,
    t_tol: real,
    lost: wp.array(dtype=int),
    start: int,
    pairs: Pairs,
    out: Out,
):
    """Slave i's outputs from its pairs' search (the slaves swept_scan searched: its own):
    the tie band's smallest face (its pairs within t_tol of the earliest), where and whether
    its search converged."""
    i = start + wp.tid()
    if lost[i] == 1:
        return
    at = pairs.offset[i]
    n = pairs.count[i]
    first = pairs.first[i]
    f = int(2147483647)
    pick = int(-1)
    for q in range(at, at + n):
        t = pairs.toi[q]
        if t < real(2.0) and t <= first + t_tol and pairs.face[q] < f:
            f = pairs.face[q]
            pick = q
    out.converged[i] = 1
    if pick < 0:
        out.hit[i] = 0
        out.face[i] = -1
        return
    where = pairs.where[pick]
    out.converged[i] = pairs.conv[pick]
    _write(i, el, x0, x1, faces, f, pairs.first[i], where, s0[i], s1[i], feature_tol, out)
