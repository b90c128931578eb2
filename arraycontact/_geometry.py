"""Point-to-face geometry, written once against an array namespace `xp` (NumPy or jax.numpy).

Every function takes batched arrays (a leading batch of point-face pairs) and returns batched
results; nothing branches on data, so the same code runs eagerly, under `jax.jit` and `vmap`.
Each closest-point routine returns natural coordinates `xi`, the feature the point lies on
(FACE / EDGE / VERTEX) and `local`, the local edge or corner id of that feature (-1 for FACE).
"""

from __future__ import annotations

import numpy as np

from ._elements import EDGE, FACE, VERTEX, interpolate, shape_functions, shape_second_derivatives
from ._xp import einsum, fori, is_numpy, lead, rows_dot


def _dot(a, b, xp):
    return xp.sum(a * b, axis=-1)


def _safe_div(a, b, xp):
    ok = b != 0
    return xp.where(ok, a / xp.where(ok, b, 1), 0 * a)


def closest_point_triangle(p, a, b, c, xp=np):
    """Closest point on triangles (a, b, c) to points p, all [..., 3], by Voronoi regions.

    Returns xi = (v, w) with x = a + v (b - a) + w (c - a) (the tri3 natural coordinates),
    the feature and the local edge/corner id. Regions are tested in the order vertex a,
    vertex b, edge ab, vertex c, edge ca, edge bc, interior; the first that holds wins, so a
    point on a region border gets the lower-dimensional feature. Collinear and coincident
    corners fall into an edge or vertex region, never into a division by zero."""
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = _dot(ab, ap, xp), _dot(ac, ap, xp)
    bp = p - b
    d3, d4 = _dot(ab, bp, xp), _dot(ac, bp, xp)
    cp = p - c
    d5, d6 = _dot(ab, cp, xp), _dot(ac, cp, xp)
    v, w, feature, local = _triangle_regions(d1, d2, d3, d4, d5, d6, xp)
    return xp.stack([v, w], -1), feature, local


def triangle_distance(r, e1, e2, xp=np):
    """The distance from points r to triangles (0, e1, e2), each a tuple of its 3 coordinate
    arrays (the Pallas kernels' layout: no axis of 3), by closest_point_triangle's regions and
    arithmetic: the distance of `project` to rounding (the fused multiply-adds a compiler
    may form)."""

    def dot(u, v):
        return u[0] * v[0] + u[1] * v[1] + u[2] * v[2]

    bp = tuple(r[i] - e1[i] for i in range(3))
    cp = tuple(r[i] - e2[i] for i in range(3))
    d = (dot(e1, r), dot(e2, r), dot(e1, bp), dot(e2, bp), dot(e1, cp), dot(e2, cp))
    v, w, _, _ = _triangle_regions(*d, xp)
    g = [r[i] - v * e1[i] - w * e2[i] for i in range(3)]
    return xp.sqrt(dot(g, g))


def _triangle_regions(d1, d2, d3, d4, d5, d6, xp):
    """closest_point_triangle's regions from the dot products of the edges ab, ac with ap,
    bp, cp: v, w, feature, local."""
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    # Each of va, vb, vc is a difference of two products, zero where p projects onto an edge:
    # within its rounding (a fused multiply-add, as XLA and the Warp kernels may compute it,
    # rounds it otherwise) it counts as zero, so every back end puts such a point on the edge.
    r = 4 * xp.finfo(d1.dtype).eps
    ta = r * (abs(d3 * d6) + abs(d5 * d4))
    tb = r * (abs(d5 * d2) + abs(d1 * d6))
    tc = r * (abs(d1 * d4) + abs(d3 * d2))
    zero = 0 * d1
    one = zero + 1
    den = va + vb + vc
    # (condition, v, w, feature, local) from the last region to the first: later assignments win.
    regions = [
        (den > 0, _safe_div(vb, den, xp), _safe_div(vc, den, xp), FACE, -1),
        (
            (va <= ta) & (d4 - d3 >= 0) & (d5 - d6 >= 0),
            1 - _safe_div(d4 - d3, (d4 - d3) + (d5 - d6), xp),
            _safe_div(d4 - d3, (d4 - d3) + (d5 - d6), xp),
            EDGE,
            1,
        ),
        ((vb <= tb) & (d2 >= 0) & (d6 <= 0), zero, _safe_div(d2, d2 - d6, xp), EDGE, 2),
        ((d6 >= 0) & (d5 <= d6), zero, one, VERTEX, 2),
        ((vc <= tc) & (d1 >= 0) & (d3 <= 0), _safe_div(d1, d1 - d3, xp), zero, EDGE, 0),
        ((d3 >= 0) & (d4 <= d3), one, zero, VERTEX, 1),
        ((d1 <= 0) & (d2 <= 0), zero, zero, VERTEX, 0),
    ]
    v, w = zero, zero
    feature = xp.zeros(d1.shape, dtype=xp.int32) + FACE
    local = xp.zeros(d1.shape, dtype=xp.int32) - 1
    for cond, rv, rw, f, loc in regions:
        v, w = xp.where(cond, rv, v), xp.where(cond, rw, w)
        feature = xp.where(cond, f, feature)
        local = xp.where(cond, loc, local)
    return v, w, feature, local


def _least(a, b, c, tiny, xp):
    """The least eigenvalue of the symmetric [[a, b], [b, c]] (J^T J of a face: positive),
    det / the largest (no cancellation where they differ by orders), at least tiny.

    The active-set methods' KKT residual is the projected gradient g over sqrt(k tr J^T J),
    k J^T J's least value over the free directions (this, off the edges): the Gauss-Newton
    step's length in space, |J (J^T J)^-1 g| <= |g| / sqrt(k), relative to the face's size
    sqrt(tr J^T J). Over the trace (as before) it understated that step on a stretched face
    by sqrt(tr / k): on the crumpled tri6 sheet's (tr / k 50-100) float32's tolerance, 1e-4,
    stopped 3e-3 from the point in xi, the distance up to 3e-4 too large. Over k alone (the
    step in natural coordinates) float32 could not reach it on slivers (tr / k up to 5e4),
    whose distances it had to rounding.
    """
    largest = 0.5 * (a + c + xp.sqrt((a - c) ** 2 + 4 * b * b))
    return xp.maximum(_safe_div(a * c - b * b, largest, xp), tiny)


def _solve2(m, r, xp):
    """Solve the 2x2 systems m [..., 2, 2] x = r [..., 2] by Cramer's rule (0 where singular)."""
    det = m[..., 0, 0] * m[..., 1, 1] - m[..., 0, 1] * m[..., 1, 0]
    x0 = r[..., 0] * m[..., 1, 1] - m[..., 0, 1] * r[..., 1]
    x1 = m[..., 0, 0] * r[..., 1] - m[..., 1, 0] * r[..., 0]
    return xp.stack([_safe_div(x0, det, xp), _safe_div(x1, det, xp)], -1)


