"""Point-to-face geometry as `@wp.func`s (the twins of arraycontact._geometry), exported so a
simulator can call them from its own kernels.

    closest_point_triangle(p, a, b, c) -> (xi, feature, local)          tri3, Voronoi regions
    closest_point_face(el, r, xe, xi0, iterations, tol) -> (xi, feature, local, converged)
        any element (quad4, tri6, quad8, quad9; tri3 too) by the active-set method of
        seed 003 eq. (8), in the frame of xe (face nodes relative to a nearby origin).
    closest_point_edge(el, r, xe, e) -> (t, squared distance)   exact, over the whole edge e
    face_point(el, xe, xi) -> x(xi)

Element data travel in an `Element` struct (`element_data(name, device)` builds it), or for
quad4 in a `Quads` struct (`quad_data(device)`: the same fields, the bilinear shortcuts taken
at compile time, so that a kernel specialised on it holds no curved-face code); face nodes
in a `FaceNodes` struct of up to 9 points (`face_nodes(points, faces, f, origin)`, or
`xe = set_node(xe, i, x)` node by node).
feature: 0 face interior, 1 edge (local = edge id, from corner local to local + 1), 2 vertex
(local = corner id).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import warp as wp

from arraycontact._elements import get_element

from ._real import ACTIVE_TOL, EPS, NP_REAL, mat22, real, vec2, vec3

# Forward only, no loop unrolling (a scan's loops unrolled copy the projection many times into
# the kernel: minutes of CUDA compilation for no speed).
wp.set_module_options({"enable_backward": False, "max_unroll": 1})

FACE = wp.constant(0)
EDGE = wp.constant(1)
VERTEX = wp.constant(2)


#: An element's data: the fields of `Element` and `Quads`.
_ELEMENT_FIELDS = {
    "nn": int,  # nodes per face
    "n_corners": int,
    "bilinear": int,  # quad4: its shape functions in closed form (`is_bilinear`)
    "n_mono": int,
    "n_cons": int,
    "coef": wp.array2d(dtype=real),  # N_i = sum_j coef[i, j] xi^px[j] eta^py[j]
    "px": wp.array(dtype=int),
    "py": wp.array(dtype=int),
    "cons_a": wp.array(dtype=vec2),  # domain: a_j . xi >= b_j
    "cons_b": wp.array(dtype=real),
    "cons_edge": wp.array(dtype=int),  # local edge of constraint j
    "nodes": wp.array(dtype=vec2),  # natural coordinates of the nodes
    "centre": vec2,
}


def make_struct(name: str, fields: dict, doc: str, module: str = __name__):
    """A Warp struct `name` of `fields` {name: type} (several structs of one field table)."""
    ns = {"__annotations__": dict(fields), "__doc__": doc, "__module__": module}
    return wp.struct(type(name, (), {**ns, "__qualname__": name}))


#: Any element (quad4 too): the data the element functions below read.
Element = make_struct("Element", _ELEMENT_FIELDS, "Any element's data (`element_data`).")

#: quad4 as a type of its own, for the detection kernels: the functions below take the
#: bilinear shortcuts at compile time (`is_bilinear`, `straight`), so a quad4 kernel holds no
#: curved-face code (behind a run-time flag it cost the kernels registers: H100, 2^20 quad4,
#: face scan 3.84 -> 2.86 ms, finish kernel 0.79 -> 0.39 ms; float64 first call 26 -> 18 s).
Quads = make_struct(
    "Quads", _ELEMENT_FIELDS, "quad4's data (`quad_data`): an `Element` known bilinear."
)


@wp.struct
class Triangles:
    """tri3 only: the kernels specialise on this type (no curved-face solver in the way)."""

    n_corners: int
    nodes: wp.array(dtype=vec2)
    centre: vec2


@wp.struct
class FaceNodes:
    """Up to 9 node coordinates, one field a node (`_row`, `set_node`): indexed at run time, a
    matrix lives in a GPU thread's slow local memory; fields stay in registers."""

    x0: vec3
    x1: vec3
    x2: vec3
    x3: vec3
    x4: vec3
    x5: vec3
    x6: vec3
    x7: vec3
    x8: vec3


def triangle_data(device=None) -> Triangles:
    t = Triangles()
    t.n_corners = 3
    t.nodes = wp.array(np.array([[0, 0], [1, 0], [0, 1]], NP_REAL), dtype=vec2, device=device)
    t.centre = vec2(1.0 / 3.0, 1.0 / 3.0)
    return t


def element_data(name, device=None) -> Element:
    return _fill(Element(), name, device)


def quad_data(device=None) -> Quads:
    return _fill(Quads(), "quad4", device)


def _fill(el, name, device):
    e = get_element(name)
    el.nn, el.n_corners = e.nodes_per_face, e.n_corners
    el.bilinear = int(name == "quad4")
    el.n_mono, el.n_cons = len(e.monomials), len(e.constraints_b)
    el.coef = wp.array(e.coefficients.astype(NP_REAL), dtype=real, device=device)
    el.px = wp.array([p for p, _ in e.monomials], dtype=int, device=device)
    el.py = wp.array([q for _, q in e.monomials], dtype=int, device=device)
    el.cons_a = wp.array(e.constraints_a.astype(NP_REAL), dtype=vec2, device=device)
    el.cons_b = wp.array(e.constraints_b.astype(NP_REAL), dtype=real, device=device)
    el.cons_edge = wp.array(e.constraint_edge, dtype=int, device=device)
    el.nodes = wp.array(e.nodes.astype(NP_REAL), dtype=vec2, device=device)
    el.centre = vec2(*[float(v) for v in e.centre])
    return el


@wp.func
def is_bilinear(el: Element):
    """Whether the face is a quad4 (its shape functions in closed form): Quads' a constant."""
    return el.bilinear == 1


@wp.func
def is_bilinear(el: Quads):  # noqa: F811 (a Warp overload)
    return True


@wp.func
def straight(el: Element):
    """Whether the face's edges are straight (its nodes are its corners)."""
    return el.nn == el.n_corners


@wp.func
def straight(el: Quads):  # noqa: F811 (a Warp overload)
    return True


# The element's domain and nodes: Element's and Triangles' from their arrays, Quads' as
# constants, so a quad4 kernel reads no array for them and divides by a constant 4 (with
# `face_nodes` and quad4's `exact_edges` written out on the node fields: H100, 2^20 quad4,
# the face scan 2.81 -> 2.04 ms; self-contact's quad4 scans at 2^17 22-27 % faster; the same
# answers bit for bit; neutral on the CPU, whose compiler kept them in registers already).
@wp.func
def corners(el: Quads):
    return 4


@wp.func
def corners(el: Any):  # noqa: F811 (a Warp overload)
    return el.n_corners


