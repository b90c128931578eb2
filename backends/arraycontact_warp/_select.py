"""Stage 5 in Warp: the signed gap and normal of the chosen closest point from the pseudo-
normal of its feature (face normal, sum of the normals of the faces sharing the edge, angle-
weighted node normal), as arraycontact._normals does."""

from __future__ import annotations

from typing import Any

import warp as wp

from ._geometry import EDGE, FACE, Triangles, face_nodes, face_tangents
from ._prepare import control_point, n_control
from ._projection import Master, Slab
from ._real import real, vec2, vec3

# Forward only, no loop unrolling (a scan's loops unrolled copy the projection many times into
# the kernel: minutes of CUDA compilation for no speed).
wp.set_module_options({"enable_backward": False, "max_unroll": 1})


@wp.func
def _unit(v: vec3):
    n = wp.length(v)
    if n > 0.0:
        return v / n
    return v


@wp.func
def face_normal(el: Any, m: Master, f: int, xi: vec2):
    xe = face_nodes(m.points, m.faces, f, m.points[m.faces[f, 0]])
    t0, t1 = face_tangents(el, xe, xi)
    return _unit(wp.cross(t0, t1))


@wp.func
def _tangents(el: Any, m: Master, f: int, xi: vec2):
    xe = face_nodes(m.points, m.faces, f, m.points[m.faces[f, 0]])
    return face_tangents(el, xe, xi)


@wp.func
def _tangents(el: Triangles, m: Master, f: int, xi: vec2):  # noqa: F811
    a = m.points[m.faces[f, 0]]
    return m.points[m.faces[f, 1]] - a, m.points[m.faces[f, 2]] - a


# A Warp overload: tri3 normals in closed form.
@wp.func
def face_normal(el: Triangles, m: Master, f: int, xi: vec2):  # noqa: F811
    a = m.points[m.faces[f, 0]]
    return _unit(wp.cross(m.points[m.faces[f, 1]] - a, m.points[m.faces[f, 2]] - a))


@wp.func
def pseudo_normal(el: Any, m: Master, f: int, feature: int, local: int, xi: vec2):
    if feature == FACE:
        return face_normal(el, m, f, xi)
    k = el.n_corners
    if feature == EDGE:
        ca = local
        cb = (local + 1) % k
        xa = el.nodes[ca]
        xb = el.nodes[cb]
        t = wp.dot(xi - xa, xb - xa) / wp.dot(xb - xa, xb - xa)
        na = m.faces[f, ca]
        nb = m.faces[f, cb]
        e = m.face_edges[f, local]
        n = vec3(0.0)
        for side in range(2):
            g = m.edge_faces[e, side]
            if g >= 0:
                ia = int(0)
                ib = int(0)
                for c in range(k):
                    if m.faces[g, c] == na:
                        ia = c
                    if m.faces[g, c] == nb:
                        ib = c
                xg = el.nodes[ia] + t * (el.nodes[ib] - el.nodes[ia])
                n += face_normal(el, m, g, xg)
        return _unit(n)
    return node_normal(el, m, m.faces[f, local])


@wp.func
def classify(
    el: Any, m: Master, f: int, feature: int, local: int, xi: vec2, diff: vec3, on_surface: real
):
    """gap, distance, normal (gap < 0: penetration)."""
    npse = pseudo_normal(el, m, f, feature, local, xi)
    dist = wp.length(diff)
    s = real(1.0)
    if wp.dot(diff, npse) < 0.0:
        s = real(-1.0)
    normal = npse
    if dist > on_surface and feature != FACE:
        normal = s * diff / dist
    return s * dist, dist, normal