def closest_point_edge(element, r, xe, xp=np, steps=12):
    """The closest point to r [..., 3] on each whole edge of faces xe [..., nn, 3]: t [..., E]
    (edge e runs from corner e, t = 0, to corner e + 1, t = 1) and the squared distance.

    Every edge here is a polynomial of degree <= 2, x(t) - r = p0 + p1 t + p2 t^2 (from its
    values at t = 0, 1/2, 1), so the derivative of the squared distance, f(t) = c3 t^3 + ...
    + c0, is a cubic. The roots of f' split [0, 1] into at most three pieces on which f is
    monotone; a piece where f rises through zero holds exactly one local minimum, found by
    Newton's method kept inside the shrinking sign-change bracket (bisection when Newton
    leaves it). The global minimum is the smallest of those minima and the ends: no start can
    miss it. All edges and pieces run as one batch (one traced loop on JAX). Straight edges
    (tri3, quad4): the projection on the segment."""
    nodes = element.nodes
    a, b = element.edge_nodes[:, 0], element.edge_nodes[:, 1]
    if element.linear:  # straight edges: f is linear
        x0, x1 = xe[..., a, :], xe[..., b, :]
        u = x1 - x0
        p0 = x0 - r[..., None, :]
        t = xp.clip(_safe_div(-_dot(p0, u, xp), _dot(u, u, xp), xp), 0, 1)
        x = p0 + t[..., None] * u
        return t, _dot(x, x, xp)
    ts = np.array([0.0, 0.5, 1.0])
    samples = nodes[a][:, None] + ts[None, :, None] * (nodes[b] - nodes[a])[:, None]  # [E, 3, 2]
    n = shape_functions(element, samples.reshape(-1, 2)).reshape(len(a), 3, -1)
    x = einsum(xp, "etn,...nk->...etk", xp.asarray(n, dtype=xe.dtype), xe)  # [..., E, 3, 3]
    x0, xm, x1 = x[..., 0, :], x[..., 1, :], x[..., 2, :]
    p0 = x0 - r[..., None, :]
    p1, p2 = 4 * xm - 3 * x0 - x1, 2 * (x0 + x1) - 4 * xm
    c3 = 2 * _dot(p2, p2, xp)
    c2 = 3 * _dot(p1, p2, xp)
    c1 = _dot(p1, p1, xp) + 2 * _dot(p0, p2, xp)
    c0 = _dot(p0, p1, xp)
    # Roots of f' = 3 c3 t^2 + 2 c2 t + c1 (the stable quadratic formula), clipped to [0, 1].
    qa, qb = 3 * c3, 2 * c2
    disc = qb * qb - 4 * qa * c1
    sq = xp.sqrt(xp.maximum(disc, 0))
    q = -0.5 * (qb + xp.where(qb >= 0, sq, -sq))
    real = disc > 0
    s1 = xp.clip(xp.where(real, _safe_div(q, qa, xp), 0 * q), 0, 1)
    s2 = xp.clip(xp.where(real, _safe_div(c1, q, xp), 0 * q), 0, 1)
    s1, s2 = xp.minimum(s1, s2), xp.maximum(s1, s2)
    lo = xp.stack([0 * s1, s1, s2], -1)  # the three pieces [..., E, 3]
    hi = xp.stack([s1, s2, 0 * s2 + 1], -1)
    c3, c2, c1, c0 = c3[..., None], c2[..., None], c1[..., None], c0[..., None]

    def f(t):
        return ((c3 * t + c2) * t + c1) * t + c0

    flo, fhi = f(lo), f(hi)
    rises = (flo <= 0) & (fhi >= 0)
    # Start at the secant root; keep the bracket [lo, hi] with f(lo) <= 0 <= f(hi).
    t0 = xp.where(fhi > flo, lo - flo * _safe_div(hi - lo, fhi - flo, xp), lo)

    def newton(i, state):
        t, lo_, hi_ = state
        ft = f(t)
        lo_ = xp.where(ft <= 0, t, lo_)
        hi_ = xp.where(ft >= 0, t, hi_)
        d = (3 * c3 * t + 2 * c2) * t + c1
        tn = t - _safe_div(ft, d, xp)
        # Inclusive: a converged Newton step lands on the bracket's end it just set.
        return xp.where((d > 0) & (tn >= lo_) & (tn <= hi_), tn, 0.5 * (lo_ + hi_)), lo_, hi_

    t, _, _ = fori(xp, steps, newton, (t0, lo, hi))
    t = xp.where(rises, xp.clip(t, lo, hi), lo)  # a piece without a minimum: its start
    # Candidates: the end t = 1 first, then each piece's; the first smallest wins.
    t = xp.concatenate([0 * t[..., :1] + 1, t], -1)
    xt = p0[..., None, :] + t[..., None] * (p1[..., None, :] + t[..., None] * p2[..., None, :])
    d = _dot(xt, xt, xp)
    k = xp.argmin(d, -1)
    return (
        xp.take_along_axis(t, k[..., None], -1)[..., 0],
        xp.take_along_axis(d, k[..., None], -1)[..., 0],
    )


def closest_point_edges(element, r, xe, xp=np):
    """The closest point over all edges of each face: xi, feature (EDGE or VERTEX), local id
    and squared distance. The first edge wins a tie."""
    t, d = closest_point_edge(element, r, xe, xp)
    e = xp.argmin(d, -1)
    t = xp.take_along_axis(t, e[..., None], -1)[..., 0]
    d = xp.take_along_axis(d, e[..., None], -1)[..., 0]
    k = element.n_corners
    start = xp.asarray(element.corners, xe.dtype)[e]
    xi = start + t[..., None] * (xp.asarray(element.corners, xe.dtype)[(e + 1) % k] - start)
    f = xp.where((t <= 0) | (t >= 1), VERTEX, EDGE).astype(xp.int32)
    loc = xp.where(t <= 0, e, xp.where(t >= 1, (e + 1) % k, e)).astype(xp.int32)
    return xi, f, loc, d


def surely_convex(element, r, xe, xp=np):
    """Whether |x(xi) - r|^2 is strictly convex over each bilinear face xe [..., 4, 3] (quad4):
    then one Newton start finds its closest point to r [..., 3]. x = a0 + a1 xi + a2 eta +
    a3 xi eta; the Hessian J^T J + [[0, c], [c, 0]], c = (x - r) . a3, is positive definite
    where lambda_min(J^T J) >= det / trace exceeds |c|. Over the square |x_xi x x_eta| >=
    |a1 x a2| - |a1 x a3| - |a3 x a2| (the normal is affine in xi), and the trace and |c| are
    at most their largest values at a corner (c is bilinear). 1% spare covers the rounding.
    Where that fails, det H > 0 over the square by its Bernstein coefficients (see the Warp
    kernels' twin, arraycontact_warp._geometry.surely_convex, for both bounds)."""
    return _bilinear_surely_convex(*_bilinear_parts(r, xe), xp)


def _norm(v, xp):
    return xp.sqrt(_dot(v, v, xp))