@wp.func
def node_xi(el: Quads, i: int):
    """Node i's natural coordinates: quad4's corners (-1, -1), (1, -1), (1, 1), (-1, 1)."""
    x = wp.where(i == 1 or i == 2, real(1.0), real(-1.0))
    return vec2(x, wp.where(i >= 2, real(1.0), real(-1.0)))


@wp.func
def node_xi(el: Any, i: int):  # noqa: F811
    return el.nodes[i]


@wp.func
def n_cons(el: Quads):
    return 4


@wp.func
def n_cons(el: Any):  # noqa: F811
    return el.n_cons


@wp.func
def cons_a(el: Quads, j: int):
    """Constraint j's a (a . xi >= b): quad4's xi >= -1, -xi >= -1, eta >= -1, -eta >= -1."""
    s = wp.where(j % 2 == 0, real(1.0), real(-1.0))
    return wp.where(j < 2, vec2(s, real(0.0)), vec2(real(0.0), s))


@wp.func
def cons_a(el: Any, j: int):  # noqa: F811
    return el.cons_a[j]


@wp.func
def cons_b(el: Quads, j: int):
    return real(-1.0)


@wp.func
def cons_b(el: Any, j: int):  # noqa: F811
    return el.cons_b[j]


@wp.func
def cons_edge(el: Quads, j: int):
    """The local edge of constraint j: quad4's 3, 1, 0, 2."""
    return wp.where(j < 2, wp.where(j == 0, 3, 1), wp.where(j == 2, 0, 2))


@wp.func
def cons_edge(el: Any, j: int):  # noqa: F811
    return el.cons_edge[j]


@wp.func
def _pw(x: real, p: int):
    if p == 0:
        return real(1.0)
    if p == 1:
        return x
    return x * x


@wp.func
def _dpw(x: real, p: int):
    if p == 0:
        return real(0.0)
    if p == 1:
        return real(1.0)
    return real(2.0) * x


@wp.func
def _ddpw(p: int):
    if p == 2:
        return real(2.0)
    return real(0.0)


@wp.func
def shape(el: Any, xi: vec2, i: int):
    """N_i, dN_i/dxi, dN_i/deta, and the three second derivatives (xixi, xieta, etaeta)."""
    if is_bilinear(el):  # (1 + a0 xi)(1 + a1 eta) / 4: 3.2x faster quad4 detection (CPU)
        a = node_xi(el, i)
        u = real(1.0) + a[0] * xi[0]
        v = real(1.0) + a[1] * xi[1]
        w = real(0.25)
        return w * u * v, w * a[0] * v, w * a[1] * u, real(0.0), w * a[0] * a[1], real(0.0)
    n = real(0.0)
    d0 = real(0.0)
    d1 = real(0.0)
    h00 = real(0.0)
    h01 = real(0.0)
    h11 = real(0.0)
    for j in range(el.n_mono):
        c = el.coef[i, j]
        p = el.px[j]
        q = el.py[j]
        n += c * _pw(xi[0], p) * _pw(xi[1], q)
        d0 += c * _dpw(xi[0], p) * _pw(xi[1], q)
        d1 += c * _pw(xi[0], p) * _dpw(xi[1], q)
        h00 += c * _ddpw(p) * _pw(xi[1], q)
        h01 += c * _dpw(xi[0], p) * _dpw(xi[1], q)
        h11 += c * _pw(xi[0], p) * _ddpw(q)
    return n, d0, d1, h00, h01, h11


@wp.func
def _row(xe: FaceNodes, i: int):
    """Node i (< 9)."""
    if i < 4:
        if i < 2:
            return wp.where(i == 0, xe.x0, xe.x1)
        return wp.where(i == 2, xe.x2, xe.x3)
    if i < 6:
        return wp.where(i == 4, xe.x4, xe.x5)
    if i < 8:
        return wp.where(i == 6, xe.x6, xe.x7)
    return xe.x8


@wp.func
def set_node(x: FaceNodes, i: int, v: vec3):
    """x with node i (< 9) set to v."""
    if i == 0:
        x.x0 = v
    elif i == 1:
        x.x1 = v
    elif i == 2:
        x.x2 = v
    elif i == 3:
        x.x3 = v
    elif i == 4:
        x.x4 = v
    elif i == 5:
        x.x5 = v
    elif i == 6:
        x.x6 = v
    elif i == 7:
        x.x7 = v
    else:
        x.x8 = v
    return x


@wp.func
def _corner_weights(xi: vec2):
    """quad4's four shape functions (corners (-1, -1), (1, -1), (1, 1), (-1, 1)), as `shape`
    computes them: unrolled on the node fields, a bilinear face skips the loop over nodes and
    the run-time node selection (quad4 detection 1.5-2x faster, CPU and GPU)."""
    u0 = real(1.0) - xi[0]
    u1 = real(1.0) + xi[0]
    v0 = real(1.0) - xi[1]
    v1 = real(1.0) + xi[1]
    w = real(0.25)
    return w * u0 * v0, w * u1 * v0, w * u1 * v1, w * u0 * v1


@wp.func
def face_point(el: Any, xe: FaceNodes, xi: vec2):
    if is_bilinear(el):
        n0, n1, n2, n3 = _corner_weights(xi)
        return n0 * xe.x0 + n1 * xe.x1 + n2 * xe.x2 + n3 * xe.x3
    x = vec3(0.0)
    for i in range(el.nn):
        n, d0, d1, h00, h01, h11 = shape(el, xi, i)
        x += n * _row(xe, i)
    return x


@wp.func
def face_tangents(el: Any, xe: FaceNodes, xi: vec2):
    if is_bilinear(el):
        return _bilinear_tangents(xe, xi)
    t0 = vec3(0.0)
    t1 = vec3(0.0)
    for i in range(el.nn):
        n, d0, d1, h00, h01, h11 = shape(el, xi, i)
        t0 += d0 * _row(xe, i)
        t1 += d1 * _row(xe, i)
    return t0, t1


@wp.func
def _bilinear_tangents(xe: FaceNodes, xi: vec2):
    """dx/dxi and dx/deta of a quad4 (`shape`'s derivatives, unrolled)."""
    u0 = real(0.25) * (real(1.0) - xi[0])
    u1 = real(0.25) * (real(1.0) + xi[0])
    v0 = real(0.25) * (real(1.0) - xi[1])
    v1 = real(0.25) * (real(1.0) + xi[1])
    t0 = v0 * (xe.x1 - xe.x0) + v1 * (xe.x2 - xe.x3)
    t1 = u0 * (xe.x3 - xe.x0) + u1 * (xe.x2 - xe.x1)
    return t0, t1


