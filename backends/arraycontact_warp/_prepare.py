"""Stage 1 in Warp: the master's geometry from its current coordinates (local frame), every
step: face balls (centre, Lebesgue radius), angle-weighted node pseudo-normals, and the largest
face radius against the one the face grid was planned for (a device-side overflow flag)."""

from __future__ import annotations

import warp as wp

from ._geometry import Element, face_tangents, shape
from ._real import real, vec3

# Forward only, no loop unrolling: the 27-cell stencil unrolled would copy the whole
# projection 27 times into the kernel (minutes of CUDA compilation for no speed).
wp.set_module_options({"enable_backward": False, "max_unroll": 1})


@wp.kernel
def localise(x: wp.array(dtype=vec3), origin: vec3, out: wp.array(dtype=vec3)):
    i = wp.tid()
    out[i] = x[i] - origin


@wp.kernel
def face_bounds(points: wp.array(dtype=vec3), faces: wp.array2d(dtype=int),
                lebesgue: real, r_cap: real,
                centres: wp.array(dtype=vec3), radii: wp.array(dtype=real),
                overflow: wp.array(dtype=int)):
    f = wp.tid()
    nn = faces.shape[1]
    c = vec3(0.0)
    for i in range(nn):
        c += points[faces[f, i]]
    c = c / real(nn)
    r = real(0.0)
    for i in range(nn):
        r = wp.max(r, wp.length(points[faces[f, i]] - c))
    r = lebesgue * r
    centres[f] = c
    radii[f] = r
    if r > r_cap:
        wp.atomic_max(overflow, 0, 1)


@wp.kernel
def node_normals_add(el: Element, points: wp.array(dtype=vec3),
                     faces: wp.array2d(dtype=int), acc: wp.array(dtype=vec3)):
    f, i = wp.tid()
    xi = el.nodes[i]
    t0 = vec3(0.0)
    t1 = vec3(0.0)
    for j in range(el.nn):
        n, d0, d1, h00, h01, h11 = shape(el, xi, j)
        p = points[faces[f, j]]
        t0 += d0 * p
        t1 += d1 * p
    nrm = wp.cross(t0, t1)
    ln = wp.length(nrm)
    if ln > 0.0:
        nrm = nrm / ln
    w = real(1.0)
    k = el.n_corners
    if i < k:
        # Interior angle at the corner, along the natural directions of its two edges.
        e1 = el.nodes[(i + 1) % k] - xi
        e2 = el.nodes[(i + k - 1) % k] - xi
        a = t0 * e1[0] + t1 * e1[1]
        b = t0 * e2[0] + t1 * e2[1]
        w = wp.atan2(wp.length(wp.cross(a, b)), wp.dot(a, b))
    wp.atomic_add(acc, faces[f, i], w * nrm)


@wp.kernel
def normalise(acc: wp.array(dtype=vec3)):
    i = wp.tid()
    ln = wp.length(acc[i])
    if ln > 0.0:
        acc[i] = acc[i] / ln


__all__ = ["localise", "face_bounds", "node_normals_add", "normalise", "face_tangents"]