def curved_convex(element, r, xe, xp=np):
    """Whether |x(xi) - r|^2 is strictly convex over each curved face xe [..., nn, 3] (tri6,
    quad8, quad9; r [..., 3]): then Newton from start I finds its closest point and the other
    starts are not needed. The bounds of the Warp kernels' twin
    (arraycontact_warp._geometry.curved_convex, whose docstring derives them), in the same
    frame (the face's first node) and order, so that the back ends decide alike."""
    c, two = element.coefficients, 2.0
    x0 = xe[..., 0, :]
    rows = [xe[..., i, :] - x0 for i in range(xe.shape[-2])]
    a = {}
    for j, pq in enumerate(element.monomials):
        a[pq] = sum(float(c[i, j]) * rows[i] for i in range(len(rows)) if c[i, j] != 0)
    zero = 0 * x0
    A = {(p, q): a.get((p, q), zero) for p in range(3) for q in range(3)}
    r = r - x0

    def spread(u, v):  # tri6: |J(c + (u, v)) - J(c)|_F
        return xp.sqrt(
            _dot(two * u * A[2, 0] + v * A[1, 1], two * u * A[2, 0] + v * A[1, 1], xp)
            + _dot(u * A[1, 1] + two * v * A[0, 2], u * A[1, 1] + two * v * A[0, 2], xp)
        )

    if element.n_corners == 3:
        t = 1.0 / 3.0
        b00 = A[0, 0] + t * (A[1, 0] + A[0, 1]) + t * t * (A[2, 0] + A[1, 1] + A[0, 2]) - r
        b10 = A[1, 0] + two * t * A[2, 0] + t * A[1, 1]
        b01 = A[0, 1] + two * t * A[0, 2] + t * A[1, 1]
        corners = [(-t, -t), (2 * t, -t), (-t, 2 * t)]
        delta = xp.maximum(
            xp.maximum(spread(*corners[0]), spread(*corners[1])), spread(*corners[2])
        )
        k11, k12, k22 = two * _norm(A[2, 0], xp), _norm(A[1, 1], xp), two * _norm(A[0, 2], xp)
        tail = (4.0 * (k11 + k22) / two + 2.0 * k12) / 9.0
    else:
        b00, b10, b01 = A[0, 0] - r, A[1, 0], A[0, 1]
        n = {pq: _norm(A[pq], xp) for pq in ((0, 2), (1, 1), (1, 2), (2, 0), (2, 1), (2, 2))}
        d1 = n[1, 1] + n[1, 2] + two * (n[2, 0] + n[2, 1] + n[2, 2])
        d2 = two * (n[0, 2] + n[1, 2] + n[2, 2]) + n[1, 1] + n[2, 1]
        delta = xp.sqrt(d1 * d1 + d2 * d2)
        k11 = two * (n[2, 0] + n[2, 1] + n[2, 2])
        k12 = n[1, 1] + two * (n[1, 2] + n[2, 1]) + 4.0 * n[2, 2]
        k22 = two * (n[0, 2] + n[1, 2] + n[2, 2])
        corners = [(1.0, 1.0), (1.0, -1.0), (-1.0, 1.0), (-1.0, -1.0)]
        tail = n[2, 0] + n[1, 1] + n[0, 2] + n[2, 1] + n[1, 2] + n[2, 2]
    far = None
    for u, v in corners:
        d = _norm(b00 + u * b10 + v * b01, xp)
        far = d if far is None else xp.maximum(far, d)
    far = far + tail
    kappa = xp.sqrt(k11 * k11 + two * k12 * k12 + k22 * k22)
    p, q, s = _dot(b10, b10, xp), _dot(b01, b01, xp), _dot(b10, b01, xp)
    least = 0.5 * (p + q - xp.sqrt((p - q) * (p - q) + 4.0 * s * s))
    sigma = xp.sqrt(xp.maximum(least, 0.0))
    spare = sigma - delta
    ok = (delta < 0.9 * sigma) & (spare * spare > 1.02 * far * kappa)
    if element.n_corners == 3:
        ok = ok | _tri6_hessian_positive(A, r, xp)
    return ok


def _tri6_hessian_positive(A, r, xp):
    """The Warp kernels' `_tri6_hessian_positive` (its docstring says why), the same
    arithmetic: A the monomial coefficients {(p, q): [..., 3]}, r in their frame."""
    two, half = 2.0, 0.5

    def h(s, w):
        xs = A[1, 0] + two * s * A[2, 0] + w * A[1, 1]
        xw = A[0, 1] + s * A[1, 1] + two * w * A[0, 2]
        d = A[0, 0] + s * (A[1, 0] + s * A[2, 0] + w * A[1, 1]) + w * (A[0, 1] + w * A[0, 2]) - r
        return (
            _dot(xs, xs, xp) + two * _dot(d, A[2, 0], xp),
            _dot(xs, xw, xp) + _dot(d, A[1, 1], xp),
            _dot(xw, xw, xp) + two * _dot(d, A[0, 2], xp),
        )

    def mid(m, a, b):
        return tuple(two * u - half * (v + w) for u, v, w in zip(m, a, b))

    def q(g):
        return g[0] * g[2] - g[1] * g[1]

    def p(g, k):
        return g[0] * k[2] + k[0] * g[2] - two * g[1] * k[1]

    g0, g1, g2 = h(0.0, 0.0), h(1.0, 0.0), h(0.0, 1.0)
    g3 = mid(h(half, 0.0), g0, g1)
    g4 = mid(h(half, half), g1, g2)
    g5 = mid(h(0.0, half), g0, g2)
    size = xp.maximum(xp.maximum(g0[0] + g0[2], g1[0] + g1[2]), g2[0] + g2[2])
    tol = 1.0e-3 * size
    least = g0[0]
    for g in (g1, g2, g3, g4, g5):
        least = xp.minimum(least, g[0])
    c = [6.0 * q(g0), 6.0 * q(g1), 6.0 * q(g2)]
    c += [p(g0, g1) + 4.0 * q(g3), p(g0, g2) + 4.0 * q(g5), p(g1, g2) + 4.0 * q(g4)]
    c += [3.0 * p(g0, g3), 3.0 * p(g0, g5), 3.0 * p(g1, g3), 3.0 * p(g1, g4)]
    c += [3.0 * p(g2, g5), 3.0 * p(g2, g4)]
    c += [p(g0, g4) + two * p(g3, g5), p(g1, g5) + two * p(g3, g4), p(g2, g3) + two * p(g4, g5)]
    low = c[0]
    for v in c[1:]:
        low = xp.minimum(low, v)
    return (size > 0) & (least > tol) & (low > 6.0 * tol * size)


def start_option_one(element, r, xe, xp=np):
    """Seed 003 start (I): the closest of the corners and the centre, in natural coordinates."""
    cand = np.concatenate([element.corners, element.centre[None]], 0)  # [k+1, 2]
    n = xp.asarray(shape_functions(element, cand), dtype=xe.dtype)  # [k+1, nn]
    x = einsum(xp, "cn,...nk->...ck", n, xe)
    d = xp.sum((x - r[..., None, :]) ** 2, -1)
    best = xp.argmin(d, axis=-1)
    return xp.asarray(cand, dtype=xe.dtype)[best]


def start_option_two(element, r, xe, xp=np):
    """Seed 003 start (II): the centre of the element."""
    c = xp.asarray(element.centre, xe.dtype)
    return xp.zeros(r.shape[:-1] + (2,), dtype=xe.dtype) + lead(xp, c, r.ndim)