@wp.func
def _bilinear(xe: FaceNodes):
    """A quad4 as x = a0 + a1 xi + a2 eta + a3 xi eta: (a0, a1, a2, a3)."""
    q = real(0.25)
    a0 = q * ((xe.x0 + xe.x2) + (xe.x1 + xe.x3))
    a1 = q * ((xe.x1 + xe.x2) - (xe.x0 + xe.x3))
    a2 = q * ((xe.x2 + xe.x3) - (xe.x0 + xe.x1))
    a3 = q * ((xe.x0 + xe.x2) - (xe.x1 + xe.x3))
    return a0, a1, a2, a3


@wp.func
def face_nodes(points: wp.array(dtype=vec3), faces: wp.array2d(dtype=int), f: int, origin: vec3):
    """The nodes of face f relative to `origin` (nearby values subtract exactly). Written out
    field by field (a loop over the nodes picks each node's field at run time)."""
    n = faces.shape[1]
    xe = FaceNodes()
    xe.x0 = points[faces[f, 0]] - origin
    xe.x1 = points[faces[f, 1]] - origin
    xe.x2 = points[faces[f, 2]] - origin
    if n > 3:
        xe.x3 = points[faces[f, 3]] - origin
    if n > 4:
        xe.x4 = points[faces[f, 4]] - origin
        xe.x5 = points[faces[f, 5]] - origin
    if n > 6:
        xe.x6 = points[faces[f, 6]] - origin
        xe.x7 = points[faces[f, 7]] - origin
    if n > 8:
        xe.x8 = points[faces[f, 8]] - origin
    return xe


@wp.func
def _sdiv(a: real, b: real):
    if b != 0.0:
        return a / b
    return real(0.0)


ROUND = wp.constant(real(4.0) * EPS)


@wp.func
def closest_point_triangle(p: vec3, a: vec3, b: vec3, c: vec3):
    """Closest point on triangle (a, b, c) to p by Voronoi regions: xi = (v, w) with
    x = a + v (b - a) + w (c - a), feature, local (same regions and order as the NumPy twin)."""
    ab = b - a
    ac = c - a
    ap = p - a
    d1 = wp.dot(ab, ap)
    d2 = wp.dot(ac, ap)
    if d1 <= 0.0 and d2 <= 0.0:
        return vec2(0.0, 0.0), VERTEX, 0
    bp = p - b
    d3 = wp.dot(ab, bp)
    d4 = wp.dot(ac, bp)
    if d3 >= 0.0 and d4 <= d3:
        return vec2(1.0, 0.0), VERTEX, 1
    # Within its rounding a difference of two products counts as zero (the NumPy twin says why).
    vc = d1 * d4 - d3 * d2
    if vc <= ROUND * (wp.abs(d1 * d4) + wp.abs(d3 * d2)) and d1 >= 0.0 and d3 <= 0.0:
        return vec2(_sdiv(d1, d1 - d3), real(0.0)), EDGE, 0
    cp = p - c
    d5 = wp.dot(ab, cp)
    d6 = wp.dot(ac, cp)
    if d6 >= 0.0 and d5 <= d6:
        return vec2(0.0, 1.0), VERTEX, 2
    vb = d5 * d2 - d1 * d6
    if vb <= ROUND * (wp.abs(d5 * d2) + wp.abs(d1 * d6)) and d2 >= 0.0 and d6 <= 0.0:
        return vec2(real(0.0), _sdiv(d2, d2 - d6)), EDGE, 2
    va = d3 * d6 - d5 * d4
    if va <= ROUND * (wp.abs(d3 * d6) + wp.abs(d5 * d4)) and (d4 - d3) >= 0.0 and (d5 - d6) >= 0.0:
        w = _sdiv(d4 - d3, (d4 - d3) + (d5 - d6))
        return vec2(real(1.0) - w, w), EDGE, 1
    den = va + vb + vc
    return vec2(_sdiv(vb, den), _sdiv(vc, den)), FACE, -1


# A curved face's projection evaluates x(xi) and its derivatives hundreds of times (starts,
# Newton steps, line searches); through the shape functions each evaluation costs nn of them
# of n_mono terms each (quad8: 64 terms, each with its exponents read and a node picked at run
# time). On the face's monomial coefficients (A_pq = sum_i coef[i, j] x_i for monomial j =
# xi^p eta^q, so x(xi) = sum A_pq xi^p eta^q), made once a projection and kept in the fields
# of a FaceNodes by (p, q) (slot 3 p + q; p, q <= 2 for every element, absent ones zero), an
# evaluation is a fixed polynomial written out (Warp's CPU device, rough surfaces 2^14, a
# steady detection: tri6 608 -> 135 ms, quad8 1361 -> 167 ms, quad9 686 -> 86 ms). Bilinear
# faces keep their closed forms on the nodes. `pe` below: those coefficients (`coefficients`),
# or the nodes of a bilinear face (unread).
@wp.func
def monomials_of(el: Any, xe: FaceNodes):
    """The coefficients A_pq of the face's monomials xi^p eta^q, in slot 3 p + q."""
    pe = FaceNodes()
    for j in range(el.n_mono):
        a = vec3(0.0)
        for i in range(el.nn):
            a += el.coef[i, j] * _row(xe, i)
        pe = set_node(pe, 3 * el.px[j] + el.py[j], a)
    return pe


@wp.func
def coefficients(el: Any, xe: FaceNodes):
    """What `_at` and `_jet` read: a bilinear face's nodes, else its monomials' coefficients."""
    if is_bilinear(el):
        return xe
    return monomials_of(el, xe)


@wp.func
def _at(el: Any, xe: FaceNodes, pe: FaceNodes, xi: vec2):
    """x(xi) (face_point) from the nodes xe and `coefficients` pe."""
    if is_bilinear(el):
        return face_point(el, xe, xi)
    return polynomial(pe, xi)


@wp.func
def polynomial(pe: FaceNodes, xi: vec2):
    """sum A_pq xi^p eta^q over the coefficients pe of `monomials_of`."""
    y = xi[1]
    r0 = pe.x0 + y * (pe.x1 + y * pe.x2)  # the terms of xi^0, xi^1, xi^2
    r1 = pe.x3 + y * (pe.x4 + y * pe.x5)
    r2 = pe.x6 + y * (pe.x7 + y * pe.x8)
    return r0 + xi[0] * (r1 + xi[0] * r2)


