"""Stage 4: candidate faces of every slave and the closest point on each, all pairs at once.

Candidates (exact mode): each face is held by a box (Surface.face_boxes, rigorous for curved
faces), so a face can hold a point within rho of slave s only if its box is within rho. Here
rho = min(distance to the closest node, d_max) plus rounding slack: the closest node is a point
of the surface, so no face farther than it can hold the closest point, and none farther than
d_max can make the slave active; the face tree (_grid) shrinks it further to the nearest
surface point it meets. The closest face need not contain the closest node (seed 003 Fig. 2a):
every face passing the box test is projected.

Projections: tri3 in closed form (Voronoi regions); every other element by the active-set
Newton method of seed 003 eq. (8) from start option I, with a fixed iteration budget and a
convergence flag.
"""

from __future__ import annotations

import numpy as np

from . import _grid
from ._elements import shape_functions
from ._geometry import (
    bilinear_best_of_starts,
    closest_point_edges,
    closest_point_face,
    closest_point_triangle,
    curved_convex,
    start_option_one,
    start_option_two,
    surely_convex,
    triangle_distance,
)
from ._xp import compact, einsum, is_numpy, lead, norm


def candidate_faces(xp, tree, slave_x, rho, *, slack, capacity, normal=None):
    """Candidate (slave, face) pairs, the faces whose box is within rho of the slave (shrunk
    by the tree to the nearest surface point it meets; self-contact, `normal` given: those
    that may face the slave's normal): (slave [P], face [P], valid [P], pair counts per tree
    level)."""
    slave, pos, valid, counts = _grid.query(
        xp, tree, slave_x, rho, slack, capacity, "face_level", normal
    )
    if valid.shape[0] == 0:  # (NumPy, no pair at all) one invalid pair keeps the shapes
        slave, pos, valid = xp.zeros(1, np.int32), xp.zeros(1, np.int32), xp.zeros(1, bool)
    return slave, tree.ids[pos], valid, counts


def _pair_frame(slave_x, nodes_x, faces, slave, face):
    """Each pair in a frame at its face's first node: (that node, the slave, the face's nodes).
    Nearby float32 values subtract exactly, so distances keep full precision relative to the
    element size however far the scene is."""
    xe = nodes_x[faces[face]]
    x0 = xe[:, 0]
    return x0, slave_x[slave] - x0, xe - x0[:, None]


def project(xp, element, slave_x, nodes_x, faces, slave, face, *, iterations, tol):
    """Closest point of slave_x[slave] on faces[face]: xi, point, slave - point, feature,
    local, converged."""
    x0, r, xe = _pair_frame(slave_x, nodes_x, faces, slave, face)
    if element.name == "tri3":
        xi, feature, local = closest_point_triangle(r, xe[:, 0], xe[:, 1], xe[:, 2], xp)
        converged = xp.ones(r.shape[0], dtype=bool)
    else:
        xi, feature, local, converged = _best_of_starts(xp, element, r, xe, iterations, tol)
    point = einsum(xp, "pn,pnk->pk", shape_functions(element, xi, xp), xe)
    diff = r - point  # slave minus closest point, exact of the frame's offset
    return xi, point + x0, diff, feature, local, converged


