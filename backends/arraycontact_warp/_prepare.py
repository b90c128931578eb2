"""Stage 1 in Warp: the master's geometry from its current coordinates (local frame), every
step: face balls (centre, Lebesgue radius) and boxes, and the largest face radius against the
one the face grid was planned for (a device-side overflow flag). Node pseudo-normals are
computed where a slave ends on a vertex (_select.node_normal), not for every node."""

from __future__ import annotations

import warp as wp

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
                lo: wp.array(dtype=vec3), hi: wp.array(dtype=vec3),
                overflow: wp.array(dtype=int)):
    """The ball (c, r) places a face in the grid; the box is what a scan tests. Per axis, with
    m and w the middle and half-width of the nodes' range, x(xi) - m = sum_i N_i (x_i - m), so
    |x(xi) - m| <= lebesgue w: the box m +- lebesgue w holds the face (the nodes' box when the
    shape functions are non-negative), and so does the ball's cube."""
    f = wp.tid()
    nn = faces.shape[1]
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
    centres[f] = c
    radii[f] = r
    m = real(0.5) * (a + b)
    w = real(0.5) * lebesgue * (b - a)
    lo[f] = wp.max(m - w, c - vec3(r))
    hi[f] = wp.min(m + w, c + vec3(r))
    if r > r_cap:
        wp.atomic_max(overflow, 0, 1)


__all__ = ["localise", "face_bounds"]