@wp.func
def _jet(el: Any, xe: FaceNodes, pe: FaceNodes, xi: vec2):
    """x(xi), x_xi, x_eta, x_xixi, x_xieta, x_etaeta (as _at)."""
    if is_bilinear(el):
        x = face_point(el, xe, xi)
        t0, t1 = _bilinear_tangents(xe, xi)
        bl0, bl1, bl2, a3 = _bilinear(xe)
        return x, t0, t1, vec3(0.0), a3, vec3(0.0)
    u = xi[0]
    y = xi[1]
    two = real(2.0)
    r0 = pe.x0 + y * (pe.x1 + y * pe.x2)
    r1 = pe.x3 + y * (pe.x4 + y * pe.x5)
    r2 = pe.x6 + y * (pe.x7 + y * pe.x8)
    d0 = pe.x1 + two * y * pe.x2  # d/deta of r0, r1, r2
    d1 = pe.x4 + two * y * pe.x5
    d2 = pe.x7 + two * y * pe.x8
    x = r0 + u * (r1 + u * r2)
    t0 = r1 + two * u * r2
    t1 = d0 + u * (d1 + u * d2)
    s00 = two * r2
    s01 = d1 + two * u * d2
    s11 = two * (pe.x2 + u * (pe.x5 + u * pe.x8))
    return x, t0, t1, s00, s01, s11


@wp.func
def _objective(el: Any, xe: FaceNodes, pe: FaceNodes, r: vec3, xi: vec2):
    return wp.length_sq(r - _at(el, xe, pe, xi))


@wp.func
def _solve2(m: mat22, v: vec2):
    det = m[0, 0] * m[1, 1] - m[0, 1] * m[1, 0]
    return vec2(
        _sdiv(v[0] * m[1, 1] - m[0, 1] * v[1], det), _sdiv(m[0, 0] * v[1] - m[1, 0] * v[0], det)
    )


@wp.func
def _least(m: mat22):
    """The least eigenvalue of J^T J (symmetric, positive): det over the largest, at least
    1e-30 (arraycontact._geometry._least)."""
    a = m[0, 0]
    b = m[0, 1]
    c = m[1, 1]
    largest = real(0.5) * (a + c + wp.sqrt((a - c) * (a - c) + real(4.0) * b * b))
    return wp.max(_sdiv(a * c - b * b, largest), real(1.0e-30))


@wp.func
def _cross2(a: vec2, b: vec2):
    return a[0] * b[1] - a[1] * b[0]


@wp.func
def _cubic(c3: real, c2: real, c1: real, c0: real, t: real):
    return ((c3 * t + c2) * t + c1) * t + c0


@wp.func
def edge_xi(el: Any, e: int, t: real):
    """Natural coordinates of parameter t on edge e (corner e to corner e + 1)."""
    a = node_xi(el, e)
    return a + t * (node_xi(el, (e + 1) % corners(el)) - a)


@wp.func
def unit_cross(a: vec3, b: vec3):
    """a x b normalised (zero where it vanishes)."""
    v = wp.cross(a, b)
    length = wp.length(v)
    if length > real(0.0):
        v = v / length
    return v


@wp.func
def _segment(r: vec3, x0: vec3, x1: vec3):
    """The closest point to r on the segment x0 -> x1: (t, squared distance)."""
    u = x1 - x0
    t = wp.clamp(_sdiv(wp.dot(r - x0, u), wp.dot(u, u)), real(0.0), real(1.0))
    return t, wp.length_sq(r - x0 - t * u)


@wp.func
def closest_point_edge(el: Any, r: vec3, xe: FaceNodes, e: int):
    """The closest point to r on the whole edge e: (t, squared distance). The twin of
    arraycontact._geometry.closest_point_edge: the derivative of the squared distance along
    the edge is a cubic; the roots of its derivative split [0, 1] into monotone pieces; a
    piece where it rises through zero holds one minimum, found by Newton kept inside the
    sign-change bracket; the smallest of those and the ends wins."""
    if straight(el):  # a straight edge: the cubic is linear (as NumPy's)
        return _segment(r, _row(xe, e), _row(xe, (e + 1) % corners(el)))
    # The edge's corners and its mid-edge node (node n_corners + e) are x at t = 0, 1 and
    # 1/2: read, not evaluated (exact, so a slave on a corner gets t = 0 or 1).
    nc = corners(el)
    x0 = _row(xe, e)
    xm = _row(xe, nc + e)
    x1 = _row(xe, (e + 1) % nc)
    p0 = x0 - r
    p1 = real(4.0) * xm - real(3.0) * x0 - x1
    p2 = real(2.0) * (x0 + x1) - real(4.0) * xm
    c3 = real(2.0) * wp.dot(p2, p2)
    c2 = real(3.0) * wp.dot(p1, p2)
    c1 = wp.dot(p1, p1) + real(2.0) * wp.dot(p0, p2)
    c0 = wp.dot(p0, p1)
    qa = real(3.0) * c3
    qb = real(2.0) * c2
    disc = qb * qb - real(4.0) * qa * c1
    s1 = real(0.0)
    s2 = real(0.0)
    if disc > 0.0:
        sq = wp.sqrt(disc)
        q = -real(0.5) * (qb + wp.where(qb >= 0.0, sq, -sq))
        s1 = wp.clamp(_sdiv(q, qa), real(0.0), real(1.0))
        s2 = wp.clamp(_sdiv(c1, q), real(0.0), real(1.0))
    lo_s = wp.min(s1, s2)
    hi_s = wp.max(s1, s2)
    best_t = real(1.0)
    best_d = wp.length_sq(p0 + p1 + p2)
    for k in range(3):
        a = real(0.0)
        b = lo_s
        if k == 1:
            a = lo_s
            b = hi_s
        elif k == 2:
            a = hi_s
            b = real(1.0)
        fa = _cubic(c3, c2, c1, c0, a)
        fb = _cubic(c3, c2, c1, c0, b)
        t = a
        if fa <= 0.0 and fb >= 0.0:
            lo = a
            hi = b
            if fb > fa:
                t = a - fa * (b - a) / (fb - fa)
            for _ in range(12):
                ft = _cubic(c3, c2, c1, c0, t)
                if ft <= 0.0:
                    lo = t
                if ft >= 0.0:
                    hi = t
                dft = (real(3.0) * c3 * t + real(2.0) * c2) * t + c1
                tn = t - _sdiv(ft, dft)
                if dft > 0.0 and tn >= lo and tn <= hi:
                    t = tn
                else:
                    t = real(0.5) * (lo + hi)
            t = wp.clamp(t, a, b)
        x = p0 + t * (p1 + t * p2)
        d = wp.dot(x, x)
        if d < best_d:
            best_d = d
            best_t = t
    return best_t, best_d