@wp.func
def proximal(el: Any, m: Master, s: vec3, node: int):
    """Seed 000 eq. (13), as arraycontact._select.proximal: is s in the proximal volume of
    boundary node `node`? m2 -> m -> m1 follow the boundary; n2, n1 are the normals (at the
    centre) of the faces owning edges (m2, m) and (m, m1). A convex corner (eq. 12) needs both
    half-spaces, a concave one either."""
    rm = m.points[node]
    rm1 = m.points[m.next_node[node]]
    rm2 = m.points[m.prev_node[node]]
    n1 = vec3(0.0)
    n2 = vec3(0.0)
    if m.next_face[node] >= 0:
        n1 = face_normal(el, m, m.next_face[node], el.centre)
    if m.prev_face[node] >= 0:
        n2 = face_normal(el, m, m.prev_face[node], el.centre)
    rs = s - rm
    a = wp.dot(wp.cross(n2, rm - rm2), rs) >= real(0.0)
    b = wp.dot(wp.cross(n1, rm1 - rm), rs) >= real(0.0)
    if wp.dot(wp.cross(rm - rm2, rm1 - rm), n2 + n1) < real(0.0):  # concave
        return a or b
    return a and b


__all__ = ["pseudo_normal", "classify", "face_normal", "proximal"]


# ---------------------------------------------------------------------------------------------
# Self-contact geometry from the current coordinates (arraycontact._surface: node_normals,
# normal_boxes, mesh_sizes).


@wp.func
def _corner_edges(m: Master, f: int, c: int, k: int):
    """The edges from corner c of a straight-edged face (tri3, quad4) to the next corner and
    to the previous one: the corner's tangents (scaled), whose cross product is its normal
    and whose angle is its weight, without the shape functions' derivatives (self-contact's
    geometry, every node and face each call: spiral 2^16 quad4 on the CPU, node normals 4.1
    -> 2.9 ms, the faces' normal boxes 3.0 -> 1.9 ms)."""
    x = m.points[m.faces[f, c]]
    return m.points[m.faces[f, (c + 1) % k]] - x, m.points[m.faces[f, (c + k - 1) % k]] - x


@wp.func
def node_normal(el: Any, m: Master, node: int):
    """The pseudo-normal of a node (arraycontact._surface.node_normals) from the faces around
    it: at a corner the angle-weighted face normals, at a mid-edge or centre node their plain
    sum. Computed where needed (a slave ending on a vertex; self-contact's nodes): cheaper than
    accumulating every node's normal over every face each step."""
    k = el.n_corners
    nn = m.faces.shape[1]
    n = vec3(0.0)
    for j in range(m.nf_offsets[node], m.nf_offsets[node + 1]):
        g = m.nf_ids[j]
        for c in range(nn):
            if m.faces[g, c] == node:
                if nn == k:
                    a, b = _corner_edges(m, g, c, k)
                    n += wp.atan2(wp.length(wp.cross(a, b)), wp.dot(a, b)) * _unit(wp.cross(a, b))
                else:
                    xi = el.nodes[c]
                    t0, t1 = _tangents(el, m, g, xi)
                    w = real(1.0)
                    if c < k:
                        e1 = el.nodes[(c + 1) % k] - xi
                        e2 = el.nodes[(c + k - 1) % k] - xi
                        a = t0 * e1[0] + t1 * e1[1]
                        b = t0 * e2[0] + t1 * e2[1]
                        w = wp.atan2(wp.length(wp.cross(a, b)), wp.dot(a, b))
                    n += w * _unit(wp.cross(t0, t1))
    return _unit(n)


@wp.kernel
def self_node_geometry(
    first: int,
    el: Any,
    m: Master,
    nodes: wp.array(dtype=int),
    h_face: wp.array(dtype=real),
    normals: wp.array(dtype=vec3),
    h_node: wp.array(dtype=real),
):
    """Each used node's pseudo-normal and local mesh size (the mean of its faces' sizes).
    Threads first + t (no atomics: on the CPU in parts)."""
    i = nodes[first + wp.tid()]
    normals[i] = node_normal(el, m, i)
    h = real(0.0)
    for j in range(m.nf_offsets[i], m.nf_offsets[i + 1]):
        h += h_face[m.nf_ids[j]]
    h_node[i] = h / real(wp.max(m.nf_offsets[i + 1] - m.nf_offsets[i], 1))