def closest_point_face(
    element,
    r,
    xe,
    xi0,
    *,
    iterations,
    tol,
    xp=np,
    method="active_set",
    hessian="exact",
    _resume=None,
):
    """Closest point on faces with nodes xe [P, nn, 3] to points r [P, 3]: seed 003 eq. (8).

    Two methods on the element's linear constraints A xi >= b, both with the exact Hessian of
    eqs. (11)-(13) (Gauss-Newton where that is not positive definite) and a fixed number of
    iterations (static shapes):

    - "active_set": a primal active-set method. Each iteration drops the working-set
      constraint with the most negative multiplier; with no working constraint it takes the
      Newton step (with its second-order correction where both stay on the face and the
      correction is closer), with one it goes to the closest point of that edge (exact:
      closest_point_edge); it halves the step while the distance grows, and a step that
      meets a constraint (ratio test) goes on to the exact closest point of that edge.
    - "sqp": sequential quadratic programming. Each iteration takes the best feasible one of:
      the free Newton step of the quadratic model, its second-order correction, and the exact
      closest point on each edge (which holds the model's minimiser on each constraint line
      and each corner); it halves the step while the distance grows; iterates stay feasible.

    Both count one iteration per evaluation of the derivatives at an iterate; the edges'
    closed-form solutions are part of the iteration that uses them.

    Returns xi, feature, local, converged (KKT residual <= tol), iterations used (the first
    iteration after which the KKT conditions held) and the final KKT residual (in natural
    coordinates: the projected gradient over sqrt(k tr J^T J), k J^T J's least value in the
    free directions, see `_least`; a negative multiplier over the trace)."""
    if element.name == "quad4" and method == "active_set" and hessian == "exact":
        if not is_numpy(xp) and _resume is None:  # (the same steps, fused: see its docstring)
            return _closest_point_bilinear(r, xe, xi0, iterations=iterations, tol=tol, xp=xp)
    A = xp.asarray(element.constraints_a, dtype=xe.dtype)  # [m, 2]
    # b and the constraint indices as rows over the leading axes of xi0 (explicit broadcasts).
    b = lead(xp, xp.asarray(element.constraints_b, dtype=xe.dtype), xi0.ndim)
    m = A.shape[0]
    ar = lead(xp, xp.arange(m), xi0.ndim)
    ce = element.constraint_edge
    feasible_tol = 64 * xp.finfo(xe.dtype).eps

    def objective(xi):
        # xi [..., 2] or [..., c, 2] (several candidates per face)
        n = shape_functions(element, xi, xp)
        if xi.ndim == r.ndim + 1:
            x = einsum(xp, "...cn,...nk->...ck", n, xe)
            return xp.sum((r[..., None, :] - x) ** 2, -1)
        x = einsum(xp, "...n,...nk->...k", n, xe)
        return xp.sum((r - x) ** 2, -1)

    def derivatives(xi):
        x, dx = interpolate(element, xe, xi, xp)
        d = r - x
        g = -einsum(xp, "...ka,...k->...a", dx, d)
        gn = einsum(xp, "...ka,...kb->...ab", dx, dx)
        if element.linear and element.kind == "tri":
            h = gn
        else:
            d2 = einsum(xp, "...ns,...nk->...ks", shape_second_derivatives(element, xi, xp), xe)
            c = einsum(xp, "...ks,...k->...s", d2, d)
            h = gn - xp.stack(
                [xp.stack([c[..., 0], c[..., 1]], -1), xp.stack([c[..., 1], c[..., 2]], -1)], -2
            )
        if hessian != "exact":
            h = gn
        scale = xp.maximum(gn[..., 0, 0] + gn[..., 1, 1], xp.finfo(xe.dtype).tiny)
        return g, h, gn, scale

    def stiffness(gn, w):
        # The residual's scale (see _least): sqrt(k tr J^T J), k J^T J's least value over the
        # free directions (its least eigenvalue off the edges, its value along the one edge in
        # W); the trace at a corner (no free direction: only the multipliers, as before).
        tiny = xp.finfo(xe.dtype).tiny
        a = A[xp.argmax(w, -1)]
        t0, t1 = -a[..., 1], a[..., 0]
        along = t0 * t0 * gn[..., 0, 0] + 2 * t0 * t1 * gn[..., 0, 1] + t1 * t1 * gn[..., 1, 1]
        along = _safe_div(along, t0 * t0 + t1 * t1, xp)
        nw = xp.sum(w, -1)
        least = _least(gn[..., 0, 0], gn[..., 0, 1], gn[..., 1, 1], tiny, xp)
        trace = xp.maximum(gn[..., 0, 0] + gn[..., 1, 1], tiny)
        k = xp.where(nw == 0, least, xp.where(nw == 1, along, trace))
        return xp.maximum(xp.sqrt(k * trace), tiny)

    def chebyshev(xi, p, h):
        # The second-order (Chebyshev) correction of a Newton step p on the gradient
        # g = J^T (x - r): solve h c = -1/2 g''(p, p) with g''(p, p) = 2 X''(., p)^T (J p) +
        # J^T X''(p, p), the term (x - r) . X'''(., p, p) left out (it vanishes as the
        # residual does). Near a zero-residual solution (a point on the face) the error of
        # p + c is cubic in that of xi instead of quadratic: one derivative evaluation fewer.
        # (Zero on tri3, whose X'' is zero.)
        _, dx = interpolate(element, xe, xi, xp)
        d2 = einsum(xp, "...ns,...nk->...ks", shape_second_derivatives(element, xi, xp), xe)
        jp = einsum(xp, "...ka,...a->...k", dx, p)
        m0 = d2[..., 0] * p[..., 0:1] + d2[..., 1] * p[..., 1:2]  # X''(e_xi, p)
        m1 = d2[..., 1] * p[..., 0:1] + d2[..., 2] * p[..., 1:2]  # X''(e_eta, p)
        xpp = m0 * p[..., 0:1] + m1 * p[..., 1:2]
        c = 2 * xp.stack([_dot(m0, jp, xp), _dot(m1, jp, xp)], -1)
        c = c + einsum(xp, "...ka,...k->...a", dx, xpp)
        return p - _solve2(h, 0.5 * c, xp)

    def multipliers(g, w):
        # KKT: g = sum_{j in W} lambda_j a_j. With one active row, lambda = a.g/|a|^2; with two,
        # solve the 2x2 system. Rows outside W get +inf so they are never dropped.
        nw = xp.sum(w, -1)
        j1 = xp.argmax(w, -1)
        j2 = m - 1 - xp.argmax(w[..., ::-1], -1)
        a1, a2 = A[j1], A[j2]
        lam1 = _safe_div(_dot(a1, g, xp), _dot(a1, a1, xp), xp)
        both = _solve2(xp.stack([a1, a2], -1), g, xp)
        l1 = xp.where(nw == 2, both[..., 0], lam1)
        l2 = xp.where(nw == 2, both[..., 1], np.inf)
        lam = xp.where(ar == j1[..., None], l1[..., None], np.inf)
        lam = xp.where((ar == j2[..., None]) & (nw[..., None] == 2), l2[..., None], lam)
        return xp.where(w, lam, np.inf)

    def edge_points(xi):
        # The exact closest point on each edge, as a step from xi: [..., n_edges, 2]. A working
        # set of one constraint is an edge, and the closest point on it is known in closed
        # form (closest_point_edge), so one iteration lands on it however curved the edge.
        t, _ = closest_point_edge(element, r, xe, xp)
        k = element.n_corners
        start = xp.asarray(element.corners, xe.dtype)
        end = xp.asarray(element.corners[(np.arange(k) + 1) % k], xe.dtype)
        n = t.ndim + 1
        return lead(xp, start, n) + t[..., None] * lead(xp, end - start, n) - xi[..., None, :]

    def model(h, gn):
        # The model's Hessian: the exact one where it is positive definite, Gauss-Newton's
        # (always positive on a non-degenerate face) where not.
        pd = (h[..., 0, 0] > 0) & (h[..., 0, 0] * h[..., 1, 1] - h[..., 0, 1] ** 2 > 0)
        return xp.where(pd[..., None, None], h, gn)

    def step(xi, g, h, gn, w, p_edges):
        # Free: Newton with the model's Hessian (`model`), plus its second-order
        # correction. One working constraint: to that edge's closest point. Two: stay.
        nw = xp.sum(w, -1)
        j1 = xp.argmax(w, -1)
        hq = model(h, gn)
        p0 = -_solve2(hq, g, xp)
        # Only for a Newton step that stays on the face: far outside, the correction of a poor
        # model step is no better and can stall the ratio test. The correction must stay on the
        # face too: from an edge whose constraint is being dropped, a corrected step back out
        # through it would keep the constraint, and the iterate, where they are for good (a
        # convex tri6 pair stalled so, 1.15 from its closest point).
        pc = chebyshev(xi, p0, hq)
        inside = (rows_dot(xp, xi + p0, A) - b >= 0).all(-1)
        inside = inside & (rows_dot(xp, xi + pc, A) - b >= 0).all(-1)
        # (compared on the lanes that use them: elsewhere the steps can be huge, and float32
        # overflowed in their objective)
        ins = inside[..., None]
        p0 = xp.where(ins, better(xi, xp.where(ins, p0, 0), xp.where(ins, pc, 0)), p0)
        p1 = xp.take_along_axis(p_edges, xp.asarray(ce)[j1][..., None, None], -2)[..., 0, :]
        return xp.where((nw == 0)[..., None], p0, xp.where((nw == 1)[..., None], p1, 0 * p0))

    def better(xi, p, q):
        # The step to the smaller distance (p on a tie).
        return xp.where((objective(xi + q) < objective(xi + p))[..., None], q, p)

    def residual(g, w, gn):
        lam = multipliers(g, w)
        lam_w = xp.where(w, lam, 0)
        proj = g - einsum(xp, "...j,ja->...a", lam_w, A)
        kkt = xp.sqrt(xp.sum(proj**2, -1)) / stiffness(gn, w)
        neg = xp.min(xp.where(w, lam, np.inf), -1)
        trace = xp.maximum(gn[..., 0, 0] + gn[..., 1, 1], xp.finfo(xe.dtype).tiny)
        kkt = xp.maximum(kkt, xp.where(neg < 0, -neg / trace, 0))
        return kkt, lam

    def ratios(xi, p, w):
        # Ratio test: how far along p each constraint outside W lets xi go (inf: any way).
        ap = rows_dot(xp, p, A)
        alpha_j = xp.where((ap < 0) & ~w, _safe_div(b - rows_dot(xp, xi, A), ap, xp), np.inf)
        return xp.maximum(alpha_j, 0)

    def iteration(it, state):
        xi, w, done, iters = state
        g, h, gn, scale = derivatives(xi)
        kkt, lam = residual(g, w, gn)
        newly = (kkt <= tol) & ~done
        iters = xp.where(newly, it + 1, iters)
        done = done | newly
        # Drop the working constraint with the most negative multiplier, unless the step on the
        # smaller working set would lead straight back through it (then keep it, move along).
        jmin = xp.argmin(lam, -1)
        drop = (xp.min(lam, -1) < 0) & ~done
        w_drop = w & ~((ar == jmin[..., None]) & drop[..., None])
        p_edges = edge_points(xi)
        p_drop = step(xi, g, h, gn, w_drop, p_edges)
        drop = drop & (_dot(A[jmin], p_drop, xp) >= 0)
        w = xp.where(drop[..., None], w_drop, w)
        p = xp.where(drop[..., None], p_drop, step(xi, g, h, gn, w, p_edges))
        alpha_j = ratios(xi, p, w)
        jb = xp.argmin(alpha_j, -1)
        alpha = xp.minimum(xp.min(alpha_j, -1), 1.0)
        # Halve the step while the distance grows (a fixed number of times).
        f0 = objective(xi)
        # Growth below rounding is no growth: halving on noise would stall the last steps.
        f_tol = 16 * xp.finfo(xe.dtype).eps * (f0 + scale)
        for _ in range(4):
            grow = objective(xi + alpha[..., None] * p) > f0 + f_tol
            alpha = xp.where(grow, 0.5 * alpha, alpha)
        blocked = (xp.min(alpha_j, -1) <= alpha) & ~done
        new = xi + alpha[..., None] * p
        # A step that hit a constraint goes on to the exact closest point of that edge (the
        # next working set's solution, known without new derivatives); W holds every
        # constraint active there (both at a corner).
        on_edge = (
            xi + xp.take_along_axis(p_edges, xp.asarray(ce)[jb][..., None, None], -2)[..., 0, :]
        )
        new = xp.where(blocked[..., None], on_edge, new)
        w = w | (blocked[..., None] & (xp.abs(rows_dot(xp, new, A) - b) <= feasible_tol))
        w = w | ((ar == jb[..., None]) & blocked[..., None])
        return xp.where(done[..., None], xi, new), w, done, iters

    def sqp_iteration(it, state):
        xi, w, done, iters = state
        g, h, gn, scale = derivatives(xi)
        w = xp.abs(rows_dot(xp, xi, A) - b) <= feasible_tol
        kkt, _ = residual(g, w, gn)
        newly = (kkt <= tol) & ~done
        iters = xp.where(newly, it + 1, iters)
        done = done | newly
        hq = model(h, gn)
        p_newton = -_solve2(hq, g, xp)
        cands = xp.stack([p_newton, chebyshev(xi, p_newton, hq)], -2)
        p_all = xp.concatenate([cands, edge_points(xi)], -2)  # [..., n_cand, 2]
        feas = (rows_dot(xp, xi[..., None, :] + p_all, A) - b >= -feasible_tol).all(-1)
        # Choose by the true distance: the edge candidates are exact, the model's are not.
        f_all = objective(xi[..., None, :] + p_all)
        best = xp.argmin(xp.where(feas, f_all, np.inf), -1)
        p = xp.take_along_axis(p_all, best[..., None, None], -2)[..., 0, :]
        alpha = xp.ones(xi.shape[:-1], dtype=xe.dtype)
        f0 = objective(xi)
        # Growth below rounding is no growth: halving on noise would stall the last steps.
        f_tol = 16 * xp.finfo(xe.dtype).eps * (f0 + scale)
        for _ in range(4):
            grow = objective(xi + alpha[..., None] * p) > f0 + f_tol
            alpha = xp.where(grow, 0.5 * alpha, alpha)
        new = xi + alpha[..., None] * p
        return xp.where(done[..., None], xi, new), w, done, iters

    if _resume is None:
        w0 = xp.abs(rows_dot(xp, xi0, A) - b) <= feasible_tol
        iters0, it0 = xp.zeros(xi0.shape[:-1], dtype=xp.int32), 0
    else:  # (NumPy: the pairs not yet done, gathered: their working sets, counts, iteration)
        w0, iters0, it0 = _resume
    done0 = xp.zeros(xi0.shape[:-1], dtype=bool)
    body = sqp_iteration if method == "sqp" else iteration
    state = (xi0, w0, done0, iters0)
    busy = None
    if is_numpy(xp):
        # Iterations after every pair is done change nothing (a done pair keeps its state);
        # once at most 1/8 of many pairs are left, they go on gathered (a few pairs that
        # need every iteration were most of a quad8 surface's detection).
        for it in range(it0, iterations):
            left = np.flatnonzero(~state[2])
            if not len(left):
                break
            if len(state[2]) >= 1024 and 8 * len(left) <= len(state[2]):
                busy = left
                break
            state = body(it, state)
        xi, w, done, iters = state
    else:
        xi, w, done, iters = fori(xp, iterations, body, state, stop=lambda s: xp.all(s[2]))
    if method == "sqp":
        w = xp.abs(rows_dot(xp, xi, A) - b) <= feasible_tol
    g, h, gn, _ = derivatives(xi)
    kkt, _ = residual(g, w, gn)
    converged = kkt <= tol
    iters = xp.where(done, iters, iterations + 1)
    # One Newton step more where the projection met its tolerance within sqrt(tol) face sizes
    # of the face, from the derivatives the residual was checked with, whatever its working
    # set: the free step, cut at the face's border (which it then holds); one that an edge
    # blocks at once goes along that edge instead, and then along the next. (Of a convex
    # model, a feature whose KKT conditions hold blocks each at once: it stays.) Why: for a
    # slave on the face or just off it the distance is first order in the error of xi, and
    # float32's tolerance (1e-4 in natural coordinates, on the multipliers too) left distances
    # off by up to 1.7e-4 of the longest edge (tri6) against the 1e-5 promised: iterates short
    # of the answer inside, or held at an edge or a corner whose multiplier was just negative
    # (or positive in a corner's decomposition, with the answer just inside). Near the answer
    # Newton converges quadratically, so one step takes that to rounding for a 2x2 solve (a
    # tolerance tight enough for the same took tri6's float32 detection 75 % longer on an
    # H200: iterations at rounding). Farther off, the error is second order, under tol
    # sqrt(tr J^T J) / 2 there, and the step is left out (on every candidate face it cost
    # 5-10 % of float32's detection on an H200).
    keep = xp.zeros_like(w)
    trace = xp.maximum(gn[..., 0, 0] + gn[..., 1, 1], xp.finfo(xe.dtype).tiny)
    active = done & (objective(xi) <= tol * trace)
    hq = model(h, gn)
    p_free = -_solve2(hq, g, xp)
    for _ in range(3):  # (blocked at once by an edge: along that edge instead, twice at most)
        a = A[xp.argmax(keep, -1)]
        t = xp.stack([-a[..., 1], a[..., 0]], -1)  # (along the edge held)
        tht = _dot(t, xp.sum(hq * t[..., None, :], -1), xp)
        p_edge = t * _safe_div(-_dot(t, g, xp), tht, xp)[..., None]
        p = xp.where((xp.sum(keep, -1) == 0)[..., None], p_free, p_edge)
        alpha_j = ratios(xi, p, keep)
        amin = xp.min(alpha_j, -1)
        hit = ar == xp.argmin(alpha_j, -1)[..., None]
        go = active & (amin > 0)
        xi = xi + xp.where(go, xp.minimum(amin, 1.0), 0)[..., None] * p
        # (W as the iterations make it: the edge held, the one that cut the step, and every
        # constraint active where it ends, so that a step within rounding, as of a slave lying
        # on a vertex or an edge, keeps its feature)
        on = xp.abs(rows_dot(xp, xi, A) - b) <= feasible_tol
        w = xp.where(go[..., None], keep | (hit & (amin < 1)[..., None]) | on, w)
        active = active & ~go
        keep = xp.where(active[..., None], hit, keep)
    nw = xp.sum(w, -1)
    j1 = xp.argmax(w, -1)
    j2 = m - 1 - xp.argmax(w[..., ::-1], -1)
    e1 = xp.asarray(ce)[j1]
    e2 = xp.asarray(ce)[j2]
    k = element.n_corners
    # Two active constraints meet at the corner shared by their edges: edge e runs from
    # corner e to corner e+1, so the shared corner of e1 and e2 is the end of one of them.
    corner = xp.where((e1 + 1) % k == e2, e2, e1)
    feature = xp.where(nw == 0, FACE, xp.where(nw == 1, EDGE, VERTEX)).astype(xp.int32)
    local = xp.where(nw == 0, -1, xp.where(nw == 1, e1, corner)).astype(xp.int32)
    out = (xi, feature, local, converged, iters, kkt)
    if busy is not None:
        inner = closest_point_face(
            element,
            r[busy],
            xe[busy],
            xi[busy],
            iterations=iterations,
            tol=tol,
            method=method,
            hessian=hessian,
            _resume=(w[busy], iters[busy], it),
        )
        for a, b_ in zip(out, inner):
            a[busy] = b_
    return out