@wp.func
def _step(
    el: Any,
    r: vec3,
    xe: FaceNodes,
    pe: FaceNodes,
    xi: vec2,
    h: mat22,
    g: vec2,
    t0: vec3,
    t1: vec3,
    s00: vec3,
    s01: vec3,
    s11: vec3,
    w1: int,
    w2: int,
):
    """The step for the working set {w1, w2} (-1: empty slot). Empty: Newton (h positive
    definite or Gauss-Newton's) with its second-order correction where both stay on the face
    and the correction is closer; one constraint: to the exact closest point of that edge;
    two: none."""
    if w1 < 0:
        p = -_solve2(h, g)
        for j in range(n_cons(el)):
            if wp.dot(cons_a(el, j), xi + p) < cons_b(el, j):
                return p
        jp = p[0] * t0 + p[1] * t1
        m0 = p[0] * s00 + p[1] * s01
        m1 = p[0] * s01 + p[1] * s11
        xpp = p[0] * m0 + p[1] * m1
        c = vec2(
            real(2.0) * wp.dot(m0, jp) + wp.dot(t0, xpp),
            real(2.0) * wp.dot(m1, jp) + wp.dot(t1, xpp),
        )
        pc = p - _solve2(h, real(0.5) * c)
        # (the correction stays on the face too: see the NumPy step)
        for j in range(n_cons(el)):
            if wp.dot(cons_a(el, j), xi + pc) < cons_b(el, j):
                return p
        if _objective(el, xe, pe, r, xi + pc) < _objective(el, xe, pe, r, xi + p):
            return pc
        return p
    if w2 < 0:
        e = cons_edge(el, w1)
        t, d = closest_point_edge(el, r, xe, e)
        return edge_xi(el, e, t) - xi
    return vec2(0.0)


@wp.func
def closest_point_face(el: Any, r: vec3, xe: FaceNodes, xi0: vec2, iterations: int, tol: real):
    """The closest point to r on the face of nodes xe from xi0 (_active_set)."""
    return _active_set(el, r, xe, coefficients(el, xe), xi0, iterations, tol)


@wp.func
def _active_set(
    el: Any, r: vec3, xe: FaceNodes, pe: FaceNodes, xi0: vec2, iterations: int, tol: real
):
    """Active-set method on min |r - x(xi)|^2 s.t. A xi >= b from xi0 (seed 003 eq. 8), the
    twin of the NumPy "active_set" method: exact Hessian (Gauss-Newton where it is not
    positive definite), steps from `_step`; the working set holds at most two constraints
    (w1, w2 = -1 when empty). Returns xi, feature, local, converged."""
    xi = xi0
    w1 = int(-1)
    w2 = int(-1)
    for j in range(n_cons(el)):
        if wp.abs(wp.dot(cons_a(el, j), xi) - cons_b(el, j)) <= ACTIVE_TOL:
            if w1 < 0:
                w1 = j
            elif w2 < 0:
                w2 = j
    converged = int(0)
    for it in range(iterations + 1):
        x, t0, t1, s00, s01, s11 = _jet(el, xe, pe, xi)
        d = r - x
        g = vec2(-wp.dot(t0, d), -wp.dot(t1, d))
        gn = mat22(wp.dot(t0, t0), wp.dot(t0, t1), wp.dot(t0, t1), wp.dot(t1, t1))
        h = gn - mat22(wp.dot(s00, d), wp.dot(s01, d), wp.dot(s01, d), wp.dot(s11, d))
        scale = wp.max(gn[0, 0] + gn[1, 1], real(1.0e-30))
        k = _least(gn)  # (the residual's scale, sqrt(k tr): arraycontact._geometry._least)
        # multipliers of the working set and the KKT residual
        lam1 = real(0.0)
        lam2 = real(0.0)
        proj = g
        if w1 >= 0 and w2 >= 0:
            a1 = cons_a(el, w1)
            a2 = cons_a(el, w2)
            lam = _solve2(mat22(a1[0], a2[0], a1[1], a2[1]), g)
            lam1 = lam[0]
            lam2 = lam[1]
            proj = g - lam1 * a1 - lam2 * a2
        elif w1 >= 0:
            a1 = cons_a(el, w1)
            lam1 = _sdiv(wp.dot(a1, g), wp.dot(a1, a1))
            proj = g - lam1 * a1
        # (k on one edge: J^T J along it; at a corner the trace; a negative multiplier over
        # the trace)
        if w1 >= 0 and w2 >= 0:
            k = scale
        elif w1 >= 0:
            a1 = cons_a(el, w1)
            t = vec2(-a1[1], a1[0])
            k = _sdiv(wp.dot(t, gn * t), wp.dot(t, t))
        kkt = wp.length(proj) / wp.max(wp.sqrt(k * scale), real(1.0e-30))
        neg = real(0.0)
        jmin = int(-1)
        if w1 >= 0 and lam1 < neg:
            neg = lam1
            jmin = w1
        if w2 >= 0 and lam2 < neg:
            neg = lam2
            jmin = w2
        kkt = wp.max(kkt, -neg / scale)
        pd = h[0, 0] > 0.0 and (h[0, 0] * h[1, 1] - h[0, 1] * h[1, 0]) > 0.0
        if not pd:
            h = gn
        if kkt <= tol:
            converged = 1
            if wp.length_sq(d) <= tol * scale:
                # One Newton step more near the face: free, cut at the border, along an edge
                # that blocks it at once (why: arraycontact._geometry.closest_point_face:
                # float32 near the surface).
                k1 = int(-1)
                for _ in range(3):
                    p = -_solve2(h, g)
                    if k1 >= 0:
                        a1 = cons_a(el, k1)
                        t = vec2(-a1[1], a1[0])
                        p = t * _sdiv(-wp.dot(t, g), wp.dot(t, h * t))
                    # (the iterations' ratio test below, written again: as one wp.func
                    # returning both, quad4 2^20 took 2.89 -> 2.96 ms on an H200)
                    amin = real(1.0)
                    jb = int(-1)
                    for j in range(n_cons(el)):
                        ap = wp.dot(cons_a(el, j), p)
                        if j != k1 and ap < 0.0:
                            step_j = wp.max(
                                -(wp.dot(cons_a(el, j), xi) - cons_b(el, j)) / ap, real(0.0)
                            )
                            if step_j < amin:
                                amin = step_j
                                jb = j
                    if amin > 0.0:
                        # W as the iterations make it: the edge held, the one that cut the
                        # step, every constraint active where it ends (a step within rounding,
                        # as of a slave lying on a vertex, keeps its feature); active within
                        # NumPy's 64 eps (feasible_tol): this step ends anywhere, the
                        # iterations' exactly on edges
                        xi = xi + amin * p
                        w1 = k1
                        w2 = -1
                        if jb >= 0:
                            if w1 < 0:
                                w1 = jb
                            else:
                                w2 = jb
                        for j in range(n_cons(el)):
                            if j != w1 and j != w2:
                                slack = wp.dot(cons_a(el, j), xi) - cons_b(el, j)
                                if wp.abs(slack) <= real(64.0) * EPS:
                                    if w1 < 0:
                                        w1 = j
                                    elif w2 < 0:
                                        w2 = j
                        break
                    k1 = jb  # (blocked at once: along that edge)
            break
        if it == iterations:
            break
        # drop the constraint with the most negative multiplier unless the step would go back
        # through it
        v1 = w1
        v2 = w2
        if jmin >= 0:
            if jmin == w1:
                v1 = w2
                v2 = -1
            else:
                v2 = -1
        p = _step(el, r, xe, pe, xi, h, g, t0, t1, s00, s01, s11, v1, v2)
        if jmin >= 0 and wp.dot(cons_a(el, jmin), p) >= 0.0:
            w1 = v1
            w2 = v2
        else:
            p = _step(el, r, xe, pe, xi, h, g, t0, t1, s00, s01, s11, w1, w2)
        # ratio test
        amin = real(1.0e30)
        jb = int(-1)
        for j in range(n_cons(el)):
            if j != w1 and j != w2:
                ap = wp.dot(cons_a(el, j), p)
                if ap < 0.0:
                    step_j = wp.max(-(wp.dot(cons_a(el, j), xi) - cons_b(el, j)) / ap, real(0.0))
                    if step_j < amin:
                        amin = step_j
                        jb = j
        alpha = wp.min(amin, real(1.0))
        f0 = wp.length_sq(d)  # (_objective at xi: d is r - x(xi))
        ftol = real(16.0) * EPS * (f0 + scale)
        for _ in range(4):
            if _objective(el, xe, pe, r, xi + alpha * p) > f0 + ftol:
                alpha = real(0.5) * alpha
            else:
                break  # (accepted: the rounds left test the same point; H100 quad4 2^20 face
                # scan 2.04 -> 1.95 ms, CPU 2^16 detection 35.5 -> 32.4 ms)
        new = xi + alpha * p
        if jb >= 0 and amin <= alpha:
            # On to the exact closest point of the edge it hit (as NumPy); W gains every
            # constraint active there (both at a corner).
            e = cons_edge(el, jb)
            t_e, d_e = closest_point_edge(el, r, xe, e)
            new = edge_xi(el, e, t_e)
            for j in range(n_cons(el)):
                if j != w1 and j != w2:
                    if j == jb or wp.abs(wp.dot(cons_a(el, j), new) - cons_b(el, j)) <= ACTIVE_TOL:
                        if w1 < 0:
                            w1 = j
                        elif w2 < 0:
                            w2 = j
        xi = new
    feature = FACE
    local = int(-1)
    if w1 >= 0 and w2 >= 0:
        e1 = cons_edge(el, w1)
        e2 = cons_edge(el, w2)
        feature = VERTEX
        local = e1
        if (e1 + 1) % corners(el) == e2:
            local = e2
    elif w1 >= 0:
        feature = EDGE
        local = cons_edge(el, w1)
    return xi, feature, local, converged