@wp.func
def _net(m: Master, f: int, i: int, j: int):
    """A quad8 or quad9 face's control net point P_ij (i along xi, j along eta, 0..2): its
    `control_point`s 0-3 at the corners, 4-7 mid-edge, 8 at the centre."""
    c = wp.where(j == 0, 0, wp.where(j == 1, 7, 3))
    if i == 1:
        c = wp.where(j == 0, 4, wp.where(j == 1, 8, 6))
    elif i == 2:
        c = wp.where(j == 0, 1, wp.where(j == 1, 5, 2))
    return control_point(m.points, m.faces, f, c)


@wp.kernel
def self_face_geometry(
    first: int,
    el: Any,
    m: Master,
    lo: wp.array(dtype=vec3),
    hi: wp.array(dtype=vec3),
    h_face: wp.array(dtype=real),
    slab: wp.array(dtype=Slab),
):
    """Each face's normal box (arraycontact._surface.normal_boxes: tri3 its normal, quad4 its
    corner normals, tri6 the nine cross products of x_xi and x_eta at its corners, quad8 and
    quad9 the 36 of their control net's differences), its size (the mean length of its edges)
    and its `Slab`. Threads first + t."""
    f = first + wp.tid()
    nn = m.faces.shape[1]
    k = el.n_corners
    b_lo = vec3(real(-1.0))
    b_hi = vec3(real(1.0))
    if nn == 3 or nn == 4 or nn == 6:
        b_lo = vec3(real(1.0))
        b_hi = vec3(real(-1.0))
        for a in range(k):
            if nn == 6:
                ta, ua = _tangents(el, m, f, el.nodes[a])
                for b in range(k):
                    tb, ub = _tangents(el, m, f, el.nodes[b])
                    g = _unit(wp.cross(ta, ub))
                    b_lo = wp.min(b_lo, g)
                    b_hi = wp.max(b_hi, g)
            elif nn == 4 or a == 0:  # a corner's own normal (tri3: its one normal)
                ta, ua = _corner_edges(m, f, a, k)
                g = _unit(wp.cross(ta, ua))
                b_lo = wp.min(b_lo, g)
                b_hi = wp.max(b_hi, g)
    else:  # quad8, quad9: the 36 cross products of the control net's xi and eta differences
        b_lo = vec3(real(1.0))
        b_hi = vec3(real(-1.0))
        for ni in range(2):
            for nj in range(3):
                along = _net(m, f, ni + 1, nj) - _net(m, f, ni, nj)
                for nk in range(3):
                    for nl in range(2):
                        across = _net(m, f, nk, nl + 1) - _net(m, f, nk, nl)
                        g = _unit(wp.cross(along, across))
                        b_lo = wp.min(b_lo, g)
                        b_hi = wp.max(b_hi, g)
    lo[f] = b_lo
    hi[f] = b_hi
    h = real(0.0)
    for c in range(k):
        h += wp.length(m.points[m.faces[f, (c + 1) % k]] - m.points[m.faces[f, c]])
    h_face[f] = h / real(k)
    sb = Slab(real(0.0), real(0.0), real(0.0), real(-1.0e30), real(1.0e30))
    c0 = m.points[m.faces[f, 0]]
    c1 = m.points[m.faces[f, 1]]
    c2 = m.points[m.faces[f, 2]]
    c3 = c2
    n = wp.cross(c1 - c0, c2 - c0)
    if k == 4:
        c3 = m.points[m.faces[f, 3]]
        n = wp.cross(c2 - c0, c3 - c1)  # (the diagonals': a warped quad's mean normal)
    ln = wp.length(n)
    if ln > real(0.0):
        n = n / ln
        d0 = wp.dot(n, c0)
        d1 = wp.dot(n, c1)
        d2 = wp.dot(n, c2)
        d3 = wp.dot(n, c3)
        s_lo = wp.min(wp.min(d0, d1), wp.min(d2, d3))
        s_hi = wp.max(wp.max(d0, d1), wp.max(d2, d3))
        if nn > 4:  # a curved face: over its Bernstein control points, whose hull holds it
            for i in range(k, n_control(m.faces)):
                d = wp.dot(n, control_point(m.points, m.faces, f, i))
                s_lo = wp.min(s_lo, d)
                s_hi = wp.max(s_hi, d)
        sb = Slab(n[0], n[1], n[2], s_lo, s_hi)
    slab[f] = sb
