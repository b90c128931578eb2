"""Swept detection's detailed check: the earliest time a moving node lies on a moving face.

Every node moves linearly over the step, x(t) = x0 + t (x1 - x0), t in [0, 1], and so does
every face node. With (s, w) in the unit square mapped onto the face's natural coordinates
(quads: xi = 2 s - 1, eta = 2 w - 1; triangles: xi = s, eta = w, boxes past xi + eta = 1
dropped),

    F(s, w, t) = sum_a N_a(xi(s, w)) (X_a + t V_a) - (p + t v)

is zero exactly when the node lies on the face at time t (a triangle's nodes taken from its
corner whose edges are nearest orthogonal, `corner_shift`, its (s, w) mapped back after). F
is linear in t and of degree <= 1 (tri3, quad4) or <= 2 (tri6, quad8, quad9) in s and in w,
so on a box of (s, w, t) its Bernstein coefficients (the corner values for the linear faces;
a three-point rule an axis for the curved ones) are control points whose convex hull holds
F's range there, and their differences bound its Jacobian. The search is depth first over
boxes, the earlier half in time first, and for each box:

1. exclusion: the hull misses 0 along an axis or along the face normal at either end of the
   step (by more than a rounding margin): no contact in the box;
2. Krawczyk's operator K (krawczyk): every zero of F in the box lies in K, so K missing the box
   excludes it too, and K inside the box proves exactly one zero, which a few contractions
   (quadratic) enclose in a box shorter than T_TOL in time: a contact at that box's earliest
   time. Typical contacts are proven after a handful of splits, not followed down to the
   tolerance (the box count per contact fell 5-15x);
3. otherwise a box whose hull is within SPACE_RTOL of 0 and shorter than T_TOL in time is a
   contact at its earliest time (a contact on an edge or vertex of the domain, a grazing or
   degenerate one, where no box around it proves it); else the box is split along the axis its
   control points spread most along (a box stays long along a curve where F does not change),
   in time once it is tight in space.
After a contact the search keeps only boxes that start earlier.

Guarantee (certified root search, no sampling): a real contact at time t* is never missed and
toi <= t*; toi >= t' - T_TOL, where t' is the first time the node comes within the contact
tolerance delta + margin of the face (pair_frame: max(SPACE_RTOL, 4 ROUND eps) + ROUND eps
times scale, the largest coordinate of the pair, face node 0 at the start as origin; 1e-9 in
float64, 3.8e-5 in float32, where the rounding margin exceeds SPACE_RTOL), which is t* unless
the node grazes the face before touching it. The bounds are rigorous in exact arithmetic and
widened by the rounding of the computed control points (ROUND * eps * scale). A pair whose
search exceeds VISITS boxes reports the earliest box left (still never late) with status
NOT_CONVERGED.
"""

from __future__ import annotations

import numpy as np

from ._elements import EDGE, FACE, VERTEX, interpolate, shape_functions
from ._surface import _dot, _unit, face_normals

#: Time resolution, relative to the step: toi is within T_TOL before the first contact.
T_TOL = {np.dtype(np.float64): 1e-6, np.dtype(np.float32): 1e-4}
#: A box is a contact when its hull is within SPACE_RTOL * scale of 0 (and short in time).
SPACE_RTOL = {np.dtype(np.float64): 1e-9, np.dtype(np.float32): 1e-5}
#: The hull misses 0 only by more than ROUND * eps * scale (the control points' rounding).
ROUND = 64
#: Pending boxes a pair may hold (a split adds one; the depth is ~3 log2(1 / SPACE_RTOL)).
DEPTH = 128
#: Krawczyk contractions of a box proven to hold one contact (quadratic: 3-4 reach T_TOL).
CONTRACTIONS = 8
#: Boxes a pair may visit before it stops with the earliest one left.
VISITS = 8192
#: Natural coordinates this close to a constraint put the contact on an edge or vertex.
FEATURE_TOL = {np.dtype(np.float64): 1e-6, np.dtype(np.float32): 1e-3}