def _vdot(p, q):
    """p . q of vectors held as 3-tuples of arrays (one array a coordinate)."""
    return p[0] * q[0] + p[1] * q[1] + p[2] * q[2]


def _bilinear_parts(r, xe):
    """Points r [..., 3] and bilinear faces xe [..., 4, 3] one array a coordinate: R, the
    corners X[i] and the coefficients a0..a3 of x(u, v) = a0 + a1 u + a2 v + a3 u v."""
    X = [tuple(xe[..., i, k] for k in range(3)) for i in range(4)]
    R = tuple(r[..., k] for k in range(3))

    def comb(c):
        return tuple(0.25 * (c[0] * X[0][k] + c[1] * X[1][k] + c[2] * X[2][k] + c[3] * X[3][k])
                     for k in range(3))  # fmt: skip

    a = comb((1, 1, 1, 1)), comb((-1, 1, 1, -1)), comb((-1, -1, 1, 1)), comb((1, -1, 1, -1))
    return R, X, a


#: quad4's corners in natural coordinates; edge e runs from corner e to corner e + 1.
_SQUARE = ((-1.0, -1.0), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0))


def _bilinear_edges(R, X, xp):
    """Each edge's exact closest point to r (`closest_point_edge` on a straight edge): its
    parameter t from corner e (0) to corner e + 1 (1), and the squared distance, per edge."""
    ts, ds = [], []
    for e in range(4):
        x0, x1 = X[e], X[(e + 1) % 4]
        ue = tuple(x1[k] - x0[k] for k in range(3))
        p0 = tuple(x0[k] - R[k] for k in range(3))
        t = xp.clip(_safe_div(-_vdot(p0, ue), _vdot(ue, ue), xp), 0, 1)
        q = tuple(p0[k] + t * ue[k] for k in range(3))
        ts.append(t)
        ds.append(_vdot(q, q))
    return ts, ds


