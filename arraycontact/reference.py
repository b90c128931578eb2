"""Brute-force closest points: the oracle every test trusts.

`closest_points(points, surface)` checks every point against every face in float64, over face
interiors, edges and vertices (seed 003, eq. 7), with methods chosen to be obviously right and
independent of the detection pipeline:

- face interiors: linear triangles by projection onto the plane (kept if inside); other elements
  by unconstrained Newton from a lattice of interior starts, kept where it converged inside;
- edges: every edge is a polynomial curve of degree <= 2 in its parameter, so the stationary
  points of the squared distance are the roots of a cubic, found as companion-matrix
  eigenvalues, plus each end;
- vertices: every corner.

The smallest of all these candidate distances is the distance to the surface. Work is pruned
only by rigorous bounds: a face can hold the closest point only if the lower bound
|r - c| - radius of its ball is below the distance to the nearest corner (a point on the
surface). Points and faces are processed in chunks, so memory stays bounded.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ._elements import EDGE, FACE, VERTEX, interpolate, shape_functions, shape_second_derivatives
from ._normals import pseudo_normal, signed_gap
from ._surface import Surface, validate_points

#: Two faces whose distances differ by at most TIE_RTOL * longest edge are a tie; the tie goes to
#: the smaller face id (the rule of every back end).
TIE_RTOL = 1e-10
#: Self-contact: a face faces a node when n_i . n_f < -FACING_TOL (unit normals; perpendicular
#: ones, a dot product of rounding noise, do not).
FACING_TOL = 1e-6


@dataclass(frozen=True)
class ReferenceResult:
    face: np.ndarray
    xi: np.ndarray
    point: np.ndarray
    distance: np.ndarray
    gap: np.ndarray
    normal: np.ndarray
    feature: np.ndarray
    local: np.ndarray  # local edge or corner id of the feature on `face` (-1 for a face interior)


def _edge_candidates(element, r, xe):
    """Candidate (t, edge) minimisers on every edge: [P, n_edges, 6] parameters in [0, 1]."""
    out = []
    for a, b, *_ in element.edge_nodes:
        xa, xb = element.nodes[a], element.nodes[b]
        ts = np.array([0.0, 0.5, 1.0])
        n = shape_functions(element, xa + ts[:, None] * (xb - xa))  # [3, nn]
        x0, xm, x1 = np.einsum("tn,pnk->tpk", n, xe)
        # x(t) = p0 + p1 t + p2 t^2 through the three samples; d/dt |x - r|^2 / 2 is a cubic.
        p0, p1, p2 = x0 - r, -3 * x0 + 4 * xm - x1, 2 * x0 - 4 * xm + 2 * x1
        c3 = 2 * np.sum(p2 * p2, -1)
        c2 = 3 * np.sum(p1 * p2, -1)
        c1 = np.sum(p1 * p1, -1) + 2 * np.sum(p0 * p2, -1)
        c0 = np.sum(p0 * p1, -1)
        t_lin = np.divide(-c0, c1, out=np.zeros_like(c0), where=c1 > 0)
        cand = [np.zeros_like(c0), np.ones_like(c0), t_lin]
        curved = c3 > 1e-20 * np.maximum(c1, 1e-300)
        roots = np.full((len(r), 3), 0.5)
        if curved.any():
            comp = np.zeros((curved.sum(), 3, 3))
            comp[:, 0, :] = -np.stack([c2, c1, c0], -1)[curved] / c3[curved, None]
            comp[:, 1, 0] = comp[:, 2, 1] = 1.0
            ev = np.linalg.eigvals(comp)
            roots[curved] = np.where(np.abs(ev.imag) < 1e-7 * (1 + np.abs(ev.real)), ev.real, 0.5)
        cand += [roots[:, 0], roots[:, 1], roots[:, 2]]
        t = np.clip(np.stack(cand, -1), 0.0, 1.0)
        out.append(xa + t[..., None] * (xb - xa))  # natural coordinates [P, 6, 2]
    return np.concatenate(out, 1)


def _interior_candidates(element, r, xe):
    """Interior stationary points of |x(xi) - r|^2 reached by Newton from a lattice of starts."""
    if element.name == "tri3":
        a, b, c = xe[:, 0], xe[:, 1], xe[:, 2]
        m = np.stack([b - a, c - a], -1)  # [P, 3, 2]
        mtm = np.einsum("pka,pkb->pab", m, m)
        rhs = np.einsum("pka,pk->pa", m, r - a)
        det = np.linalg.det(mtm)
        ok = det > 1e-14 * np.einsum("paa->p", mtm) ** 2
        xi = np.zeros((len(r), 2))
        xi[ok] = np.linalg.solve(mtm[ok], rhs[ok][..., None])[..., 0]
        inside = ok & (xi[:, 0] >= 0) & (xi[:, 1] >= 0) & (xi.sum(1) <= 1)
        return xi[:, None], inside[:, None]
    if element.linear:  # a bilinear quad: mildly curved, a 3 x 3 lattice is plenty
        s = np.array([-0.7, 0.0, 0.7])
    elif element.kind == "tri":  # down to 0.02 from the edges, where minima hide too
        s = np.array([0.02, 0.15, 0.3, 0.45, 0.6, 0.75, 0.96])
    else:
        s = np.array([-0.98, -0.66, -0.33, 0.0, 0.33, 0.66, 0.98])
    starts = np.stack(np.meshgrid(s, s, indexing="ij"), -1).reshape(-1, 2)
    if element.kind == "tri":
        starts = starts[starts.sum(1) <= 0.98]
    # The starts of all points in one flat list [P * S]: the descent goes on with the starts
    # that still move (a start whose step left it where it was stays there: the same
    # arithmetic again).
    xi = np.tile(starts, (len(r), 1))
    pair = np.repeat(np.arange(len(r)), len(starts))  # each start's (point, face) pair

    def f(xi, rows):  # |x(xi) - r|^2, x = sum_n N_n x_n as a matmul (einsum's loops are slow here)
        x = (shape_functions(element, xi)[:, None, :] @ xe[pair[rows]])[:, 0, :]
        return np.sum((x - r[pair[rows]]) ** 2, -1)

    # Descent: Newton where the Hessian is positive definite, Gauss-Newton elsewhere, each step
    # halved until the distance does not grow; so iterates go to local minima, not saddles.
    live = np.arange(len(xi))
    for _ in range(30):
        at, xe_, r_ = xi[live], xe[pair[live]], r[pair[live]]
        x, dx = interpolate(element, xe_, at)
        d = r_ - x
        g = -np.einsum("...ka,...k->...a", dx, d)
        d2 = np.swapaxes(xe_, -1, -2) @ shape_second_derivatives(element, at)  # [..., 3, 3]
        c = np.einsum("...ks,...k->...s", d2, d)
        gn = np.einsum("...ka,...kb->...ab", dx, dx)
        h = gn - np.stack(
            [np.stack([c[..., 0], c[..., 1]], -1), np.stack([c[..., 1], c[..., 2]], -1)], -2
        )
        pd = (h[..., 0, 0] > 0) & (h[..., 0, 0] * h[..., 1, 1] - h[..., 0, 1] ** 2 > 0)
        h = np.where(pd[..., None, None], h, gn)
        det = h[..., 0, 0] * h[..., 1, 1] - h[..., 0, 1] * h[..., 1, 0]
        det = np.where(np.abs(det) > 1e-300, det, 1e-300)
        step = (
            np.stack(
                [
                    h[..., 1, 1] * g[..., 0] - h[..., 0, 1] * g[..., 1],
                    h[..., 0, 0] * g[..., 1] - h[..., 1, 0] * g[..., 0],
                ],
                -1,
            )
            / det[..., None]
        )
        # The halvings evaluated only where the distance still grows (a step accepted stays
        # accepted).
        f0, alpha = np.sum(d**2, -1), np.ones(len(live))
        todo = np.arange(len(live))
        for _ in range(10):
            trial = at[todo] - alpha[todo, None] * step[todo]
            todo = todo[f(trial, live[todo]) > f0[todo] * (1 + 1e-14)]
            alpha[todo] /= 2
        new = np.clip(at - alpha[:, None] * step, -10.0, 10.0)  # keep runaways finite
        xi[live] = new
        live = live[(new != at).any(1)]
        if len(live) == 0:
            break
    xi = xi.reshape(len(r), len(starts), 2)
    rr, xx = r[:, None], np.broadcast_to(xe[:, None], (len(r), len(starts)) + xe.shape[1:])
    x, dx = interpolate(element, xx, xi)
    g = -np.einsum("...ka,...k->...a", dx, rr - x)
    scale = np.einsum("...kaa->...", dx[..., None] * dx[..., None, :])
    conv = np.linalg.norm(g, axis=-1) <= 1e-12 * np.maximum(scale, 1e-300) * (
        1 + np.linalg.norm(rr - x, axis=-1) / np.sqrt(np.maximum(scale, 1e-300))
    )
    a, b = element.constraints_a, element.constraints_b
    inside = conv & (xi @ a.T - b >= -1e-12).all(-1)
    return xi, inside


def _closest_on_faces(element, r, xe):
    """Closest point of r [P, 3] on faces xe [P, nn, 3]: xi, distance^2."""
    # Work relative to each face's first node (exact in float64 for nearby values), so that the
    # oracle keeps its precision far from the origin.
    x0 = xe[:, :1]
    r, xe = r - x0[:, 0], xe - x0
    xi_e = _edge_candidates(element, r, xe)
    xi_i, ok_i = _interior_candidates(element, r, xe)
    xi = np.concatenate([xi_e, xi_i], 1)
    valid = np.concatenate([np.ones(xi_e.shape[:2], bool), ok_i], 1)
    n = shape_functions(element, xi)
    x = np.einsum("pcn,pnk->pck", n, xe)
    d2 = np.where(valid, np.sum((x - r[:, None]) ** 2, -1), np.inf)
    best = np.argmin(d2, 1)
    ar = np.arange(len(r))
    return xi[ar, best], d2[ar, best]


def _feature_of(element, xi, tol=1e-9):
    """Feature and local id from the constraints active at xi."""
    act = np.abs(xi @ element.constraints_a.T - element.constraints_b) <= tol
    nact = act.sum(1)
    ce = element.constraint_edge
    feature = np.where(nact == 0, FACE, np.where(nact == 1, EDGE, VERTEX)).astype(np.int32)
    local = np.full(len(xi), -1, np.int32)
    one = nact == 1
    local[one] = ce[np.argmax(act[one], 1)]
    corners = element.corners
    many = nact >= 2
    if many.any():
        dc = np.linalg.norm(xi[many, None] - corners[None], axis=-1)
        local[many] = np.argmin(dc, 1)
    return feature, local


def closest_points(points, surface: Surface, *, chunk_points=1024, chunk_faces=8192):
    """Closest point on `surface` of every point in `points` [n, 3], by brute force in float64.

    Work is done in blocks of chunk_points x chunk_faces (about 200 MB of temporaries at the
    defaults, whatever the sizes: 2^16 points x 2^17 faces runs in the same memory)."""
    if not isinstance(surface, Surface):
        raise ValueError("surface must be an arraycontact.Surface")
    r_all = validate_points(points, "points")
    e = surface.element
    nf = surface.n_faces
    n = len(r_all)
    face = np.full(n, -1, np.int64)
    xi = np.full((n, 2), np.nan)
    dist2 = np.full(n, np.inf)
    if nf == 0 or n == 0:
        return _finish(surface, r_all, face, xi, dist2)
    centres, radii = surface.face_bounds
    corner_ids = np.unique(surface.faces[:, : e.n_corners])
    corner_x = surface.points[corner_ids]
    tie = TIE_RTOL * surface.longest_edge
    for p0 in range(0, n, chunk_points):
        r = r_all[p0 : p0 + chunk_points]
        # Upper bound: the nearest corner is a point of the surface.
        ub = np.full(len(r), np.inf)
        for q0 in range(0, len(corner_x), chunk_faces):
            d = np.linalg.norm(r[:, None] - corner_x[None, q0 : q0 + chunk_faces], axis=-1)
            ub = np.minimum(ub, d.min(1))
        cand = []
        for f0 in range(0, nf, chunk_faces):
            f1 = min(f0 + chunk_faces, nf)
            lb = np.linalg.norm(r[:, None] - centres[None, f0:f1], axis=-1) - radii[None, f0:f1]
            pi, fi = np.nonzero(lb <= ub[:, None] * (1 + 1e-9) + tie)
            if len(pi):
                xq, dq = _closest_on_faces(e, r[pi], surface.points[surface.faces[fi + f0]])
                cand.append((pi, fi + f0, xq, np.sqrt(dq)))
        pi, fi, xq, dq = (np.concatenate(c) for c in zip(*cand))
        k = _tie_rule(len(r), pi, fi, dq, tie)  # every point has a candidate (ub)
        at = p0 + pi[k]
        face[at], xi[at], dist2[at] = fi[k], xq[k], dq[k] ** 2
    return _finish(surface, r_all, face, xi, dist2)


def _tie_rule(n, pi, fi, dq, tie):
    """The chosen candidate of each point that has one (indices into pi): the smallest face
    id among the faces within `tie` of the smallest distance."""
    dmin = np.full(n, np.inf)
    np.minimum.at(dmin, pi, dq)
    best_f = np.full(n, np.iinfo(np.int64).max)
    near = dq <= dmin[pi] + tie
    np.minimum.at(best_f, pi[near], fi[near])
    return np.nonzero(near & (fi == best_f[pi]))[0]


def closest_points_self(
    surface: Surface, *, d_max=None, rows=None, chunk_points=512, chunk_faces=4096
):
    """Self-contact by brute force in float64: for every node used by the faces (in
    `surface.nodes` order), the closest admissible face, the rule of `detect_self`: a face is
    admissible when it does not hold the node and its unit normal x_xi x x_eta at its own
    closest point to the node faces the node's pseudo-normal (n_i . n_f < -FACING_TOL). Ties: the
    smallest face id within TIE_RTOL * longest edge. d_max: faces farther (by their balls) are
    not examined (None: every face). Nodes with no admissible face within reach get face -1.
    rows: only these rows of `surface.nodes` (a subset to check a large surface against).

    Every (node, face) pair whose ball is within d_max is projected with the same
    independent methods as `closest_points`; the admissibility test is applied per pair."""
    if not isinstance(surface, Surface):
        raise ValueError("surface must be an arraycontact.Surface")
    e = surface.element
    ids = surface.nodes if rows is None else surface.nodes[np.asarray(rows)]
    r_all = surface.points[ids]
    n = len(ids)
    face = np.full(n, -1, np.int64)
    xi = np.full((n, 2), np.nan)
    dist2 = np.full(n, np.inf)
    if n == 0:
        return _finish(surface, r_all, face, xi, dist2)
    centres, radii = surface.face_bounds
    normals = surface.node_normals[ids]
    tie = TIE_RTOL * surface.longest_edge
    reach = np.inf if d_max is None else float(d_max) * (1 + 1e-9) + tie
    nf = surface.n_faces
    for p0 in range(0, n, chunk_points):
        r = r_all[p0 : p0 + chunk_points]
        cand = []
        for f0 in range(0, nf, chunk_faces):
            f1 = min(f0 + chunk_faces, nf)
            lb = np.linalg.norm(r[:, None] - centres[None, f0:f1], axis=-1) - radii[None, f0:f1]
            holds = (surface.faces[None, f0:f1] == ids[p0 : p0 + len(r), None, None]).any(-1)
            pi, fi = np.nonzero((lb <= reach) & ~holds)
            if len(pi):
                xe = surface.points[surface.faces[fi + f0]]
                xq, dq = _closest_on_faces(e, r[pi], xe)
                _, dx = interpolate(e, xe, xq)
                nq = np.cross(dx[..., 0], dx[..., 1])
                nq /= np.maximum(np.linalg.norm(nq, axis=-1, keepdims=True), 1e-300)
                ok = np.einsum("pk,pk->p", normals[p0 + pi], nq) < -FACING_TOL
                cand.append((pi[ok], fi[ok] + f0, xq[ok], np.sqrt(dq[ok])))
        if not cand:
            continue
        pi, fi, xq, dq = (np.concatenate(c) for c in zip(*cand))
        if not len(pi):
            continue
        k = _tie_rule(len(r), pi, fi, dq, tie)
        at = p0 + pi[k]
        face[at], xi[at], dist2[at] = fi[k], xq[k], dq[k] ** 2
    return _finish(surface, r_all, face, xi, dist2)


def _finish(surface, r, face, xi, dist2):
    e = surface.element
    n = len(r)
    point = np.full((n, 3), np.nan)
    gap = np.full(n, np.nan)
    normal = np.full((n, 3), np.nan)
    feature = np.full(n, -1, np.int32)
    local = np.full(n, -1, np.int32)
    ok = face >= 0
    if ok.any():
        f = face[ok]
        x, _ = interpolate(e, surface.points[surface.faces[f]], xi[ok])
        point[ok] = x
        feature[ok], local[ok] = _feature_of(e, xi[ok])
        npse = pseudo_normal(
            e,
            surface.points,
            surface.faces,
            surface.face_edges,
            surface.edge_faces,
            surface.node_normals,
            f,
            feature[ok],
            local[ok],
            xi[ok],
        )
        gap[ok], _, normal[ok] = signed_gap(
            r[ok] - x, npse, feature[ok], on_surface=TIE_RTOL * surface.longest_edge
        )
    return ReferenceResult(
        face=face,
        xi=xi,
        point=point,
        distance=np.sqrt(dist2),
        gap=gap,
        normal=normal,
        feature=feature,
        local=local,
    )


@dataclass(frozen=True)
class SweptReference:
    hit: np.ndarray  # [n] bool
    toi: np.ndarray  # [n] earliest contact time in [0, 1] (inf: none)
    face: np.ndarray  # [n] the face of that contact (-1: none)
    xi: np.ndarray  # [n, 2] natural coordinates of the contact on it
    pair_toi: dict  # {(slave row, face): toi} for every pair in contact (ties, checks)


#: The oracle's time resolution: its toi is within SWEPT_TOL before the exact one.
SWEPT_TOL = 1e-9


def _det(a, b, c):
    return np.einsum("pk,pk->p", a, np.cross(b, c))


def _tri3_cubic(xe0, xe1, p0, p1):
    """Coefficients c0..c3 of det[e1(t), e2(t), r(t)] (e1, e2 the edges from vertex 0, r the
    node from vertex 0), which vanishes when the node and the triangle are coplanar: the
    determinant is linear in each column, so each power of t is a sum of determinants."""
    a = [xe0[:, 1] - xe0[:, 0], xe0[:, 2] - xe0[:, 0], p0 - xe0[:, 0]]
    e1 = xe1 - xe0
    b = [e1[:, 1] - e1[:, 0], e1[:, 2] - e1[:, 0], (p1 - p0) - e1[:, 0]]
    c = np.zeros((len(p0), 4))
    for mask in range(8):  # column j from b when bit j is set
        cols = [b[j] if mask >> j & 1 else a[j] for j in range(3)]
        c[:, bin(mask).count("1")] += _det(*cols)
    return c


def _cubic_roots_01(c):
    """All roots in [0, 1] of the cubics c0 + c1 t + c2 t^2 + c3 t^3 [P, 4], as [P, 7] (NaN
    padded): each monotone piece between the derivative's roots is bisected to the last bit
    where its ends differ in sign, and a piece's end where the cubic is (to rounding) zero
    counts too (a double root, where the node touches the plane without crossing it)."""
    P = len(c)
    d = np.stack([c[:, 1], 2 * c[:, 2], 3 * c[:, 3]], -1)  # derivative's coefficients
    disc = d[:, 1] ** 2 - 4 * d[:, 2] * d[:, 0]
    with np.errstate(all="ignore"):
        sq = np.sqrt(np.maximum(disc, 0))
        q1 = np.where(d[:, 2] != 0, (-d[:, 1] - sq) / (2 * d[:, 2]), np.nan)
        q2 = np.where(d[:, 2] != 0, (-d[:, 1] + sq) / (2 * d[:, 2]), np.nan)
        lin = np.where((d[:, 2] == 0) & (d[:, 1] != 0), -d[:, 0] / d[:, 1], np.nan)
    crit = np.stack([q1, q2, lin], -1)
    crit = np.where((disc[:, None] >= 0) | (d[:, 2:3] == 0), crit, np.nan)
    crit = np.where((crit > 0) & (crit < 1), crit, np.nan)
    knots = np.sort(np.concatenate([np.zeros((P, 1)), crit, np.ones((P, 1))], 1), 1)  # NaN last

    def f(t):
        return ((c[:, 3:4] * t + c[:, 2:3]) * t + c[:, 1:2]) * t + c[:, 0:1]

    lo, hi = knots[:, :-1], knots[:, 1:]
    flo, fhi = f(lo), f(hi)
    ok = np.isfinite(lo) & np.isfinite(hi) & (np.sign(flo) * np.sign(fhi) < 0)
    a, b = np.where(ok, lo, 0.0), np.where(ok, hi, 0.0)
    fa = f(a)
    for _ in range(64):
        m = 0.5 * (a + b)
        fm = f(m)
        left = np.sign(fm) == np.sign(fa)
        a, fa = np.where(left, m, a), np.where(left, fm, fa)
        b = np.where(left, b, m)
    crossing = np.where(ok, a, np.nan)  # the earlier end: never after the root
    scale = np.abs(c).sum(1, keepdims=True)
    flat = np.isfinite(knots) & (np.abs(f(np.nan_to_num(knots))) <= 1e-13 * scale)
    touching = np.where(flat, knots, np.nan)
    return np.concatenate([crossing, touching], 1)


def _tri3_swept(xe0, xe1, p0, p1):
    """toi and xi of each tri3 pair by the coplanarity cubic and the in-face test at its roots;
    pairs whose cubic vanishes identically (coplanar motion) are returned as undecided."""
    c = _tri3_cubic(xe0, xe1, p0, p1)
    L = max(np.abs(np.r_[xe0.ravel(), xe1.ravel(), p0.ravel(), p1.ravel()]).max(), 1e-300)
    flat = np.abs(c).max(1) <= 1e-13 * L**3
    ts = _cubic_roots_01(c)
    toi = np.full(len(c), np.inf)
    xi = np.full((len(c), 2), np.nan)
    for k in np.argsort(np.nan_to_num(ts, nan=np.inf), 1).T:  # roots in time order
        t = ts[np.arange(len(c)), k]
        todo = np.isfinite(t) & ~np.isfinite(toi) & ~flat
        if not todo.any():
            continue
        tt = t[todo, None]
        x = xe0[todo] + tt[:, :, None] * (xe1[todo] - xe0[todo])
        r = p0[todo] + tt * (p1[todo] - p0[todo]) - x[:, 0]
        e1, e2 = x[:, 1] - x[:, 0], x[:, 2] - x[:, 0]
        g = np.stack(
            [
                np.stack([np.einsum("pk,pk->p", e1, e1), np.einsum("pk,pk->p", e1, e2)], -1),
                np.stack([np.einsum("pk,pk->p", e1, e2), np.einsum("pk,pk->p", e2, e2)], -1),
            ],
            -2,
        )
        rhs = np.stack([np.einsum("pk,pk->p", e1, r), np.einsum("pk,pk->p", e2, r)], -1)
        with np.errstate(all="ignore"):
            uv = np.linalg.solve(g + 1e-300 * np.eye(2), rhs[..., None])[..., 0]
        tol = 1e-9
        inside = (uv[:, 0] >= -tol) & (uv[:, 1] >= -tol) & (uv.sum(1) <= 1 + tol)
        inside &= np.isfinite(uv).all(1)
        rows = np.nonzero(todo)[0][inside]
        toi[rows] = t[rows]
        xi[rows] = uv[inside]
    return toi, xi, flat


def _interval_mul(a0, a1, b0, b1):
    p = np.stack([a0 * b0, a0 * b1, a1 * b0, a1 * b1])
    return p.min(0), p.max(0)


def _power(u0, u1, k):
    if k == 0:
        return np.ones_like(u0), np.ones_like(u1)
    if k == 1:
        return u0, u1
    sq = np.stack([u0 * u0, u1 * u1])
    return np.where((u0 < 0) & (u1 > 0), 0.0, sq.min(0)), sq.max(0)


def _subdivision_swept(element, xe0, xe1, p0, p1):
    """toi and xi of each pair by interval subdivision of (xi, eta, t) over the natural domain:
    F = sum_m m(xi, eta) (C_m + t D_m) in the monomial basis of the element, bounded on a box
    by interval arithmetic (a method apart from the pipeline's Bernstein hulls); a box whose
    interval misses 0 is dropped, the others split at their widest side (relative to the
    domain), earlier time first, depth first, until every side is below SWEPT_TOL: a contact
    at the box's earliest time, after which only earlier boxes are searched. All pairs advance
    in lock step, one pending-box stack each."""
    P = len(p0)
    coef = element.coefficients  # N_a = sum_m coef[a, m] m
    C = np.einsum("am,pak->pmk", coef, xe0)
    D = np.einsum("am,pak->pmk", coef, xe1 - xe0)
    C[:, 0] -= p0  # the constant monomial comes first in every element
    D[:, 0] -= p1 - p0
    L = np.abs(np.r_[xe0.ravel(), xe1.ravel(), p0.ravel(), p1.ravel()]).max(initial=1e-300)
    margin = 1e-13 * L
    lo_dom = 0.0 if element.kind == "tri" else -1.0
    width = np.array([1.0 - lo_dom, 1.0 - lo_dom, 1.0])
    depth = 3 * int(np.ceil(np.log2(1 / SWEPT_TOL))) + 2
    stack = np.zeros((P, depth, 6))
    stack[:, 0] = (lo_dom, 1.0, lo_dom, 1.0, 0.0, 1.0)
    sp = np.ones(P, np.int64)
    toi = np.full(P, np.inf)
    xi = np.full((P, 2), np.nan)
    visits = np.zeros(P, np.int64)
    act = np.arange(P)
    while len(act):
        sp[act] -= 1
        box = stack[act, sp[act]]
        keep = box[:, 4] < toi[act]
        if element.kind == "tri":
            keep &= box[:, 0] + box[:, 2] <= 1
        a, box = act[keep], box[keep]
        u0, u1, v0, v1, t0, t1 = box.T
        f0 = np.zeros((len(a), 3))
        f1 = np.zeros((len(a), 3))
        for m, (i, j) in enumerate(element.monomials):
            ma, mb = _interval_mul(*_power(u0, u1, i), *_power(v0, v1, j))
            c0 = C[a, m] + t0[:, None] * D[a, m]
            c1 = C[a, m] + t1[:, None] * D[a, m]
            lo, hi = _interval_mul(ma[:, None], mb[:, None], np.minimum(c0, c1), np.maximum(c0, c1))
            f0, f1 = f0 + lo, f1 + hi
        out = ((f0 > margin) | (f1 < -margin)).any(1)
        w = (box[:, 1::2] - box[:, 0::2]) / width
        leaf = ~out & (w.max(1) <= SWEPT_TOL)
        toi[a[leaf]] = box[leaf, 4]
        xi[a[leaf]] = 0.5 * (box[leaf][:, [0, 2]] + box[leaf][:, [1, 3]])
        split = ~out & ~leaf
        a, box, w = a[split], box[split], w[split]
        d = 2 - np.argmax(w[:, ::-1], 1)  # the widest side, ties to time
        r = np.arange(len(a))
        mid = 0.5 * (box[r, 2 * d] + box[r, 2 * d + 1])
        early, late = box.copy(), box.copy()
        early[r, 2 * d + 1] = mid
        late[r, 2 * d] = mid
        stack[a, sp[a]] = late
        stack[a, sp[a] + 1] = early
        sp[a] += 2
        visits[act] += 1
        if visits.max(initial=0) > 10**6:
            # Faces of zero area meet a node along a curve of (xi, eta): not for this oracle.
            raise RuntimeError("reference.swept: a pair needs more than 10^6 boxes")
        act = np.nonzero(sp > 0)[0]
    return _polish(element, xe0, xe1, p0, p1, toi, xi)


def _polish(element, xe0, xe1, p0, p1, toi, xi):
    """Newton on F(xi, eta, t) = 0 from each contact box (sides below SWEPT_TOL): the exact
    root where it converges within 1e-7 of the box, else the box's earliest time (a box left
    by the interval bounds lies within a few of its sides of the root)."""
    k = np.nonzero(np.isfinite(toi))[0]
    if not len(k):
        return toi, xi
    a0, a1, b0, b1 = xe0[k], xe1[k], p0[k], p1[k]
    z = np.concatenate([xi[k], toi[k, None]], 1)
    start = z.copy()
    L = np.abs(np.r_[xe0.ravel(), xe1.ravel(), p0.ravel(), p1.ravel()]).max()
    for _ in range(8):
        t = z[:, 2:3]
        x, dx = interpolate(element, a0 + t[:, :, None] * (a1 - a0), z[:, :2])
        n = shape_functions(element, z[:, :2])
        vf = np.einsum("pa,pak->pk", n, a1 - a0)
        f = x - (b0 + t * (b1 - b0))
        jac = np.concatenate([dx, (vf - (b1 - b0))[..., None]], -1)
        with np.errstate(all="ignore"):  # pinv: a node moving in the face's plane is singular
            step = (np.linalg.pinv(jac) @ f[..., None])[..., 0]
        z = np.where(np.isfinite(step).all(1, keepdims=True), z - step, z)
    t = z[:, 2:3]
    x, _ = interpolate(element, a0 + t[:, :, None] * (a1 - a0), z[:, :2])
    res = np.linalg.norm(x - (b0 + t * (b1 - b0)), axis=1)
    ok = (res <= 1e-12 * L) & (np.abs(z - start).max(1) <= 1e-7)
    toi, xi = toi.copy(), xi.copy()
    toi[k[ok]], xi[k[ok]] = z[ok, 2], z[ok, :2]
    return toi, xi


def swept(slave_x0, slave_x1, master: Surface, master_x1):
    """Swept detection by brute force in float64: for every slave node moving from slave_x0 to
    slave_x1 [n, 3] (linearly in t over [0, 1]) and the master surface moving from its points
    to master_x1, the earliest t at which the node lies on a face, and that face.

    Pairs whose boxes over the step do not meet are skipped (a rigorous bound); the others are
    solved exactly: tri3 faces by the coplanarity cubic (node and triangle coplanar), its real
    roots in [0, 1] bracketed between the derivative's roots and bisected to the last bit, then
    the in-face test at each root in time order; every other element, and tri3 pairs moving in
    a common plane (the cubic vanishes), by interval subdivision (_subdivision_swept) and a
    Newton polish of its root. The returned toi is the exact root to rounding (the cubic's
    bracket's earlier end; Newton's root), or where Newton does not settle within 1e-7 of the
    subdivision's contact box, that box's earliest time: never after the root, and before it
    by the interval bounds' slack over the node's speed across the face (a few SWEPT_TOL; a
    crossing at a shallow angle more: up to 2e-6 of the step was seen, bilinear quads, where
    an answer within tolerance of the root is then after the reference's). Ties: the smallest
    face id among the faces whose toi is within `tie` (the caller's) of the earliest."""
    if not isinstance(master, Surface):
        raise ValueError("master must be an arraycontact.Surface")
    x0, x1 = validate_points(slave_x0, "slave_x0"), validate_points(slave_x1, "slave_x1")
    m1 = validate_points(master_x1, "master_x1")
    e = master.element
    faces = master.faces
    xe0, xe1 = master.points[faces], m1[faces]
    flo = np.minimum(xe0.min(1), xe1.min(1))
    fhi = np.maximum(xe0.max(1), xe1.max(1))
    if not e.linear:  # a curved face bulges past its nodes by at most its Lebesgue constant
        c = 0.5 * (flo + fhi)
        flo, fhi = c - e.lebesgue * (c - flo), c + e.lebesgue * (fhi - c)
    slo, shi = np.minimum(x0, x1), np.maximum(x0, x1)
    pad = 1e-9 * max(np.abs(np.r_[x0.ravel(), x1.ravel(), xe0.ravel(), xe1.ravel()]).max(), 1e-300)
    chunk = max(1, (1 << 22) // max(len(flo), 1))  # (slaves x faces) blocks of 4M pairs
    blocks = [
        np.nonzero(
            (
                (slo[i : i + chunk, None] <= fhi[None] + pad)
                & (shi[i : i + chunk, None] >= flo[None] - pad)
            ).all(-1)
        )
        for i in range(0, len(x0), chunk)
    ]
    pi = np.concatenate([b[0] + i * chunk for i, b in enumerate(blocks)] + [np.zeros(0, int)])
    fi = np.concatenate([b[1] for b in blocks] + [np.zeros(0, int)])
    toi = np.full(len(pi), np.inf)
    xi = np.full((len(pi), 2), np.nan)
    if e.name == "tri3":
        toi, xi, flat = _tri3_swept(xe0[fi], xe1[fi], x0[pi], x1[pi])
    else:
        flat = np.ones(len(pi), bool)
    if flat.any():
        k = np.nonzero(flat)[0]
        toi[k], xi[k] = _subdivision_swept(e, xe0[fi[k]], xe1[fi[k]], x0[pi[k]], x1[pi[k]])
    n = len(x0)
    hit_pairs = np.isfinite(toi)
    best = np.full(n, np.inf)
    np.minimum.at(best, pi[hit_pairs], toi[hit_pairs])
    face = np.full(n, -1, np.int64)
    out_xi = np.full((n, 2), np.nan)
    # The earliest, and among equal earliest times the smallest face id.
    order = np.lexsort((fi, toi, pi))
    first = order[np.r_[True, pi[order][1:] != pi[order][:-1]]] if len(order) else order
    first = first[hit_pairs[first]]
    face[pi[first]], out_xi[pi[first]] = fi[first], xi[first]
    pair_toi = {
        (int(a), int(b)): float(t) for a, b, t in zip(pi[hit_pairs], fi[hit_pairs], toi[hit_pairs])
    }
    return SweptReference(hit=np.isfinite(best), toi=best, face=face, xi=out_xi, pair_toi=pair_toi)