def capture_pads(dtype):
    """(rel, rounding): a face's capture box grows by rel times its largest side, a slave's
    segment by rel times its length, and both by rounding times the frame's largest
    coordinate, so that every pair whose search can report a contact is a candidate.

    Why that suffices: the search reports a contact only where F = face point - node is within
    delta + margin <= k sc of 0 (k = max(SPACE_RTOL, 4 ROUND eps) + ROUND eps, `pair_frame`),
    and sc, the pair's largest coordinate from face node 0, is at most W + L + k sc (W: the
    box's largest side, which holds the face at every time; L: the node's path), so the node
    passes within k (W + L) / (1 - k) < rel (W + L) of the box (rel = 4 k). The rounding term
    covers the box and segment tests' own arithmetic. A pad from the frame's extent instead
    (as before) outgrew the small faces of graded meshes: 1.8 on faces of 1 at 2^20 nodes,
    42 candidate faces a slave where 9 suffice."""
    dtype = np.dtype(dtype)
    eps = float(np.finfo(dtype).eps)
    return 4 * (max(SPACE_RTOL[dtype], 4 * ROUND * eps) + ROUND * eps), 16 * eps


def grown_boxes(lo, hi, rel, rounding, xp=np):
    """Capture boxes [F, 3] grown by `capture_pads` (rounding: already times the scale)."""
    pad = rel * xp.max(hi - lo, -1, keepdims=True) + rounding
    return lo - pad, hi + pad


def natural(element, s, w, xp=np):
    """Natural coordinates [..., 2] of the unit-square parameters (s, w)."""
    if element.kind == "tri":
        return xp.stack([s, w], -1)
    return xp.stack([2 * s - 1, 2 * w - 1], -1)


def outside(element, box):
    """Boxes [P, 6] wholly outside the element's domain (triangles: past xi + eta = 1)."""
    if element.kind == "tri":
        return box[:, 0] + box[:, 2] > 1
    return box[:, 0] > 1  # never: quads fill the square


def _bernstein(f, axis, xp):
    """Degree-2 Bernstein coefficients along `axis` (length 3) from values at its ends and
    middle: b1 = 2 f(1/2) - (f(0) + f(1)) / 2."""
    f0, fm, f1 = (xp.take(f, i, axis) for i in range(3))
    return xp.stack([f0, 2 * fm - 0.5 * (f0 + f1), f1], axis)


def control_points(element, xa, va, p, v, box, xp=np):
    """Control points [P, 2, g, g, 3] (t ends, s, w) of F over boxes [P, 6] = (s0, s1, w0, w1,
    t0, t1); xa, va [P, nn, 3] the face nodes at t = 0 and their motion, p, v [P, 3] the node's."""
    g = 2 if element.linear else 3
    f = xp.linspace(0.0, 1.0, g).astype(box.dtype)[None, :]
    s = box[:, 0:1] + (box[:, 1:2] - box[:, 0:1]) * f  # [P, g]
    w = box[:, 2:3] + (box[:, 3:4] - box[:, 2:3]) * f
    xi = natural(element, s[:, :, None] + 0 * w[:, None, :], 0 * s[:, :, None] + w[:, None, :], xp)
    n = shape_functions(element, xi.reshape(-1, g * g, 2), xp)  # [P, g*g, nn]
    a = (n @ xa).reshape(-1, g, g, 3) - p[:, None, None, :]
    b = (n @ va).reshape(-1, g, g, 3) - v[:, None, None, :]
    if g == 3:
        a = _bernstein(_bernstein(a, 1, xp), 2, xp)
        b = _bernstein(_bernstein(b, 1, xp), 2, xp)
    t = box[:, 4:6, None, None, None]
    return a[:, None] + t * b[:, None]


