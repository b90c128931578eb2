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


def select_closest(xp, n, slave, face, valid, dist, tie):
    """Per slave: the index of the chosen pair (clamped to 0 where none) and whether one exists."""
    d = xp.where(valid, dist, np.inf)
    dmin = segment_min(xp, d, slave, n)
    near = valid & (d <= dmin[slave] + tie)
    best_face = segment_min(xp, xp.where(near, face, BIG), slave, n)
    k = xp.arange(slave.shape[0], dtype=np.int32)
    pick = segment_min(xp, xp.where(near & (face == best_face[slave]), k, BIG), slave, n)
    has = dmin < np.inf
    return xp.where(has, pick, 0), has


def proximal(xp, slave_x, node, nodes_x, prev_node, next_node, prev_normal, next_normal,
             concave):
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


def boundary_frames(surface):
    """Per node: boundary neighbours m2 (before) and m1 (after), normals n2, n1 of the faces
    owning those boundary edges, whether the node is on the boundary and whether its corner
    is concave (eq. 12 fails). Quadratic boundary edges are split at their mid node."""
    n = len(surface.points)
    prev_node = np.arange(n)
    next_node = np.arange(n)
    prev_normal = np.zeros((n, 3))
    next_normal = np.zeros((n, 3))
    on = np.zeros(n, bool)
    be = surface.boundary_edges
    if len(be):
        fe_face, _ = np.nonzero(surface.edge_counts[surface.face_edges] == 1)
        normals = surface.face_normals[fe_face]
        segs = [(be[:, 0], be[:, 1])] if be.shape[1] == 2 else [(be[:, 0], be[:, 2]),
                                                                   (be[:, 2], be[:, 1])]
        for a, b in segs:
            next_node[a], next_normal[a] = b, normals
            prev_node[b], prev_normal[b] = a, normals
            on[a] = on[b] = True
    x = surface.points
    turn = np.cross(x - x[prev_node], x[next_node] - x)
    concave = np.einsum("ij,ij->i", turn, prev_normal + next_normal) < 0
    return prev_node, next_node, prev_normal, next_normal, on, concave


def classify(xp, element, nodes_x, faces, face_edges, edge_faces, node_normals, face, xi,
             diff, feature, local):
    """Signed gap, distance and normal of the chosen closest points."""
    n_pseudo = pseudo_normal(element, nodes_x, faces, face_edges, edge_faces, node_normals,
                             face, feature, local, xi, xp)
    return signed_gap(diff, n_pseudo, feature, xp)

