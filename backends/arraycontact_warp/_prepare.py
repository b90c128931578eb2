"""Stage 1 in Warp: the master's geometry from its current coordinates (local frame), every
step: face balls (centre, Lebesgue radius) and boxes, computed where the face tree's kernels
need them (reading the nodes, which stay in the cache, costs less than writing and gathering
per-face arrays). Node pseudo-normals are computed where a slave ends on a vertex
(_select.node_normal), not for every node."""

from __future__ import annotations

import warp as wp

from ._real import real, vec3

# Forward only, no loop unrolling (a scan's loops unrolled copy the projection many times into
# the kernel: minutes of CUDA compilation for no speed).
wp.set_module_options({"enable_backward": False, "max_unroll": 1})


@wp.kernel
def localise(x: wp.array(dtype=vec3), origin: vec3, out: wp.array(dtype=vec3)):
    i = wp.tid()
    out[i] = x[i] - origin


@wp.kernel
def localise64(x: wp.array(dtype=wp.vec3d), origin: wp.vec3d, out: wp.array(dtype=vec3)):
    """x - origin from float64 points: subtracted before the cast, so that float32 keeps its
    precision near the local frame's origin."""
    i = wp.tid()
    d = x[i] - origin
    out[i] = vec3(real(d[0]), real(d[1]), real(d[2]))


@wp.func
def control_point(points: wp.array(dtype=vec3), faces: wp.array2d(dtype=int), f: int, i: int):
    """Control point i of a quadratic face's Bernstein form, whose convex hull holds the face
    (tri6: 6 of them, quad8 and quad9: 9; arraycontact._surface.control_points): the corners,
    2 m - (a + b) / 2 for each edge a - m - b, and on quads the centre's, 4 x_c - (sum of the
    mid nodes) + (sum of the corners) / 4, where quad8's x_c is its value at the centre,
    (sum of the mid nodes) / 2 - (sum of the corners) / 4."""
    nn = faces.shape[1]
    k = 4
    if nn == 6:
        k = 3
    if i < k:
        return points[faces[f, i]]
    if i < 2 * k:
        e = i - k
        a = points[faces[f, e]]
        b = points[faces[f, (e + 1) % k]]
        return real(2.0) * points[faces[f, i]] - real(0.5) * (a + b)
    mids = vec3(0.0)
    ends = vec3(0.0)
    for e in range(k):
        mids += points[faces[f, k + e]]
        ends += points[faces[f, e]]
    if nn == 9:
        return real(4.0) * points[faces[f, 8]] - mids + real(0.25) * ends
    return mids - real(0.75) * ends


@wp.func
def n_control(faces: wp.array2d(dtype=int)):
    """A quadratic face's number of control points (`control_point`)."""
    return wp.where(faces.shape[1] == 6, 6, 9)


@wp.func
def face_bounds(points: wp.array(dtype=vec3), faces: wp.array2d(dtype=int), f: int, lebesgue: real):
    """Face f's ball (c, r), which places it in the face grid, and its box [lo, hi], which a
    scan tests. Per axis, with m and w the middle and half-width of the nodes' range,
    x(xi) - m = sum_i N_i (x_i - m), so |x(xi) - m| <= lebesgue w: the box m +- lebesgue w
    holds the face (the nodes' box when the shape functions are non-negative), and so do the
    ball's cube and, on quadratic faces, the box of the Bernstein control points (the
    tightest of the three: a nearly flat quad8's box was 3x its face across, lebesgue 3.03)."""
    nn = faces.shape[1]
    if nn <= 4 and lebesgue == real(1.0):
        # Linear faces (tri3, quad4): the nodes' box itself, as arraycontact._surface's, each
        # corner read once (a refit's gathers run every call: the loops below read them twice).
        x0 = points[faces[f, 0]]
        x1 = points[faces[f, 1]]
        x2 = points[faces[f, 2]]
        x3 = x2
        if nn == 4:
            x3 = points[faces[f, 3]]
        s = x0 + x1 + x2
        if nn == 4:
            s = s + x3
        c = s / real(nn)
        r = wp.max(wp.length(x0 - c), wp.length(x1 - c))
        r = wp.max(r, wp.max(wp.length(x2 - c), wp.length(x3 - c)))
        return c, r, wp.min(wp.min(x0, x1), wp.min(x2, x3)), wp.max(wp.max(x0, x1), wp.max(x2, x3))
    c = vec3(0.0)
    a = points[faces[f, 0]]
    b = a
    for i in range(nn):
        x = points[faces[f, i]]
        c += x
        a = wp.min(a, x)
        b = wp.max(b, x)
    c = c / real(nn)
    r = real(0.0)
    for i in range(nn):
        r = wp.max(r, wp.length(points[faces[f, i]] - c))
    r = lebesgue * r
    m = real(0.5) * (a + b)
    w = real(0.5) * lebesgue * (b - a)
    lo = wp.max(m - w, c - vec3(r))
    hi = wp.min(m + w, c + vec3(r))
    p_lo = points[faces[f, 0]]
    p_hi = p_lo
    for i in range(1, n_control(faces)):
        p = control_point(points, faces, f, i)
        p_lo = wp.min(p_lo, p)
        p_hi = wp.max(p_hi, p)
    return c, r, wp.max(lo, p_lo), wp.min(hi, p_hi)


__all__ = ["control_point", "face_bounds", "localise", "localise64", "n_control"]