def examine(cp, dirs, margin, xp=np):
    """Per box: excluded (its hull misses 0 along an axis or a direction of dirs [P, k, 3] by
    more than margin), its hull's largest axis extent, and the spread of the control points
    along s, w and t (which axis to split) [P, 3]."""
    m = cp.shape[1] * cp.shape[2] * cp.shape[3]
    flat = cp.reshape(cp.shape[0], m, 3)
    lo, hi = xp.min(flat, 1), xp.max(flat, 1)
    out = xp.any((lo > margin[:, None]) | (hi < -margin[:, None]), -1)
    proj = flat @ xp.swapaxes(dirs, 1, 2)  # [P, m, k]
    plo, phi = xp.min(proj, 1), xp.max(proj, 1)
    out = out | xp.any((plo > margin[:, None]) | (phi < -margin[:, None]), -1)
    extent = xp.max(hi - lo, -1)
    ds = xp.max(xp.abs(cp[:, :, 1:] - cp[:, :, :-1]), (1, 2, 3, 4))
    dw = xp.max(xp.abs(cp[:, :, :, 1:] - cp[:, :, :, :-1]), (1, 2, 3, 4))
    dt = xp.max(xp.abs(cp[:, 1] - cp[:, 0]), (1, 2, 3))
    return out, extent, xp.stack([ds, dw, dt], -1)


def _inverse3(m, xp):
    """Inverses [P, 3, 3] of m by the adjugate (columns a, b, c: rows b x c, c x a, a x b over
    the determinant), and the determinants [P]."""
    a, b, c = m[:, :, 0], m[:, :, 1], m[:, :, 2]
    rows = xp.stack([xp.cross(b, c), xp.cross(c, a), xp.cross(a, b)], 1)
    det = _dot(a, rows[:, 0])
    ok = xp.abs(det) > 0
    return rows / xp.where(ok, det, 1)[:, None, None], det


def krawczyk(element, xa, va, p, v, box, cp, margin, xp=np):
    """The Krawczyk operator of F on boxes [P, 6] of (s, w, t): with m the box's centre, Y the
    inverse of the middle of J, the interval Jacobian over the box (from differences of the
    control points cp, whose hull bounds the derivatives' Bernstein coefficients),

        K = m - Y F(m) + (I - Y J) (X - m).

    Every zero of F in X lies in K (for any Y), so K misses X: no contact in X; K inside X's
    interior: exactly one, in K, and X & K contracts towards it (quadratically). The radius
    of K is grown by the rounding of F(m) (margin) and of the sums.

    Triangles also bound s + w of the zero, l K with l = (1, 1, 0) (the same identity with
    the row l Y): on a sliver the box keeps a wide radius in s and in w along the poorly
    determined direction, while s + w, which says which side of the diagonal the zero lies
    on, is well determined. Returns (empty: no zero in X inside the domain, inside, the box
    X & K [P, 6], within: the zero in X, if any, is inside the domain)."""
    g = cp.shape[2]
    lo, hi = box[:, 0::2], box[:, 1::2]
    r = 0.5 * (hi - lo)
    mid = 0.5 * (hi + lo)
    d_s = (g - 1) * (cp[:, :, 1:] - cp[:, :, :-1]) / (2 * r[:, 0, None, None, None, None])
    d_w = (g - 1) * (cp[:, :, :, 1:] - cp[:, :, :, :-1]) / (2 * r[:, 1, None, None, None, None])
    d_t = (cp[:, 1] - cp[:, 0]) / (2 * r[:, 2, None, None, None])
    j_lo = xp.stack([xp.min(d_s, (1, 2, 3)), xp.min(d_w, (1, 2, 3)), xp.min(d_t, (1, 2))], -1)
    j_hi = xp.stack([xp.max(d_s, (1, 2, 3)), xp.max(d_w, (1, 2, 3)), xp.max(d_t, (1, 2))], -1)
    y, det = _inverse3(0.5 * (j_lo + j_hi), xp)
    xi = natural(element, mid[:, 0], mid[:, 1], xp)
    n = shape_functions(element, xi[:, None, :], xp)  # [P, 1, nn]
    f = (n @ xa)[:, 0] - p + mid[:, 2:3] * ((n @ va)[:, 0] - v)
    eps = float(np.finfo(np.dtype(box.dtype)).eps)
    tri = element.kind == "tri"
    # Rows l of K: those of the identity, and (1, 1, 0) for triangles (its l Y: y0 + y1).
    rows, ly, lm = np.eye(3), y, mid
    if tri:
        rows = np.concatenate([rows, [[1.0, 1.0, 0.0]]])
        ly = xp.concatenate([y, y[:, :1] + y[:, 1:2]], 1)
        lm = xp.concatenate([mid, mid[:, :1] + mid[:, 1:2]], 1)
    rows = xp.asarray(rows, dtype=box.dtype)[None]
    lf = (ly @ f[:, :, None])[:, :, 0]
    c = lm - lf
    yp, yn = xp.maximum(ly, 0), xp.minimum(ly, 0)
    m_lo = rows - (yp @ j_hi + yn @ j_lo)
    m_hi = rows - (yp @ j_lo + yn @ j_hi)
    mag = xp.maximum(xp.abs(m_lo), xp.abs(m_hi))
    rad = (mag @ r[:, :, None])[:, :, 0]
    rad = rad + 4 * xp.sum(xp.abs(ly), -1) * margin[:, None]
    rad = rad + 16 * eps * (xp.abs(lm) + xp.abs(lf) + rad)
    ok = xp.all(xp.isfinite(c - rad) & xp.isfinite(c + rad), -1) & (xp.abs(det) > 0)
    k_lo, k_hi = (c - rad)[:, :3], (c + rad)[:, :3]
    empty = ok & xp.any((k_hi < lo) | (k_lo > hi), -1)
    inside = ok & xp.all((k_lo > lo) & (k_hi < hi), -1)
    new_lo = xp.where(ok[:, None], xp.maximum(lo, k_lo), lo)
    new_hi = xp.where(ok[:, None], xp.minimum(hi, k_hi), hi)
    within = xp.ones_like(ok)
    if tri:
        sw_lo, sw_hi = c[:, 3] - rad[:, 3], c[:, 3] + rad[:, 3]
        empty = empty | (ok & ((sw_lo > 1) | (new_lo[:, 0] + new_lo[:, 1] > 1)))
        within = (ok & (sw_hi <= 1)) | (new_hi[:, 0] + new_hi[:, 1] <= 1)
    return empty, inside, xp.stack([new_lo, new_hi], -1).reshape(box.shape), within