@wp.func
def _hessian_det(b0: vec3, a1: vec3, a2: vec3, a3: vec3, s: real, t: real):
    """det H of |x - r|^2 at (xi, eta) = (s, t) on a bilinear face (b0 = a0 - r), and the sum
    of its terms' magnitudes (the scale of its rounding)."""
    xs = a1 + t * a3
    xt = a2 + s * a3
    nn = wp.length_sq(wp.cross(xs, xt))
    b = wp.dot(xs, xt)
    c = wp.dot(b0 + s * a1 + t * a2 + (s * t) * a3, a3)
    return nn - real(2.0) * b * c - c * c, nn + real(2.0) * wp.abs(b * c) + c * c


@wp.func
def _mid(f0: real, fm: real, f1: real):
    """The middle degree-2 Bernstein coefficient from values at an interval's ends and middle."""
    return real(2.0) * fm - real(0.5) * (f0 + f1)


@wp.func
def surely_convex(el: Any, r: vec3, xe: FaceNodes):
    """Whether |x(xi) - r|^2 is strictly convex over a bilinear face (quad4): then its one
    stationary point is the closest point, which one Newton start finds; where this is not
    proven (a warped quad, a point far off it) `project` adds the lattice start, as NumPy
    always does (a warped quad can hold a second, farther local minimum: the crumpled sheet
    of tests/test_self_contact.py).

    x = a0 + a1 xi + a2 eta + a3 xi eta. The Hessian H = J^T J + [[0, c], [c, 0]], c = (x -
    r) . a3, is positive definite where lambda_min(J^T J) >= det / trace exceeds |c|. Over
    the square: |x_xi x x_eta| >= |a1 x a2| - |a1 x a3| - |a3 x a2| (the normal is affine in
    xi), the trace is at most its largest value at a corner, and so is |c| (c is bilinear).
    1% spare covers the rounding. Where that cheap bound fails: H is positive definite
    exactly where det H = |x_xi x x_eta|^2 - 2 (x_xi . x_eta) c - c^2 > 0, a polynomial of
    degree 2 in xi and in eta, so positive over the square when its 9 Bernstein coefficients
    are (from its values on a 3 x 3 grid), 1% of its terms' size spare (crumpled sheet: 54%
    of candidate pairs proven by the first bound, 85% with the second)."""
    a0, a1, a2, a3 = _bilinear(xe)
    low = wp.length(wp.cross(a1, a2)) - wp.length(wp.cross(a1, a3)) - wp.length(wp.cross(a3, a2))
    trace = wp.max(wp.length_sq(a1 + a3), wp.length_sq(a1 - a3))
    trace += wp.max(wp.length_sq(a2 + a3), wp.length_sq(a2 - a3))
    c = wp.max(wp.abs(wp.dot(xe.x0 - r, a3)), wp.abs(wp.dot(xe.x1 - r, a3)))
    c = wp.max(c, wp.max(wp.abs(wp.dot(xe.x2 - r, a3)), wp.abs(wp.dot(xe.x3 - r, a3))))
    if low > real(0.0) and low * low > real(1.01) * trace * c:
        return True
    b0 = a0 - r
    m = real(-1.0)
    p = real(1.0)
    z = real(0.0)
    f00, s00 = _hessian_det(b0, a1, a2, a3, m, m)
    f01, s01 = _hessian_det(b0, a1, a2, a3, m, z)
    f02, s02 = _hessian_det(b0, a1, a2, a3, m, p)
    f10, s10 = _hessian_det(b0, a1, a2, a3, z, m)
    f11, s11 = _hessian_det(b0, a1, a2, a3, z, z)
    f12, s12 = _hessian_det(b0, a1, a2, a3, z, p)
    f20, s20 = _hessian_det(b0, a1, a2, a3, p, m)
    f21, s21 = _hessian_det(b0, a1, a2, a3, p, z)
    f22, s22 = _hessian_det(b0, a1, a2, a3, p, p)
    size = wp.max(wp.max(wp.max(s00, s01), wp.max(s02, s10)), wp.max(wp.max(s11, s12), s20))
    size = wp.max(size, wp.max(s21, s22))
    least = wp.min(wp.min(f00, f02), wp.min(f20, f22))
    c0 = _mid(f00, f01, f02)
    c1 = _mid(f10, f11, f12)
    c2 = _mid(f20, f21, f22)
    least = wp.min(least, wp.min(wp.min(c0, c2), _mid(c0, c1, c2)))
    least = wp.min(least, wp.min(_mid(f00, f10, f20), _mid(f02, f12, f22)))
    return least > real(0.01) * size