def project_kept(xp, element, slave_x, nodes_x, faces, slave, face, keep, size, **kw):
    """`project` of the pairs where `keep`, gathered first (the other pairs' outputs are zeros,
    or any pair's own projection). JAX: `size` static rows at a time, as many times as the
    kept pairs need (once where they fit): one traced copy of the projection."""
    n = slave.shape[0]
    if is_numpy(xp):
        idx = np.nonzero(keep)[0]
        idx = idx if len(idx) else np.zeros(min(n, 1), np.intp)  # (one pair keeps shapes)
        out = project(xp, element, slave_x, nodes_x, faces, slave[idx], face[idx], **kw)
        full = [np.zeros((n,) + o.shape[1:], o.dtype) for o in out]
        for a, o in zip(full, out):
            a[idx] = o
        return tuple(full)
    import jax

    chunks = -(-n // size)
    idx, count = compact(xp, keep, chunks * size)  # (padding rows: pair 0, its own answer)

    def part(c):
        rows = jax.lax.dynamic_slice_in_dim(idx, c * size, size)
        return rows, project(xp, element, slave_x, nodes_x, faces, slave[rows], face[rows], **kw)

    shapes = jax.eval_shape(lambda: part(0)[1])
    full = tuple(xp.zeros((n,) + o.shape[1:], o.dtype) for o in shapes)

    def body(state):
        c, full = state
        rows, out = part(c)
        return c + 1, tuple(a.at[rows].set(o) for a, o in zip(full, out))

    return jax.lax.while_loop(lambda st: st[0] * size < count, body, (0, full))[1]


def distance_bounds(xp, element, slave_x, nodes_x, faces, slave, face):
    """Lower and upper bounds of each pair's distance without iterations, in the face's frame
    as `project`. quad4: the distance to its triangles (0, 1, 2) and (0, 2, 3), give or take
    |x0 - x1 + x2 - x3| / 4 (the bilinear face minus that piecewise linear one at the same
    (u, v) in [0, 1]^2 is -v (1 - u) (x0 - x1 + x2 - x3) on the first triangle, likewise on
    the second, and v (1 - u) <= 1/4 there: the two surfaces lie within that distance of each
    other). Other faces: their ball (`Surface.face_bounds`) below, their nearest node (a
    point of the face) above."""
    _, r, xe = _pair_frame(slave_x, nodes_x, faces, slave, face)
    if element.name == "quad4":
        # One array a coordinate (triangle_distance): the [P, 3] layout's axes of 3 cost a
        # JAX kernel each (0.9 ms at 2^20 pairs on an H100).
        R = tuple(r[:, k] for k in range(3))
        X = [tuple(xe[:, i, k] for k in range(3)) for i in (1, 2, 3)]
        d = xp.minimum(triangle_distance(R, X[0], X[1], xp), triangle_distance(R, X[1], X[2], xp))
        t = [X[1][k] - X[0][k] - X[2][k] for k in range(3)]
        twist = 0.25 * xp.sqrt(t[0] * t[0] + t[1] * t[1] + t[2] * t[2])
        return d - twist, d + twist
    c = xp.mean(xe, 1)
    radius = element.lebesgue * xp.max(norm(xp, xe - c[:, None]), -1)
    return norm(xp, r - c) - radius, xp.min(norm(xp, r[:, None] - xe), -1)


def _best_of_starts(xp, element, r, xe, iterations, tol):
    """Active-set Newton from start option I and, on curved faces, also from the centre
    (option II) and each mid-edge node and the lattice start, on bilinear faces (quad4) from
    the lattice start; the closest result wins (the first on a tie), unless the exact minimum
    over the edges (`_edges`) is at most as far.

    The distance to a curved face can have several local minima; these starts sit in the
    basins that matter for points within an element size of the face (see
    benchmarks/seed003_study.py for how often one start alone is not enough); they count only
    where `curved_convex` does not prove the distance strictly convex over the face. A warped
    bilinear quad can have two (tests/test_self_contact.py's crumpled quad4 sheet): its
    lattice start counts only where `surely_convex` does not prove one minimum (the Warp
    kernels skip it there, and every back end gives the same answer)."""
    if element.name == "quad4" and not is_numpy(xp):  # (the same steps, fused)
        return bilinear_best_of_starts(r, xe, iterations=iterations, tol=tol, xp=xp)
    kw = dict(iterations=iterations, tol=tol)
    first = start_option_one(element, r, xe, xp)

    def one():
        return closest_point_face(element, r, xe, first, xp=xp, **kw)[:4]

    if not element.linear:
        # The other starts only where one is not proven enough (as Warp).
        convex = curved_convex(element, r, xe, xp)

        def more(r, xe, first, proven):  # every start, where not proven
            k = element.n_corners
            starts = [first, start_option_two(element, r, xe, xp)]
            starts += [
                xp.zeros_like(first) + lead(xp, xp.asarray(element.nodes[i], xe.dtype), r.ndim)
                for i in range(k, 2 * k)
            ]
            starts.append(_lattice_start(xp, element, r, xe))
            return _closest_start(xp, element, r, xe, starts, ~proven, **kw)

        # Where start I's active set did not converge (a stall on an edge did so on a convex
        # pair until the Newton correction had to stay on the face; any iteration limit may)
        # every start runs, and the edges' exact pass, as unproven (Warp).
        if is_numpy(xp):  # (the other starts' Newton runs on the rows that need them)
            res = one()
            proven = convex & res[3]
            rows = np.flatnonzero(~proven)
            if len(rows):
                sub = more(r[rows], xe[rows], first[rows], proven[rows])
                for v, w in zip(res, _edges(xp, element, r[rows], xe[rows], *sub)):
                    v[rows] = w
            return res
        import jax  # (both branches run under vmap)

        res = one()
        proven = convex & res[3]

        def rest():
            res = more(r, xe, first, proven)
            return tuple(
                xp.where(proven[:, None] if v.ndim == 2 else proven, v, w)
                for v, w in zip(res, _edges(xp, element, r, xe, *res))
            )

        return jax.lax.cond(xp.all(proven), lambda: res, rest)
    convex = surely_convex(element, r, xe, xp)

    def two():
        # The lattice start only where one start is not proven enough (as Warp).
        starts = [first, _lattice_start(xp, element, r, xe)]
        return _closest_start(xp, element, r, xe, starts, ~convex, **kw)

    if is_numpy(xp):
        res = one() if convex.all() else two()
    else:  # (both branches run under vmap)
        import jax

        res = jax.lax.cond(xp.all(convex), one, two)
    return _edges(xp, element, r, xe, *res)


def _closest_start(xp, element, r, xe, starts, more=None, **kw):
    """closest_point_face's first four outputs from the closest of `starts` (the first on a
    tie; the starts after the first only where `more`, when given)."""
    # All starts as one batch: one traced iteration loop on JAX, not one per start.
    n_s, n_p = len(starts), r.shape[0]
    rs = xp.reshape(xp.broadcast_to(r, (n_s,) + r.shape), (-1, 3))
    xes = xp.reshape(xp.broadcast_to(xe, (n_s,) + xe.shape), (-1,) + xe.shape[1:])
    res = closest_point_face(element, rs, xes, xp.concatenate(starts), xp=xp, **kw)
    x = einsum(xp, "pn,pnk->pk", shape_functions(element, res[0], xp), xes)
    d = xp.reshape(xp.sum((x - rs) ** 2, -1), (n_s, n_p))
    if more is not None:
        d = xp.concatenate([d[:1], xp.where(more, d[1:], xp.inf)])
    best = xp.argmin(d, axis=0) * n_p + xp.arange(n_p)
    return tuple(v[best] for v in res[:4])


def _lattice_start(xp, element, r, xe, n=5):
    """The closest of an n x n lattice of interior points (n (n + 1) / 2 on triangles): a start
    in the basin of an interior minimum that the node starts miss on a strongly distorted
    face. Only distances are evaluated: cheap beside a Newton run."""
    s = np.linspace(0.1, 0.8, n) if element.kind == "tri" else np.linspace(-0.8, 0.8, n)
    g = np.stack(np.meshgrid(s, s, indexing="ij"), -1).reshape(-1, 2)
    if element.kind == "tri":
        g = g[g.sum(1) <= 0.9 + 1e-9]
    x = einsum(xp, "cn,pnk->pck", xp.asarray(shape_functions(element, g), xe.dtype), xe)
    best = xp.argmin(xp.sum((x - r[:, None]) ** 2, -1), -1)
    return xp.asarray(g, xe.dtype)[best]


def _edges(xp, element, r, xe, xi, feature, local, converged):
    """The closest point over each face's edges, solved exactly (closest_point_edges), replaces
    Newton's answer when at most as far. On a curved or distorted face the global minimum can
    lie on an edge no start's Newton path reaches; on a degenerate quad4 (a collapsed edge,
    coincident nodes) Newton can stop at a stationary corner of the parametrisation. The
    edges cannot be missed either way."""
    x = einsum(xp, "pn,pnk->pk", shape_functions(element, xi, xp), xe)
    e_xi, e_f, e_loc, e_d = closest_point_edges(element, r, xe, xp)
    use = e_d <= xp.sum((r - x) ** 2, -1)
    return (
        xp.where(use[:, None], e_xi, xi),
        xp.where(use, e_f, feature),
        xp.where(use, e_loc, local),
        converged | use,
    )