def _bilinear_d2(R, a, u, v):
    """|r - x(u, v)|^2."""
    d = tuple(R[k] - (a[0][k] + a[1][k] * u + a[2][k] * v + a[3][k] * (u * v)) for k in range(3))
    return _vdot(d, d)


def _first_smallest(vals, xp):
    """The index of the first smallest of a list of arrays, and that value."""
    j, best = xp.zeros(vals[0].shape, np.int32), vals[0]
    for i in range(1, len(vals)):
        less = vals[i] < best
        j, best = xp.where(less, i, j), xp.where(less, vals[i], best)
    return j, best


def bilinear_best_of_starts(r, xe, *, iterations, tol, xp):
    """`_projection._best_of_starts` on bilinear faces (quad4) under JAX, one array a
    coordinate as `_closest_point_bilinear` (for the same reason: the generic code's axes of
    3 and 4 cost a kernel each, about 0.9 ms a round of 2^20 pairs on an H100): start option
    I, the lattice start where `surely_convex`'s two bounds do not prove one minimum, the
    closer of their Newton results (the first on a tie), then the edges' exact closest point
    where at most as far. The same choices as the generic code."""
    R, X, a = _bilinear_parts(r, xe)
    corners = _SQUARE
    # Start option I: the closest of the corners and the centre.
    d = [_vdot(*[tuple(X[i][k] - R[k] for k in range(3))] * 2) for i in range(4)]
    d.append(_bilinear_d2(R, a, 0.0, 0.0))
    j, _ = _first_smallest(d, xp)
    cand = corners + ((0.0, 0.0),)
    first = [sum(xp.where(j == i, c[q], 0.0) for i, c in enumerate(cand)) for q in range(2)]
    first = xp.stack(first, -1).astype(xe.dtype)
    convex = _bilinear_surely_convex(R, X, a, xp)
    kw = dict(iterations=iterations, tol=tol, xp=xp)

    def one():
        return _closest_point_bilinear(r, xe, first, **kw)[:4]

    def two():
        # The lattice start (arraycontact._projection._lattice_start: the closest of a 5 x 5
        # lattice; over an axis of its 25 points, which, unrolled, made the program compile
        # 0.3 s longer on the CPU), both starts in one batch, the lattice's result only where
        # not convex.
        s = np.linspace(-0.8, 0.8, 5)
        lat = np.stack(np.meshgrid(s, s, indexing="ij"), -1).reshape(-1, 2)
        lead1 = (1,) * R[0].ndim
        u, v = (xp.asarray(lat[:, q].reshape(lead1 + (-1,)), xe.dtype) for q in range(2))
        d2 = _bilinear_d2(
            tuple(c[..., None] for c in R), [tuple(c[..., None] for c in ai) for ai in a], u, v
        )
        start = xp.asarray(lat, xe.dtype)[xp.argmin(d2, -1)]
        both = _closest_point_bilinear(
            xp.concatenate([r, r]), xp.concatenate([xe, xe]), xp.concatenate([first, start]), **kw
        )
        n = r.shape[0]
        d0 = _bilinear_d2(R, a, both[0][:n, 0], both[0][:n, 1])
        d1 = _bilinear_d2(R, a, both[0][n:, 0], both[0][n:, 1])
        take = ~convex & (d1 < d0)
        return tuple(
            xp.where(take.reshape(take.shape + (1,) * (o.ndim - 1)), o[n:], o[:n]) for o in both[:4]
        )

    import jax

    xi, feature, local, converged = jax.lax.cond(xp.all(convex), one, two)
    # The edges (closest_point_edges: the first smallest of the four exact projections).
    ts, ds = _bilinear_edges(R, X, xp)
    e, e_d = _first_smallest(ds, xp)
    t = sum(xp.where(e == i, ts[i], 0.0) for i in range(4))
    e_xi = []
    for q in range(2):
        s0 = sum(xp.where(e == i, corners[i][q], 0.0) for i in range(4))
        s1 = sum(xp.where(e == i, corners[(i + 1) % 4][q], 0.0) for i in range(4))
        e_xi.append(s0 + t * (s1 - s0))
    e_f = xp.where((t <= 0) | (t >= 1), VERTEX, EDGE).astype(np.int32)
    e_loc = xp.where(t >= 1, (e + 1) % 4, e).astype(np.int32)
    use = e_d <= _bilinear_d2(R, a, xi[..., 0], xi[..., 1])
    return (
        xp.where(use[..., None], xp.stack(e_xi, -1).astype(xe.dtype), xi),
        xp.where(use, e_f, feature),
        xp.where(use, e_loc, local),
        converged | use,
    )


