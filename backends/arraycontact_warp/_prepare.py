"""Stage 1 in Warp: the master's geometry from its current coordinates (local frame), every
step: face balls (centre, Lebesgue radius) and the largest face radius against the one the face
grid was planned for (a device-side overflow flag). Node pseudo-normals are computed where a
slave ends on a vertex (_select.node_normal), not for every node."""

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


__all__ = ["localise", "face_bounds"]