@wp.func
def _corner_dist(b00: vec3, b10: vec3, b01: vec3, u: real, v: real):
    return wp.length(b00 + u * b10 + v * b01)


@wp.func
def _tri6_spread(a20: vec3, a11: vec3, a02: vec3, u: real, v: real):
    """|J(c + (u, v)) - J(c)|_F on a tri6: the columns 2 a20 u + a11 v and a11 u + 2 a02 v."""
    return wp.sqrt(
        wp.length_sq(real(2.0) * u * a20 + v * a11) + wp.length_sq(u * a11 + real(2.0) * v * a02)
    )


@wp.func
def curved_convex(el: Any, r: vec3, pe: FaceNodes):
    """Whether |x(xi) - r|^2 is strictly convex over a curved face (tri6, quad8, quad9; pe:
    its monomial coefficients A_pq, `monomials_of`): then its closest point is the one
    stationary point there, which Newton from start I finds (`_project_nodes` skips the other
    starts; NumPy and JAX take the same rule, arraycontact._geometry.curved_convex).

    H = J^T J + C, C_ab = (x - r) . x_ab. About the domain's centre c, with J_c = J(c):
    sigma_min(J) >= sigma_min(J_c) - delta (Weyl), delta >= max |J - J_c|_F over the face,
    and |C|_2 <= |x - r| kappa, kappa >= max sqrt(|x_11|^2 + 2 |x_12|^2 + |x_22|^2); so H is
    positive definite wherever (sigma_min(J_c) - delta)^2 > max |x - r| kappa. On quads
    (centre 0, |xi|, |eta| <= 1) each bound sums its polynomial's coefficients' lengths, the
    affine part of x - r taken at the corners (its exact maximum); on tri6 (c = (1/3, 1/3))
    J - J_c and the affine part of x - r are affine, their maxima at the corners, and the
    quadratic part A20 u^2 + A11 u v + A02 v^2 is at most 4/9, 2/9, 4/9 of its
    coefficients' lengths. 2 % spare (10 % on delta) covers the rounding. Where that fails on
    a tri6, H's own entries, quadratics there, are tested over the triangle
    (`_tri6_hessian_positive`: tight; the rough tri6 scene's candidate pairs, all convex, were
    33 % proven by the bound above alone)."""
    two = real(2.0)
    if corners(el) == 3:
        c = real(1.0) / real(3.0)
        a20 = pe.x6
        a11 = pe.x4
        a02 = pe.x2
        b00 = pe.x0 + c * (pe.x3 + pe.x1) + c * c * (a20 + a11 + a02) - r
        b10 = pe.x3 + two * c * a20 + c * a11
        b01 = pe.x1 + two * c * a02 + c * a11
        m = real(-1.0) / real(3.0)
        p = real(2.0) / real(3.0)
        delta = wp.max(_tri6_spread(a20, a11, a02, m, m), _tri6_spread(a20, a11, a02, p, m))
        delta = wp.max(delta, _tri6_spread(a20, a11, a02, m, p))
        k11 = two * wp.length(a20)
        k12 = wp.length(a11)
        k22 = two * wp.length(a02)
        far = wp.max(_corner_dist(b00, b10, b01, m, m), _corner_dist(b00, b10, b01, p, m))
        far = wp.max(far, _corner_dist(b00, b10, b01, m, p))
        far += (real(4.0) * (k11 + k22) / two + real(2.0) * k12) / real(9.0)
    else:
        b10 = pe.x3
        b01 = pe.x1
        l02 = wp.length(pe.x2)
        l11 = wp.length(pe.x4)
        l12 = wp.length(pe.x5)
        l20 = wp.length(pe.x6)
        l21 = wp.length(pe.x7)
        l22 = wp.length(pe.x8)
        d1 = l11 + l12 + two * (l20 + l21 + l22)
        d2 = two * (l02 + l12 + l22) + l11 + l21
        delta = wp.sqrt(d1 * d1 + d2 * d2)
        k11 = two * (l20 + l21 + l22)
        k12 = l11 + two * (l12 + l21) + real(4.0) * l22
        k22 = two * (l02 + l12 + l22)
        b00 = pe.x0 - r
        one = real(1.0)
        far = wp.max(_corner_dist(b00, b10, b01, one, one), _corner_dist(b00, b10, b01, one, -one))
        far = wp.max(far, _corner_dist(b00, b10, b01, -one, one))
        far = wp.max(far, _corner_dist(b00, b10, b01, -one, -one))
        far += l20 + l11 + l02 + l21 + l12 + l22
    kappa = wp.sqrt(k11 * k11 + two * k12 * k12 + k22 * k22)
    a = wp.length_sq(b10)
    d = wp.length_sq(b01)
    b = wp.dot(b10, b01)
    least = real(0.5) * (a + d - wp.sqrt((a - d) * (a - d) + real(4.0) * b * b))
    sigma = wp.sqrt(wp.max(least, real(0.0)))  # sigma_min(J_c)
    spare = sigma - delta
    if delta < real(0.9) * sigma and spare * spare > real(1.02) * far * kappa:
        return True
    if corners(el) == 3:
        return _tri6_hessian_positive(pe, r)
    return False


@wp.func
def _tri6_h(pe: FaceNodes, r: vec3, s: real, w: real):
    """The Hessian (h11, h12, h22) of |x - r|^2 / 2 on a tri6 at (s, w): J^T J + (x - r) . x_ab."""
    two = real(2.0)
    xs = pe.x3 + two * s * pe.x6 + w * pe.x4
    xw = pe.x1 + s * pe.x4 + two * w * pe.x2
    d = pe.x0 + s * (pe.x3 + s * pe.x6 + w * pe.x4) + w * (pe.x1 + w * pe.x2) - r
    return vec3(
        wp.dot(xs, xs) + two * wp.dot(d, pe.x6),
        wp.dot(xs, xw) + wp.dot(d, pe.x4),
        wp.dot(xw, xw) + two * wp.dot(d, pe.x2),
    )