#: A triangle's node order shifted by one and by two corners (tri3; tri6 with its midsides).
SHIFTS = {
    3: np.array([[0, 1, 2], [1, 2, 0], [2, 0, 1]]),
    6: np.array([[0, 1, 2, 3, 4, 5], [1, 2, 0, 4, 5, 3], [2, 0, 1, 5, 3, 4]]),
}


def corner_shift(xe, xp=np):
    """Per triangle [P, nn, 3], the shift r (0, 1, 2) that makes corner r the origin of the
    search's (s, w): the corner whose two edges are nearest orthogonal (the least |cos|; the
    first of equals). On a sliver the near-zero set of F is a strip along the short edge;
    with the origin at the sharp corner it lies across s and w (the edges there nearly
    parallel) and boxes aligned with s and w tile it by the thousand in float32 (graded
    meshes: 700-2800 boxes a pair where the origin at a right corner needs 60-90)."""
    cos2 = []
    for i in range(3):
        a = xe[:, (i + 1) % 3] - xe[:, i]
        b = xe[:, (i + 2) % 3] - xe[:, i]
        den = _dot(a, a) * _dot(b, b)
        cos2.append(xp.where(den > 0, _dot(a, b) ** 2 / xp.where(den > 0, den, 1), 1))
    return xp.argmin(xp.stack(cos2, -1), -1)


def shifted(xe, r, xp=np):
    """The triangles' nodes [P, nn, 3] in the order that starts at corner r [P]."""
    order = xp.asarray(SHIFTS[xe.shape[1]])[r]
    return xp.take_along_axis(xe, order[:, :, None], 1)