def _bilinear_surely_convex(R, X, a, xp):
    """`surely_convex` (its docstring says why), one array a coordinate: the NumPy code and
    the JAX quad4 projection (`bilinear_best_of_starts`) both run it."""
    _, a1, a2, a3 = a

    def cross(p, q):
        return (p[1] * q[2] - p[2] * q[1], p[2] * q[0] - p[0] * q[2], p[0] * q[1] - p[1] * q[0])

    def norm(v):
        return xp.sqrt(_vdot(v, v))

    def sq(p, q, s):  # |p + s q|^2
        return _vdot(*[tuple(p[k] + s * q[k] for k in range(3))] * 2)

    low = norm(cross(a1, a2)) - norm(cross(a1, a3)) - norm(cross(a3, a2))
    trace = xp.maximum(sq(a1, a3, 1), sq(a1, a3, -1)) + xp.maximum(sq(a2, a3, 1), sq(a2, a3, -1))
    c = [xp.abs(_vdot(tuple(X[i][k] - R[k] for k in range(3)), a3)) for i in range(4)]
    c = xp.maximum(xp.maximum(c[0], c[1]), xp.maximum(c[2], c[3]))
    cheap = (low > 0) & (low * low > 1.01 * trace * c)
    b0 = tuple(a[0][k] - R[k] for k in range(3))
    g = (-1.0, 0.0, 1.0)
    f, size = [], 0
    for s in g:
        row = []
        for t in g:
            xs = tuple(a1[k] + t * a3[k] for k in range(3))
            xt = tuple(a2[k] + s * a3[k] for k in range(3))
            cr = cross(xs, xt)
            nn = _vdot(cr, cr)
            b = _vdot(xs, xt)
            cc = _vdot(tuple(b0[k] + s * a1[k] + t * a2[k] + (s * t) * a3[k] for k in range(3)), a3)
            row.append(nn - 2 * b * cc - cc * cc)
            size = xp.maximum(size, nn + 2 * xp.abs(b * cc) + cc * cc)
        f.append(row)

    def mid(f0, fm, f1):
        return 2 * fm - 0.5 * (f0 + f1)

    cm = [mid(*row) for row in f]
    coefs = [f[0][0], f[0][2], f[2][0], f[2][2], cm[0], cm[2], mid(*cm)]
    coefs += [mid(f[0][0], f[1][0], f[2][0]), mid(f[0][2], f[1][2], f[2][2])]
    least = coefs[0]
    for v in coefs[1:]:
        least = xp.minimum(least, v)
    return cheap | (least > 0.01 * size)