@wp.func
def _q(g: vec3):
    return g[0] * g[2] - g[1] * g[1]


@wp.func
def _p(g: vec3, k: vec3):
    return g[0] * k[2] + k[0] * g[2] - real(2.0) * g[1] * k[1]


@wp.func
def _tri6_hessian_positive(pe: FaceNodes, r: vec3):
    """Whether the Hessian of |x - r|^2 is positive definite all over a tri6 (`curved_convex`'s
    second test; NumPy's twin arraycontact._geometry._tri6_hessian_positive). Its entries are
    quadratics in (s, w) (x_ab is constant), so h11 and det H = h11 h22 - h12^2 (a quartic)
    are positive over the triangle where their Bernstein coefficients are: h's from its values
    at the corners and mid-edges (b_ij = 2 f(m_ij) - (f_i + f_j) / 2), det's (times 6) from the
    products of the quadratic bases (B_a B_b = C(2; a) C(2; b) / C(4; a + b) B_(a + b)). 0.1 %
    of the largest trace (squared) spare covers the rounding."""
    half = real(0.5)
    two = real(2.0)
    g0 = _tri6_h(pe, r, real(0.0), real(0.0))
    g1 = _tri6_h(pe, r, real(1.0), real(0.0))
    g2 = _tri6_h(pe, r, real(0.0), real(1.0))
    g3 = two * _tri6_h(pe, r, half, real(0.0)) - half * (g0 + g1)
    g4 = two * _tri6_h(pe, r, half, half) - half * (g1 + g2)
    g5 = two * _tri6_h(pe, r, real(0.0), half) - half * (g0 + g2)
    size = wp.max(wp.max(g0[0] + g0[2], g1[0] + g1[2]), g2[0] + g2[2])
    tol = real(1.0e-3) * size
    least = wp.min(wp.min(wp.min(g0[0], g1[0]), wp.min(g2[0], g3[0])), wp.min(g4[0], g5[0]))
    if not (size > real(0.0) and least > tol):
        return False
    six = real(6.0)
    three = real(3.0)
    four = real(4.0)
    c = wp.min(wp.min(six * _q(g0), six * _q(g1)), six * _q(g2))
    c = wp.min(c, wp.min(_p(g0, g1) + four * _q(g3), _p(g0, g2) + four * _q(g5)))
    c = wp.min(c, _p(g1, g2) + four * _q(g4))
    c = wp.min(c, three * wp.min(wp.min(_p(g0, g3), _p(g0, g5)), wp.min(_p(g1, g3), _p(g1, g4))))
    c = wp.min(c, three * wp.min(_p(g2, g5), _p(g2, g4)))
    c = wp.min(c, wp.min(_p(g0, g4) + two * _p(g3, g5), _p(g1, g5) + two * _p(g3, g4)))
    c = wp.min(c, _p(g2, g3) + two * _p(g4, g5))
    return c > six * tol * size


@wp.func
def _range_on_edge(p: vec3, q: vec3, u: vec3, w: vec3):
    """The least and greatest of (p + q t) . (u + w t) over t in [-1, 1] (a quadratic)."""
    a = wp.dot(p, u)
    b = wp.dot(p, w) + wp.dot(q, u)
    c = wp.dot(q, w)
    lo = wp.min(a - b + c, a + b + c)
    hi = wp.max(a - b + c, a + b + c)
    if c != real(0.0):
        t = -b / (real(2.0) * c)
        if t > real(-1.0) and t < real(1.0):
            v = a + real(0.5) * b * t
            lo = wp.min(lo, v)
            hi = wp.max(hi, v)
    return lo, hi


@wp.func
def beyond_an_edge(r: vec3, xe: FaceNodes):
    """Whether r lies beyond an edge of a bilinear face (quad4) all along it, so that
    |x(xi) - r|^2 has no stationary point inside the square and its minimum lies on the edges
    (`exact_edges` alone gives the closest point: no Newton start is needed).

    With x = a0 + a1 xi + a2 eta + a3 xi eta, g = (x - r) . x_xi is affine in xi with slope
    |x_xi|^2 >= 0 (x_xi = a1 + a3 eta does not depend on xi); g < 0 all along the edge xi = 1
    makes it negative over the whole square (and g > 0 along xi = -1 positive), so no
    stationary point; the same with x_eta on the edges eta = +-1. Along an edge g is a
    quadratic whose range is exact; the margin covers rounding. Nodes relative to node 0."""
    a0, a1, a2, a3 = _bilinear(xe)
    a0 = a0 - r
    tol = real(64.0) * EPS * (wp.length(a0) + wp.length(a1) + wp.length(a2) + wp.length(a3))
    tol = tol * (wp.length(a1) + wp.length(a2) + wp.length(a3))
    lo, hi = _range_on_edge(a0 + a1, a2 + a3, a1, a3)  # xi = 1
    out = hi < -tol
    lo, hi = _range_on_edge(a0 - a1, a2 - a3, a1, a3)  # xi = -1
    out = out or lo > tol
    lo, hi = _range_on_edge(a0 + a2, a1 + a3, a2, a3)  # eta = 1
    out = out or hi < -tol
    lo, hi = _range_on_edge(a0 - a2, a1 - a3, a2, a3)  # eta = -1
    return out or lo > tol


@wp.func
def start_option_one(el: Any, r: vec3, xe: FaceNodes):
    """Seed 003 start (I): the closest of the corners and the centre."""
    return _start_one(el, r, xe, coefficients(el, xe))


@wp.func
def _start_one(el: Any, r: vec3, xe: FaceNodes, pe: FaceNodes):
    """start_option_one (pe: `coefficients`)."""
    if is_bilinear(el):  # the corners are the nodes (face_point there is exact)
        best = vec2(-1.0, -1.0)
        best_d = wp.length_sq(r - xe.x0)
        d = wp.length_sq(r - xe.x1)
        if d < best_d:
            best_d = d
            best = vec2(1.0, -1.0)
        d = wp.length_sq(r - xe.x2)
        if d < best_d:
            best_d = d
            best = vec2(1.0, 1.0)
        d = wp.length_sq(r - xe.x3)
        if d < best_d:
            best_d = d
            best = vec2(-1.0, 1.0)
        if _objective(el, xe, pe, r, el.centre) < best_d:
            best = el.centre
        return best
    best = el.nodes[0]
    best_d = _objective(el, xe, pe, r, best)
    for c in range(1, el.n_corners):
        d = _objective(el, xe, pe, r, el.nodes[c])
        if d < best_d:
            best_d = d
            best = el.nodes[c]
    if _objective(el, xe, pe, r, el.centre) < best_d:
        best = el.centre
    return best