def unshifted(where, r, xp=np):
    """(s, w) [P, 2] of the order that starts at corner r back in the face's own: the
    barycentric weights of corners r + 1 and r + 2 are s and w there."""
    s, w = where[:, 0], where[:, 1]
    u = 1 - s - w
    return xp.stack(
        [xp.where(r == 1, u, xp.where(r == 2, w, s)), xp.where(r == 1, s, xp.where(r == 2, u, w))],
        -1,
    )


def pair_frame(element, xe0, xe1, p0, p1, xp=np):
    """The pair's data in its own frame (face node 0 at t = 0 as origin): xa, va, p, v, the
    exclusion directions (the face normal at its centre at t = 0 and t = 1) [P, 2, 3], the
    rounding margin and the contact tolerance [P]."""
    o = xe0[:, :1]
    xa, va = xe0 - o, xe1 - xe0
    p, v = p0 - o[:, 0], p1 - p0
    scale = xp.maximum(
        xp.max(xp.abs(xa).reshape(len(p), -1), -1), xp.max(xp.abs(xa + va).reshape(len(p), -1), -1)
    )
    scale = xp.maximum(scale, xp.maximum(xp.max(xp.abs(p), -1), xp.max(xp.abs(p + v), -1)))
    dirs = xp.stack([face_normals(element, xa, xp), face_normals(element, xa + va, xp)], 1)
    dt = np.dtype(xe0.dtype)
    margin = ROUND * float(np.finfo(dt).eps) * scale
    delta = xp.maximum(SPACE_RTOL[dt] * scale, 4 * margin)
    return xa, va, p, v, dirs, margin, delta


def roots(element, xe0, xe1, p0, p1):
    """The certified search (module docstring) for P pairs at once, in lock step (NumPy):
    each pair keeps a stack of pending boxes. Returns toi [P] (inf: no contact), the contact
    box's centre (s, w) [P, 2], converged [P] and the boxes visited [P]."""
    dt = np.dtype(xe0.dtype)
    n = len(p0)
    tri = element.kind == "tri"
    if tri:  # (s, w) from the corner with the most nearly orthogonal edges
        r = corner_shift(xe0)
        xe0, xe1 = shifted(xe0, r), shifted(xe1, r)
    xa, va, p, v, dirs, margin, delta = pair_frame(element, xe0, xe1, p0, p1)
    t_tol = T_TOL[dt]
    stack = np.zeros((n, DEPTH, 6), dt)
    stack[:, 0] = (0, 1, 0, 1, 0, 1)
    sp = np.ones(n, np.int64)
    best = np.full(n, np.inf, dt)
    where = np.full((n, 2), np.nan, dt)
    visits = np.zeros(n, np.int64)
    converged = np.ones(n, bool)
    act = np.nonzero(sp > 0)[0]
    while len(act):
        sp[act] -= 1
        box = stack[act, sp[act]]
        visits[act] += 1
        live = box[:, 4] < best[act]
        a, box = act[live], box[live]
        cp = control_points(element, xa[a], va[a], p[a], v[a], box)
        out, extent, spread = examine(cp, dirs[a], margin[a])
        empty, inside, kbox, within = krawczyk(
            element, xa[a], va[a], p[a], v[a], box, cp, margin[a]
        )
        out = out | empty | outside(element, box)
        # One zero proven in the box: contract it (Krawczyk) to T_TOL in time, and until it
        # is known inside or outside the domain (a triangle's zero near its diagonal). One
        # still undecided after CONTRACTIONS is within K's radius of the diagonal: a contact.
        proven = ~out & inside
        if proven.any():
            k, kb, kin = a[proven], kbox[proven], within[proven]
            gone = np.zeros(len(k), bool)
            for _ in range(CONTRACTIONS):
                more = ~gone & ((kb[:, 5] - kb[:, 4] > t_tol) | ~kin)
                if not more.any():
                    break
                kc = control_points(element, xa[k], va[k], p[k], v[k], kb)
                em2, _, kb2, in2 = krawczyk(element, xa[k], va[k], p[k], v[k], kb, kc, margin[k])
                kb = np.where(more[:, None], kb2, kb)
                kin = np.where(more, in2, kin)
                gone |= more & em2
            box[proven] = kb
            out[proven] = gone
            proven &= ~out
        tw = box[:, 5] - box[:, 4]
        small = extent <= delta[a]
        leaf = ~out & ((small & (tw <= t_tol)) | proven)
        full = ~out & ~leaf & (sp[a] + 2 > DEPTH)  # no room: a contact, conservatively
        converged[a[full]] = False
        hit = leaf | full
        best[a[hit]] = box[hit, 4]
        where[a[hit]] = 0.5 * (box[hit][:, [0, 2]] + box[hit][:, [1, 3]])
        split = ~out & ~hit
        a, box, spread, small = a[split], box[split], spread[split], small[split]
        # Split the axis along which the control points spread most; a box already tight in
        # space but long in time is split in time.
        axis = np.where(small, 2, np.argmax(spread, -1))
        mid = 0.5 * (box[np.arange(len(a)), 2 * axis] + box[np.arange(len(a)), 2 * axis + 1])
        early, late = box.copy(), box.copy()
        early[np.arange(len(a)), 2 * axis + 1] = mid
        late[np.arange(len(a)), 2 * axis] = mid
        stack[a, sp[a]] = late  # the earlier half on top: popped first
        stack[a, sp[a] + 1] = early
        sp[a] += 2
        # A pair over its budget stops with the earliest pending box (never late).
        over = np.nonzero((visits > VISITS) & (sp > 0))[0]
        if len(over):
            k = np.arange(DEPTH)[None, :] < sp[over, None]
            j = np.argmin(np.where(k, stack[over, :, 4], np.inf), 1)
            b = stack[over, j]
            earlier = b[:, 4] < best[over]
            best[over[earlier]] = b[earlier, 4]
            where[over[earlier]] = 0.5 * (b[earlier][:, [0, 2]] + b[earlier][:, [1, 3]])
            converged[over] = False
            sp[over] = 0
        act = np.nonzero(sp > 0)[0]
    if tri:
        where = unshifted(where, r)
    return best, where, converged, visits


