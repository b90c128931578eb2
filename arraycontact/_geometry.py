"""Point-to-face geometry, written once against an array namespace `xp` (NumPy or jax.numpy).

Every function takes batched arrays (a leading batch of point-face pairs) and returns batched
results; nothing branches on data, so the same code runs eagerly, under `jax.jit` and `vmap`.
Each closest-point routine returns natural coordinates `xi`, the feature the point lies on
(FACE / EDGE / VERTEX) and `local`, the local edge or corner id of that feature (-1 for FACE).
"""

from __future__ import annotations

import numpy as np

from ._elements import EDGE, FACE, VERTEX, interpolate, shape_functions, shape_second_derivatives
from ._xp import fori


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
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    zero = 0 * d1
    one = zero + 1
    den = va + vb + vc
    # (condition, v, w, feature, local) from the last region to the first: later assignments win.
    regions = [
        (den > 0, _safe_div(vb, den, xp), _safe_div(vc, den, xp), FACE, -1),
        ((va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0),
         1 - _safe_div(d4 - d3, (d4 - d3) + (d5 - d6), xp),
         _safe_div(d4 - d3, (d4 - d3) + (d5 - d6), xp), EDGE, 1),
        ((vb <= 0) & (d2 >= 0) & (d6 <= 0), zero, _safe_div(d2, d2 - d6, xp), EDGE, 2),
        ((d6 >= 0) & (d5 <= d6), zero, one, VERTEX, 2),
        ((vc <= 0) & (d1 >= 0) & (d3 <= 0), _safe_div(d1, d1 - d3, xp), zero, EDGE, 0),
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
    return xp.stack([v, w], -1), feature, local


def _solve2(m, r, xp):
    """Solve the 2x2 systems m [..., 2, 2] x = r [..., 2] by Cramer's rule (0 where singular)."""
    det = m[..., 0, 0] * m[..., 1, 1] - m[..., 0, 1] * m[..., 1, 0]
    x0 = r[..., 0] * m[..., 1, 1] - m[..., 0, 1] * r[..., 1]
    x1 = m[..., 0, 0] * r[..., 1] - m[..., 1, 0] * r[..., 0]
    return xp.stack([_safe_div(x0, det, xp), _safe_div(x1, det, xp)], -1)


def start_option_one(element, r, xe, xp=np):
    """Seed 003 start (I): the closest of the corners and the centre, in natural coordinates."""
    cand = np.concatenate([element.corners, element.centre[None]], 0)  # [k+1, 2]
    n = xp.asarray(shape_functions(element, cand), dtype=xe.dtype)  # [k+1, nn]
    x = xp.einsum("cn,...nk->...ck", n, xe)
    d = xp.sum((x - r[..., None, :]) ** 2, -1)
    best = xp.argmin(d, axis=-1)
    return xp.asarray(cand, dtype=xe.dtype)[best]


def start_option_two(element, r, xe, xp=np):
    """Seed 003 start (II): the centre of the element."""
    return xp.zeros(r.shape[:-1] + (2,), dtype=xe.dtype) + xp.asarray(element.centre, xe.dtype)


def closest_point_face(element, r, xe, xi0, *, iterations, tol, xp=np, method="active_set",
                       hessian="exact"):
    """Closest point on faces with nodes xe [P, nn, 3] to points r [P, 3]: seed 003 eq. (8).

    Two methods on the element's linear constraints A xi >= b, both with the exact Hessian of
    eqs. (11)-(13) (Gauss-Newton where that is not positive definite) and a fixed number of
    iterations (static shapes):

    - "active_set": a primal active-set method. Each iteration drops the working-set
      constraint with the most negative multiplier, takes a Newton step in the null space of
      the remaining working set, halves it while the distance grows, and stops at the first
      constraint it meets (ratio test).
    - "sqp": sequential quadratic programming. Each iteration solves the quadratic model
      exactly on the element's domain (in 2-D the QP's solution is the best feasible one of:
      the free minimiser, the minimiser on each constraint line, each corner), then halves
      the step while the distance grows; iterates stay feasible.

    Returns xi, feature, local, converged (KKT residual <= tol), iterations used (the first
    iteration after which the KKT conditions held) and the final KKT residual (in natural
    coordinates: the projected gradient scaled by 1/|J|^2)."""
    A = xp.asarray(element.constraints_a, dtype=xe.dtype)  # [m, 2]
    b = xp.asarray(element.constraints_b, dtype=xe.dtype)
    m = A.shape[0]
    ce = element.constraint_edge
    feasible_tol = 64 * xp.finfo(xe.dtype).eps

    def objective(xi):
        # xi [..., 2] or [..., c, 2] (several candidates per face)
        n = shape_functions(element, xi, xp)
        if xi.ndim == r.ndim + 1:
            x = xp.einsum("...cn,...nk->...ck", n, xe)
            return xp.sum((r[..., None, :] - x) ** 2, -1)
        x = xp.einsum("...n,...nk->...k", n, xe)
        return xp.sum((r - x) ** 2, -1)

    def derivatives(xi):
        x, dx = interpolate(element, xe, xi, xp)
        d = r - x
        g = -xp.einsum("...ka,...k->...a", dx, d)
        gn = xp.einsum("...ka,...kb->...ab", dx, dx)
        if element.linear and element.kind == "tri":
            h = gn
        else:
            d2 = xp.einsum("...ns,...nk->...ks", shape_second_derivatives(element, xi, xp), xe)
            c = xp.einsum("...ks,...k->...s", d2, d)
            h = gn - xp.stack([xp.stack([c[..., 0], c[..., 1]], -1),
                               xp.stack([c[..., 1], c[..., 2]], -1)], -2)
        if hessian != "exact":
            h = gn
        scale = xp.maximum(gn[..., 0, 0] + gn[..., 1, 1], xp.finfo(xe.dtype).tiny)
        return g, h, gn, scale

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
        ar = xp.arange(m)
        lam = xp.where(ar == j1[..., None], l1[..., None], np.inf)
        lam = xp.where((ar == j2[..., None]) & (nw[..., None] == 2), l2[..., None], lam)
        return xp.where(w, lam, np.inf)

    def step(g, h, gn, w):
        # Newton on the working set's null space, with the exact curvature where it is
        # positive and Gauss-Newton's (always positive on a non-degenerate face) where not.
        nw = xp.sum(w, -1)
        j1 = xp.argmax(w, -1)
        a1 = A[j1]
        t = xp.stack([-a1[..., 1], a1[..., 0]], -1)  # tangent of the active constraint
        pd = (h[..., 0, 0] > 0) & (h[..., 0, 0] * h[..., 1, 1] - h[..., 0, 1] ** 2 > 0)
        p0 = -_solve2(xp.where(pd[..., None, None], h, gn), g, xp)
        tht = xp.einsum("...a,...ab,...b->...", t, h, t)
        tgt = xp.einsum("...a,...ab,...b->...", t, gn, t)
        p1 = -_safe_div(_dot(t, g, xp), xp.where(tht > 0, tht, tgt), xp)[..., None] * t
        return xp.where((nw == 0)[..., None], p0, xp.where((nw == 1)[..., None], p1, 0 * p0))

    def residual(g, w, scale):
        lam = multipliers(g, w)
        lam_w = xp.where(w, lam, 0)
        proj = g - xp.einsum("...j,ja->...a", lam_w, A)
        kkt = xp.sqrt(xp.sum(proj**2, -1)) / scale
        neg = xp.min(xp.where(w, lam, np.inf), -1)
        kkt = xp.maximum(kkt, xp.where(neg < 0, -neg / scale, 0))
        return kkt, lam

    def iteration(it, state):
        xi, w, done, iters = state
        g, h, gn, scale = derivatives(xi)
        kkt, lam = residual(g, w, scale)
        newly = (kkt <= tol) & ~done
        iters = xp.where(newly, it + 1, iters)
        done = done | newly
        # Drop the working constraint with the most negative multiplier, unless the step on the
        # smaller working set would lead straight back through it (then keep it, move along).
        jmin = xp.argmin(lam, -1)
        drop = (xp.min(lam, -1) < 0) & ~done
        w_drop = w & ~((xp.arange(m) == jmin[..., None]) & drop[..., None])
        p_drop = step(g, h, gn, w_drop)
        drop = drop & (_dot(A[jmin], p_drop, xp) >= 0)
        w = xp.where(drop[..., None], w_drop, w)
        p = xp.where(drop[..., None], p_drop, step(g, h, gn, w))
        # Ratio test against the constraints outside the working set.
        ap = p @ A.T
        slack = xi @ A.T - b
        alpha_j = xp.where((ap < 0) & ~w, _safe_div(-slack, ap, xp), np.inf)
        alpha_j = xp.maximum(alpha_j, 0)
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
        # Put a point that hit a constraint exactly on it, and add that constraint to W.
        aj, bj = A[jb], b[jb]
        corr = _safe_div(bj - _dot(aj, new, xp), _dot(aj, aj, xp), xp)[..., None] * aj
        new = xp.where(blocked[..., None], new + corr, new)
        w = w | ((xp.arange(m) == jb[..., None]) & blocked[..., None])
        return xp.where(done[..., None], xi, new), w, done, iters

    corners = xp.asarray(element.corners, dtype=xe.dtype)

    def sqp_iteration(it, state):
        xi, w, done, iters = state
        g, h, gn, scale = derivatives(xi)
        w = xp.abs(xi @ A.T - b) <= feasible_tol
        kkt, _ = residual(g, w, scale)
        newly = (kkt <= tol) & ~done
        iters = xp.where(newly, it + 1, iters)
        done = done | newly
        pd = (h[..., 0, 0] > 0) & (h[..., 0, 0] * h[..., 1, 1] - h[..., 0, 1] ** 2 > 0)
        hq = xp.where(pd[..., None, None], h, gn)
        cands = [-_solve2(hq, g, xp)]
        for j in range(m):
            a = A[j]
            t = xp.stack([-a[1], a[0]])
            q0 = xi + ((b[j] - xi @ a) / (a @ a))[..., None] * a
            # The edge on this constraint line runs between two corners: s in [lo, hi].
            e0, e1 = element.edge_nodes[element.constraint_edge[j], :2]
            sa = (corners[e0] - q0) @ t / (t @ t)
            sb = (corners[e1] - q0) @ t / (t @ t)
            lo, hi = xp.minimum(sa, sb), xp.maximum(sa, sb)
            # The closest point on the (curved) edge: Newton on the true distance along the
            # line, from the quadratic model's minimiser, kept on the edge. Edges are
            # polynomials of degree <= 2, so a few steps reach it from anywhere near.
            tht = xp.einsum("a,...ab,b->...", t, h, t)
            curv = xp.where(tht > 0, tht, xp.einsum("a,...ab,b->...", t, hq, t))
            s_ = -_safe_div(_dot(t, g + xp.einsum("...ab,...b->...a", hq, q0 - xi), xp),
                            curv, xp)
            s_ = xp.clip(s_, lo, hi)
            for _ in range(3):
                q = q0 + s_[..., None] * t
                x, dx = interpolate(element, xe, q, xp)
                d = x - r
                xt = xp.einsum("...ka,a->...k", dx, t)
                d2 = xp.einsum("...ns,...nk->...ks", shape_second_derivatives(element, q, xp), xe)
                xtt = (d2[..., 0] * t[0] * t[0] + 2 * d2[..., 1] * t[0] * t[1]
                       + d2[..., 2] * t[1] * t[1])
                f1 = _dot(d, xt, xp)
                f2 = _dot(xt, xt, xp) + _dot(d, xtt, xp)
                f2 = xp.where(f2 > 0, f2, _dot(xt, xt, xp))
                s_ = xp.clip(s_ - _safe_div(f1, f2, xp), lo, hi)
            cands.append(q0 + s_[..., None] * t - xi)
        cands += [corners[c] - xi for c in range(element.n_corners)]
        p_all = xp.stack(cands, -2)  # [..., n_cand, 2]
        feas = ((xi[..., None, :] + p_all) @ A.T - b >= -feasible_tol).all(-1)
        # Choose by the true distance: the edge candidates are exact, the model is not.
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

    w0 = xp.abs(xi0 @ A.T - b) <= feasible_tol
    done0 = xp.zeros(xi0.shape[:-1], dtype=bool)
    iters0 = xp.zeros(xi0.shape[:-1], dtype=xp.int32)
    body = sqp_iteration if method == "sqp" else iteration
    xi, w, done, iters = fori(xp, iterations, body, (xi0, w0, done0, iters0))
    if method == "sqp":
        w = xp.abs(xi @ A.T - b) <= feasible_tol
    g, _, _, scale = derivatives(xi)
    kkt, _ = residual(g, w, scale)
    converged = kkt <= tol
    iters = xp.where(done, iters, iterations + 1)
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
    return xi, feature, local, converged, iters, kkt
