"""Stage 5: the closest candidate per slave, its feature, signed gap and normal; node-mode rules.

Tie rule (every back end): among the candidates whose distance is within `tie` (a fixed
fraction of the longest master edge) of the smallest, the smallest face id wins; among those
pairs, the first. It depends neither on the back end nor on the order of the work.
"""

from __future__ import annotations

import numpy as np

from ._normals import pseudo_normal, signed_gap
from ._xp import segment_min

BIG = np.iinfo(np.int32).max


def select_closest(xp, n, slave, face, valid, dist, tie, slots=None):
    """Per slave: the index of the chosen pair (clamped to 0 where none) and whether one exists.
    slots: the pairs are `slots` a slave in slave order (the JAX search's layout), reduced
    column by column (JAX's segment reductions are scatters: 3 of them took 0.56 ms at 2^20
    on an H100, 3.3 ms on a graded mesh of 36 slots a slave; XLA's row reductions over
    [n, 12] took 0.63 ms)."""
    if slots is not None:
        d = xp.where(valid, dist, np.inf)
        dmin = segment_min(xp, d, slave, n, slots=slots)
        near = (d.reshape(n, slots) <= dmin[:, None] + tie).reshape(-1)  # (empty: infinite)
        best_face = segment_min(xp, xp.where(near, face, BIG), slave, n, slots=slots)
        near, f = near.reshape(n, slots), face.reshape(n, slots)
        first = xp.zeros(n, np.int32)
        for j in reversed(range(slots)):
            first = xp.where(near[:, j] & (f[:, j] == best_face), j, first)
        has = dmin < np.inf
        pick = xp.arange(n, dtype=np.int32) * slots + first
        return xp.where(has, pick, 0), has
    d = xp.where(valid, dist, np.inf)
    dmin = segment_min(xp, d, slave, n)
    near = valid & (d <= dmin[slave] + tie)
    best_face = segment_min(xp, xp.where(near, face, BIG), slave, n)
    k = xp.arange(slave.shape[0], dtype=np.int32)
    pick = segment_min(xp, xp.where(near & (face == best_face[slave]), k, BIG), slave, n)
    has = dmin < np.inf
    return xp.where(has, pick, 0), has


def proximal(xp, slave_x, node, nodes_x, prev_node, next_node, prev_normal, next_normal, concave):
    """Seed 000 eq. (13): is the slave in the proximal volume of boundary node `node`?

    m2 -> m -> m1 follow the boundary in the faces' orientation; n2, n1 are the normals of the
    faces owning edges (m2, m) and (m, m1). A convex corner (eq. 12) needs both half-spaces
    (AND), a concave one either (OR)."""
    rm = nodes_x[node]
    rm1, rm2 = nodes_x[next_node[node]], nodes_x[prev_node[node]]
    n1, n2 = next_normal[node], prev_normal[node]
    rs = slave_x - rm
    a = xp.sum(xp.cross(n2, rm - rm2) * rs, -1) >= 0
    b = xp.sum(xp.cross(n1, rm1 - rm) * rs, -1) >= 0
    return xp.where(concave[node], a | b, a & b)


def boundary_topology(surface):
    """Per node: boundary neighbours m2 (before) and m1 (after), the faces owning the boundary
    edges (m2, m) and (m, m1) (-1 off the boundary) and whether the node is on the boundary.
    Quadratic boundary edges are split at their mid node."""
    n = len(surface.points)
    prev_node, next_node = np.arange(n), np.arange(n)
    prev_face, next_face = np.full(n, -1), np.full(n, -1)
    on = np.zeros(n, bool)
    be = surface.boundary_edges
    if len(be):
        fe_face, _ = np.nonzero(surface.edge_counts[surface.face_edges] == 1)
        segs = (
            [(be[:, 0], be[:, 1])]
            if be.shape[1] == 2
            else [(be[:, 0], be[:, 2]), (be[:, 2], be[:, 1])]
        )
        for a, b in segs:
            next_node[a], next_face[a] = b, fe_face
            prev_node[b], prev_face[b] = a, fe_face
            on[a] = on[b] = True
    return prev_node, next_node, prev_face, next_face, on


def boundary_geometry(xp, nodes_x, prev_node, next_node, prev_face, next_face, face_normals):
    """Normals n2, n1 of the faces owning each node's boundary edges and whether the corner is
    concave (eq. 12 fails), from the current coordinates."""
    prev_normal = xp.where((prev_face >= 0)[:, None], face_normals[xp.maximum(prev_face, 0)], 0)
    next_normal = xp.where((next_face >= 0)[:, None], face_normals[xp.maximum(next_face, 0)], 0)
    turn = xp.cross(nodes_x - nodes_x[prev_node], nodes_x[next_node] - nodes_x)
    concave = xp.sum(turn * (prev_normal + next_normal), -1) < 0
    return prev_normal, next_normal, concave


def boundary_frames(surface):
    """boundary_topology and boundary_geometry of a Surface: m2, m1, n2, n1, on, concave."""
    prev_node, next_node, prev_face, next_face, on = boundary_topology(surface)
    prev_n, next_n, concave = boundary_geometry(
        np, surface.points, prev_node, next_node, prev_face, next_face, surface.face_normals
    )
    return prev_node, next_node, prev_n, next_n, on, concave


def classify(
    xp,
    element,
    nodes_x,
    faces,
    face_edges,
    edge_faces,
    node_normals,
    face,
    xi,
    diff,
    feature,
    local,
    on_surface,
):
    """Signed gap, distance and normal of the chosen closest points."""
    n_pseudo = pseudo_normal(
        element, nodes_x, faces, face_edges, edge_faces, node_normals, face, feature, local, xi, xp
    )
    return signed_gap(diff, n_pseudo, feature, xp, on_surface)
