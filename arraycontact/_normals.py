"""Normals and signed gaps of closest points, per feature (face interior, edge, vertex).

The sign of the gap is decided by the pseudo-normal of the feature the closest point lies on:
the face normal inside a face, the sum of the normals of the faces sharing an edge on an edge,
and the angle-weighted node normal at a vertex. For a closed, outward-oriented master this is
the inside/outside test of a signed distance (Baerentzen & Aanaes 2005), and it does not depend
on which of several equidistant faces was chosen. Written once for NumPy and jax.numpy.
"""

from __future__ import annotations

import numpy as np

from ._elements import EDGE, FACE, VERTEX, interpolate
from ._surface import _unit


def face_normal(element, xe, xi, xp=np):
    """Unit normal x_xi x x_eta of faces with nodes xe [P, nn, 3] at xi [P, 2]."""
    _, dx = interpolate(element, xe, xi, xp)
    return _unit(xp.cross(dx[..., 0], dx[..., 1]), xp)


def pseudo_normal(
    element, points, faces, face_edges, edge_faces, node_normals, face, feature, local, xi, xp=np
):
    """Unit pseudo-normal of the feature each closest point lies on ([P, 3]). node_normals:
    the nodes' pseudo-normals [n_points, 3], or a function giving them for node ids [P]."""
    f = xp.maximum(face, 0)
    n_face = face_normal(element, points[faces[f]], xi, xp)

    # Edge: map the point into each face sharing the edge through the edge parameter t, which
    # is linear in the natural coordinates for every element (straight edges in xi space).
    en = xp.asarray(element.edge_nodes[:, :2])
    loc = xp.maximum(local, 0) % element.n_corners
    ca, cb = en[loc, 0], en[loc, 1]
    corners = xp.asarray(element.corners, dtype=xi.dtype)
    xa, xb = corners[ca], corners[cb]
    t = xp.sum((xi - xa) * (xb - xa), -1) / xp.sum((xb - xa) ** 2, -1)
    node_a = xp.take_along_axis(faces[f], ca[:, None], 1)[:, 0]
    node_b = xp.take_along_axis(faces[f], cb[:, None], 1)[:, 0]
    e = xp.take_along_axis(face_edges[f], loc[:, None], 1)[:, 0]
    n_edge = 0 * n_face
    for side in range(2):
        g = edge_faces[e, side]
        has = g >= 0
        gc = faces[xp.maximum(g, 0)][:, : element.n_corners]
        ia = xp.argmax(gc == node_a[:, None], -1)
        ib = xp.argmax(gc == node_b[:, None], -1)
        xg = corners[ia] + t[:, None] * (corners[ib] - corners[ia])
        ng = face_normal(element, points[faces[xp.maximum(g, 0)]], xg, xp)
        n_edge = n_edge + xp.where(has[:, None], ng, 0)
    n_edge = _unit(n_edge, xp)

    node = xp.take_along_axis(faces[f], loc[:, None], 1)[:, 0]
    n_vertex = node_normals(node) if callable(node_normals) else node_normals[node]
    return xp.where(
        (feature == FACE)[:, None], n_face, xp.where((feature == EDGE)[:, None], n_edge, n_vertex)
    )


def signed_gap(d_vec, n_pseudo, feature, xp=np, on_surface=0.0):
    """Signed distance and unit normal from d_vec = slave - closest point: gap < 0 is
    penetration.

    The normal is the direction from the closest point to the slave, turned to the pseudo-
    normal's side; where the slave sits on the surface (distance <= `on_surface`, where that
    direction is rounding noise) it is the pseudo-normal.
    """
    dist = xp.sqrt(xp.sum(d_vec**2, -1))
    s = xp.where(xp.sum(d_vec * n_pseudo, -1) < 0, -1.0, 1.0).astype(dist.dtype)
    on = dist <= on_surface
    direction = d_vec / xp.where(dist > 0, dist, 1)[:, None]
    normal = xp.where((on | (feature == FACE))[:, None], n_pseudo, s[:, None] * direction)
    return s * dist, dist, normal


__all__ = ["face_normal", "pseudo_normal", "signed_gap", "FACE", "EDGE", "VERTEX"]