def _closest_point_bilinear(r, xe, xi0, *, iterations, tol, xp):
    """`closest_point_face`'s active-set method on bilinear faces (quad4), the same steps
    written on one array a coordinate: x = a0 + a1 u + a2 v + a3 u v, so the tangents, the
    Hessian (x_uu = x_vv = 0, x_uv = a3) and the square's four constraints are closed forms.
    Why: under JAX on a GPU the generic code's small axes (nodes, coordinates, constraints)
    become reductions and transposes, about 60 kernels an iteration (1.6 ms an iteration at
    2^20 pairs on an H100, most of the quad4 detection); elementwise arrays fuse into one (83
    us an iteration; the quad4 detection 24.4 -> 11.3 ms). NumPy keeps the generic code.
    Constraints j = 0..3: u >= -1, u <= 1, v >= -1, v <= 1 (element.constraints_a), edge
    EDGE_OF[j] of each."""
    dt = xe.dtype
    eps = float(np.finfo(dt).eps)
    feasible_tol = 64 * eps
    tiny = float(np.finfo(dt).tiny)
    inf = np.inf
    A = ((1.0, 0.0), (-1.0, 0.0), (0.0, 1.0), (0.0, -1.0))  # b = -1 for every row
    EDGE_OF = (3, 1, 0, 2)
    R, X, (a0, a1, a2, a3) = _bilinear_parts(r, xe)
    dot = _vdot

    def residual_vec(u, v):  # r - x(u, v)
        return tuple(R[k] - (a0[k] + a1[k] * u + a2[k] * v + a3[k] * (u * v)) for k in range(3))

    def objective(u, v):
        d = residual_vec(u, v)
        return dot(d, d)

    def tangents(u, v):
        return (tuple(a1[k] + a3[k] * v for k in range(3)),
                tuple(a2[k] + a3[k] * u for k in range(3)))  # fmt: skip

    def derivatives(u, v):
        d = residual_vec(u, v)
        xu, xv = tangents(u, v)
        g = (-dot(xu, d), -dot(xv, d))
        gn = (dot(xu, xu), dot(xu, xv), dot(xv, xv))  # symmetric: (00, 01, 11)
        h = (gn[0], gn[1] - dot(a3, d), gn[2])
        scale = xp.maximum(gn[0] + gn[2], tiny)
        return g, h, gn, scale

    def solve(m, rhs):  # _solve2 on a symmetric (00, 01, 11)
        det = m[0] * m[2] - m[1] * m[1]
        return (_safe_div(rhs[0] * m[2] - m[1] * rhs[1], det, xp),
                _safe_div(m[0] * rhs[1] - m[1] * rhs[0], det, xp))  # fmt: skip

    def chebyshev(u, v, p, hq):
        xu, xv = tangents(u, v)
        jp = tuple(xu[k] * p[0] + xv[k] * p[1] for k in range(3))
        m0 = tuple(a3[k] * p[1] for k in range(3))  # X''(e_u, p)
        m1 = tuple(a3[k] * p[0] for k in range(3))  # X''(e_v, p)
        xpp = tuple(m0[k] * p[0] + m1[k] * p[1] for k in range(3))
        c = (2 * dot(m0, jp) + dot(xu, xpp), 2 * dot(m1, jp) + dot(xv, xpp))
        s = solve(hq, (0.5 * c[0], 0.5 * c[1]))
        return (p[0] - s[0], p[1] - s[1])

    def first_true(w):  # argmax of the flags: the first set one, 0 if none
        return xp.where(w[0], 0, xp.where(w[1], 1, xp.where(w[2], 2, xp.where(w[3], 3, 0))))

    def last_true(w):
        return xp.where(w[3], 3, xp.where(w[2], 2, xp.where(w[1], 1, xp.where(w[0], 0, 3))))

    def pick(j, vals):  # vals[j] for a per-pair index j in 0..3
        return xp.where(
            j == 0, vals[0], xp.where(j == 1, vals[1], xp.where(j == 2, vals[2], vals[3]))
        )

    def count(w):
        return (
            w[0].astype(np.int32)
            + w[1].astype(np.int32)
            + w[2].astype(np.int32)
            + w[3].astype(np.int32)
        )

    def multipliers(g, w):
        nw = count(w)
        j1, j2 = first_true(w), last_true(w)
        a1x, a1y = pick(j1, [a[0] for a in A]), pick(j1, [a[1] for a in A])
        a2x, a2y = pick(j2, [a[0] for a in A]), pick(j2, [a[1] for a in A])
        lam1 = a1x * g[0] + a1y * g[1]  # |a|^2 = 1
        det = a1x * a2y - a2x * a1y  # [a1 a2] lam = g (Cramer, as _solve2)
        b0 = _safe_div(g[0] * a2y - a2x * g[1], det, xp)
        b1 = _safe_div(a1x * g[1] - a1y * g[0], det, xp)
        l1 = xp.where(nw == 2, b0, lam1)
        l2 = xp.where(nw == 2, b1, inf)
        lam = []
        for j in range(4):
            lj = xp.where(j1 == j, l1, inf)
            lj = xp.where((j2 == j) & (nw == 2), l2, lj)
            lam.append(xp.where(w[j], lj, inf))
        return lam

    def residual(g, w, gn):
        lam = multipliers(g, w)
        pu, pv = g[0], g[1]
        for j in range(4):
            lw = xp.where(w[j], lam[j], 0)
            pu, pv = pu - lw * A[j][0], pv - lw * A[j][1]
        # (closest_point_face's stiffness: rows 0 and 1 hold u, so v is free along them)
        nw = count(w)
        trace = xp.maximum(gn[0] + gn[2], tiny)
        along = xp.where(w[0] | w[1], gn[2], gn[0])
        k = xp.where(nw == 0, _least(*gn, tiny, xp), xp.where(nw == 1, along, trace))
        scale = xp.maximum(xp.sqrt(k * trace), tiny)
        kkt = xp.sqrt(pu * pu + pv * pv) / scale
        neg = xp.minimum(xp.minimum(lam[0], lam[1]), xp.minimum(lam[2], lam[3]))
        kkt = xp.maximum(kkt, xp.where(neg < 0, -neg / trace, 0))
        return kkt, lam

    def slack(j, u, v):  # A_j . xi - b_j
        return A[j][0] * u + A[j][1] * v + 1.0

    def ratios(u, v, p, w):
        # Ratio test against the constraints outside W: the first blocking one and how far.
        alpha_j = []
        for j in range(4):
            ap = A[j][0] * p[0] + A[j][1] * p[1]
            a = xp.where((ap < 0) & ~w[j], _safe_div(-slack(j, u, v), ap, xp), inf)
            alpha_j.append(xp.maximum(a, 0))
        return _first_smallest(alpha_j, xp)

    edge_t, _ = _bilinear_edges(R, X, xp)  # (independent of the iterate: once)

    def edge_points(u, v):
        # The exact closest point of each edge (corner e to corner e + 1) as a step from xi.
        out = []
        for e, t in enumerate(edge_t):
            s, t_ = _SQUARE[e], _SQUARE[(e + 1) % 4]
            out.append((s[0] + t * (t_[0] - s[0]) - u, s[1] + t * (t_[1] - s[1]) - v))
        return out

    def better(u, v, p, q):
        use = objective(u + q[0], v + q[1]) < objective(u + p[0], v + p[1])
        return (xp.where(use, q[0], p[0]), xp.where(use, q[1], p[1]))

    def model(h, gn):  # (as closest_point_face's; symmetric (00, 01, 11))
        pd = (h[0] > 0) & (h[0] * h[2] - h[1] ** 2 > 0)
        return tuple(xp.where(pd, h[i], gn[i]) for i in range(3))

    def step(u, v, g, h, gn, w, p_edges):
        nw = count(w)
        j1 = first_true(w)
        hq = model(h, gn)
        s = solve(hq, g)
        p0 = (-s[0], -s[1])
        pc = chebyshev(u, v, p0, hq)
        inside = slack(0, u + p0[0], v + p0[1]) >= 0
        for j in (1, 2, 3):
            inside = inside & (slack(j, u + p0[0], v + p0[1]) >= 0)
        for j in range(4):  # (the correction on the face too: see closest_point_face's step)
            inside = inside & (slack(j, u + pc[0], v + pc[1]) >= 0)
        b = better(u, v, p0, pc)
        p0 = (xp.where(inside, b[0], p0[0]), xp.where(inside, b[1], p0[1]))
        e1 = pick(j1, EDGE_OF)
        p1 = (pick(e1, [p[0] for p in p_edges]), pick(e1, [p[1] for p in p_edges]))
        return tuple(
            xp.where(nw == 0, p0[i], xp.where(nw == 1, p1[i], 0 * p0[i])) for i in range(2)
        )

    def iteration(it, state):
        u, v, w, done, iters = state
        g, h, gn, scale = derivatives(u, v)
        kkt, lam = residual(g, w, gn)
        newly = (kkt <= tol) & ~done
        iters = xp.where(newly, it + 1, iters)
        done = done | newly
        jmin, lmin = _first_smallest(lam, xp)
        drop = (lmin < 0) & ~done
        w_drop = tuple(w[j] & ~((jmin == j) & drop) for j in range(4))
        p_edges = edge_points(u, v)
        p_drop = step(u, v, g, h, gn, w_drop, p_edges)
        am = (pick(jmin, [a[0] for a in A]), pick(jmin, [a[1] for a in A]))
        drop = drop & (am[0] * p_drop[0] + am[1] * p_drop[1] >= 0)
        w = tuple(xp.where(drop, w_drop[j], w[j]) for j in range(4))
        p_keep = step(u, v, g, h, gn, w, p_edges)
        p = tuple(xp.where(drop, p_drop[i], p_keep[i]) for i in range(2))
        jb, amin = ratios(u, v, p, w)
        alpha = xp.minimum(amin, 1.0)
        f0 = objective(u, v)
        f_tol = 16 * eps * (f0 + scale)
        for _ in range(4):
            grow = objective(u + alpha * p[0], v + alpha * p[1]) > f0 + f_tol
            alpha = xp.where(grow, 0.5 * alpha, alpha)
        blocked = (amin <= alpha) & ~done
        nu, nv = u + alpha * p[0], v + alpha * p[1]
        eb = pick(jb, EDGE_OF)
        nu = xp.where(blocked, u + pick(eb, [q[0] for q in p_edges]), nu)
        nv = xp.where(blocked, v + pick(eb, [q[1] for q in p_edges]), nv)
        w = tuple(
            w[j] | (blocked & (xp.abs(slack(j, nu, nv)) <= feasible_tol)) | ((jb == j) & blocked)
            for j in range(4)
        )
        return xp.where(done, u, nu), xp.where(done, v, nv), w, done, iters

    u0, v0 = xi0[..., 0], xi0[..., 1]
    w0 = tuple(xp.abs(slack(j, u0, v0)) <= feasible_tol for j in range(4))
    state = (u0, v0, w0, xp.zeros(u0.shape, bool), xp.zeros(u0.shape, np.int32))
    u, v, w, done, iters = fori(xp, iterations, iteration, state, stop=lambda s: xp.all(s[3]))
    g, h, gn, scale = derivatives(u, v)
    kkt, _ = residual(g, w, gn)
    converged = kkt <= tol
    iters = xp.where(done, iters, iterations + 1)
    # One Newton step more near the face: free, cut at the border, along an edge that blocks
    # it at once (as closest_point_face's, and why). Rows 0 and 1 hold u (along v), 2 and 3 v.
    keep = tuple(xp.zeros_like(w[j]) for j in range(4))
    active = done & (objective(u, v) <= tol * scale)
    hq = model(h, gn)
    p_free = solve(hq, g)
    for _ in range(3):  # (blocked at once by an edge: along that edge instead, twice at most)
        on_u, on_v = keep[0] | keep[1], keep[2] | keep[3]  # (u held: along v)
        p = (
            xp.where(on_u, 0, xp.where(on_v, _safe_div(-g[0], hq[0], xp), -p_free[0])),
            xp.where(on_v, 0, xp.where(on_u, _safe_div(-g[1], hq[2], xp), -p_free[1])),
        )
        jb, amin = ratios(u, v, p, keep)
        go = active & (amin > 0)
        alpha = xp.where(go, xp.minimum(amin, 1.0), 0)
        u, v = u + alpha * p[0], v + alpha * p[1]
        w = tuple(
            xp.where(
                go,
                keep[j] | ((jb == j) & (amin < 1)) | (xp.abs(slack(j, u, v)) <= feasible_tol),
                w[j],
            )
            for j in range(4)
        )
        active = active & ~go
        keep = tuple(xp.where(active, jb == j, keep[j]) for j in range(4))
    nw = count(w)
    e1, e2 = pick(first_true(w), EDGE_OF), pick(last_true(w), EDGE_OF)
    corner = xp.where((e1 + 1) % 4 == e2, e2, e1)
    feature = xp.where(nw == 0, FACE, xp.where(nw == 1, EDGE, VERTEX)).astype(np.int32)
    local = xp.where(nw == 0, -1, xp.where(nw == 1, e1, corner)).astype(np.int32)
    return xp.stack([u, v], -1), feature, local, converged, iters, kkt