def feature_of(element, xi, tol, xp=np):
    """FACE, EDGE or VERTEX from the constraints of the domain active at xi (within tol)."""
    a = xp.asarray(element.constraints_a, xi.dtype)
    b = xp.asarray(element.constraints_b, xi.dtype)
    act = xp.abs(xi @ a.T - b[None, :]) <= tol
    k = xp.sum(act.astype(np.int32), -1)
    return xp.where(k == 0, FACE, xp.where(k == 1, EDGE, VERTEX)).astype(np.int32)


def impact(element, xe0, xe1, p0, p1, toi, xi, xp=np):
    """At the contact: the node's position, the face's unit normal there and then, and the
    normal velocity of the node relative to the face (negative: approaching its front)."""
    t = toi[:, None]
    point = p0 + t * (p1 - p0)
    _, dx = interpolate(element, xe0 + toi[:, None, None] * (xe1 - xe0), xi, xp)
    normal = _unit(xp.cross(dx[..., 0], dx[..., 1]), xp)
    n = shape_functions(element, xi, xp)
    vface = (n[:, None, :] @ (xe1 - xe0))[:, 0]
    return point, normal, _dot(normal, (p1 - p0) - vface)


def select(slave, face, toi, n, t_tol):
    """Per slave, the chosen pair (index, -1 when none hits): the smallest face id among the
    pairs whose toi is within t_tol of the slave's earliest (NumPy); and that earliest toi."""
    first = np.full(n, np.inf, toi.dtype)
    np.minimum.at(first, slave, toi)
    band = np.isfinite(toi) & (toi <= first[slave] + t_tol)
    low = np.full(n, np.iinfo(np.int64).max)
    np.minimum.at(low, slave[band], face[band])
    pick = np.full(n, -1, np.int64)
    k = np.nonzero(band & (face == low[slave]))[0]
    pick[slave[k]] = k
    return pick, first
