"""Differentiable closest points (DESIGN section 5).

The search (which face, which feature) runs under `stop_gradient`. Given its answer, the
closest point is re-expressed as a smooth function of the slave and master coordinates:

* the natural coordinates solve R(u) = 0 with xi = base + B u, where R is the stationarity
  condition of eq. (8) restricted to the feature — both coordinates free on a face interior, the
  edge parameter on an edge (edges are straight in natural coordinates), none at a vertex;
  the solution keeps the search's value and takes its derivatives from the implicit-function
  theorem (a custom JVP that calls itself, so second derivatives are exact too);
* the point is x(xi); the gap is (s - x)·n on a face interior, and ±|s - x| on an edge or at
  a vertex, with the search's sign. Where the slave lies on the edge or vertex (distance 0) the
  gap is (s - x)·n_pseudo and the point s - gap n_pseudo: same values, the derivatives of the
  surface's tangent plane there (the subgradient along the pseudo-normal), no NaN.
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

from arraycontact._elements import EDGE, FACE, interpolate, shape_functions
from arraycontact._geometry import _solve2
from arraycontact._normals import pseudo_normal
from arraycontact._surface import _unit, corner_normal, node_normals


def _residual(element, u, s, xe, base, b, mask):
    """Stationarity of |s - x(xi)|^2 / 2 along the feature's free directions (2 equations);
    a direction the feature does not have (mask 0) is pinned by u_k = 0."""
    # Products written as sums: XLA fuses them (a batched dot is a GEMM call on a GPU).
    xi = base + jnp.sum(b * u[None, :], -1)
    n = shape_functions(element, xi, jnp)
    _, dx = interpolate(element, xe, xi, jnp)  # [3, 2]
    to_slave = jnp.sum(n[:, None] * (xe - s[None, :]), 0)  # x(xi) - s from nearby differences
    g = jnp.sum(dx * to_slave[:, None], 0)
    return jnp.sum(b * g[:, None], 0) + (1 - mask) * u


@partial(jax.custom_jvp, nondiff_argnums=(0,))
def _root(element, u0, s, xe, base, b, mask):
    return u0


@_root.defjvp
def _root_jvp(element, primals, tangents):
    u0, s, xe, base, b, mask = primals
    _, ds, dxe, _, _, _ = tangents
    u = _root(element, u0, s, xe, base, b, mask)
    h = jax.jacfwd(_residual, 1)(element, u, s, xe, base, b, mask)
    _, rhs = jax.jvp(
        lambda s_, xe_: _residual(element, u, s_, xe_, base, b, mask), (s, xe), (ds, dxe)
    )
    return u, -_solve2(h, rhs, jnp)


def _polish(element, u, s, xe, base, b, mask):
    """Newton steps on R(u) = 0 from the search's answer (met to its KKT tolerance): the
    values then hold to rounding, as the implicit derivatives assume. None on tri3, whose
    closed-form answer already does (R is affine in u there)."""
    for _ in range(0 if element.name == "tri3" else 2):
        h = jax.jacfwd(_residual, 1)(element, u, s, xe, base, b, mask)
        u = u - _solve2(h, _residual(element, u, s, xe, base, b, mask), jnp)
    return u


def _feature_frame(element, feature, local, xi0):
    """base, B, mask and the start u0 of the feature's parametrisation xi = base + B u."""
    k = element.n_corners
    corners = jnp.asarray(element.corners, xi0.dtype)
    loc = jnp.maximum(local, 0) % k
    a, c = corners[loc], corners[(loc + 1) % k]
    on_face, on_edge = feature == FACE, feature == EDGE
    t0 = jnp.dot(xi0 - a, c - a) / jnp.dot(c - a, c - a)
    zero = jnp.zeros(2, xi0.dtype)
    base = jnp.where(on_face, zero, a)  # the edge start or the vertex
    b_edge = jnp.stack([c - a, zero], -1)
    b = jnp.where(on_face, jnp.eye(2, dtype=xi0.dtype), jnp.where(on_edge, b_edge, 0 * b_edge))
    mask = jnp.where(
        on_face,
        jnp.ones(2, xi0.dtype),
        jnp.where(on_edge, jnp.asarray([1.0, 0.0], xi0.dtype), zero),
    )
    u0 = jnp.where(on_face, xi0, jnp.where(on_edge, jnp.stack([t0, 0 * t0]), zero))
    return base, b, mask, u0


def _one(element, on_surface, s, xe, feature, local, xi0, n_pseudo, sign):
    base, b, mask, u0 = _feature_frame(element, feature, local, jax.lax.stop_gradient(xi0))
    u0 = _polish(element, u0, jax.lax.stop_gradient(s), jax.lax.stop_gradient(xe), base, b, mask)
    u = _root(element, u0, s, xe, base, b, mask)
    xi = base + jnp.sum(b * u[None, :], -1)
    # s - x(xi) from nearby differences (partition of unity)
    to_slave = -jnp.sum(shape_functions(element, xi, jnp)[:, None] * (xe - s[None, :]), 0)
    _, dx = interpolate(element, xe, xi, jnp)
    n_face = _unit(jnp.cross(dx[:, 0], dx[:, 1]), jnp)
    r2 = jnp.dot(to_slave, to_slave)
    on = r2 <= on_surface * on_surface  # on the surface: no direction but rounding noise
    dist = jnp.sqrt(jnp.where(on, 1, r2))
    along = jnp.dot(to_slave, n_pseudo)
    gap = jnp.where(feature == FACE, jnp.dot(to_slave, n_face), jnp.where(on, along, sign * dist))
    direction = to_slave / jnp.where(on, 1, dist)
    normal = jnp.where(feature == FACE, n_face, jnp.where(on, n_pseudo, sign * direction))
    # A slave on an edge or vertex (distance 0) sits on the surface: its closest point is
    # itself, moving with it along the surface (s - gap * n has that derivative, I - n n^T).
    # Its natural coordinates are not differentiable there (moving off switches faces).
    point = jnp.where(on & (feature != FACE), s - gap * normal, s - to_slave)
    return xi, point, gap, normal


def vertex_normals(element, nodes_x, faces, node_faces, node):
    """The angle-weighted pseudo-normals (arraycontact._surface.node_normals) of the corner
    nodes `node` [P] only, from the faces around each (node_faces [n_points, V], -1 padded):
    a gather per slave instead of a scatter over every face of the master."""
    g = node_faces[node]  # [P, V]
    fg = faces[jnp.maximum(g, 0)]  # [P, V, nn]
    corner = jnp.argmax(fg[..., : element.n_corners] == node[:, None, None], -1)
    xi = jnp.asarray(element.nodes, nodes_x.dtype)[corner]
    _, dx = interpolate(element, nodes_x[fg], xi, jnp)  # [P, V, 3, 2]
    terms = corner_normal(element, dx, corner, jnp)
    return _unit(jnp.sum(jnp.where((g >= 0)[..., None], terms, 0), 1), jnp)


#: Above this largest valence (a pole or fan node) the padded table would cost n_points x V
#: memory and every slave V faces: the smooth outputs then take every node's pseudo-normal by
#: one scatter over all faces instead.
MAX_VALENCE = 32


def valence_fits(master) -> bool:
    """Whether the master's largest valence is at most MAX_VALENCE (a padded table kept)."""
    return int(np.diff(master.node_faces[0]).max()) <= MAX_VALENCE


def padded_node_faces(master):
    """[n_points, V] the faces of each node, -1 padded (V: the largest valence); None when V
    exceeds MAX_VALENCE."""
    if not valence_fits(master):
        return None
    offsets, ids = master.node_faces
    counts = np.diff(offsets)
    rows = np.repeat(np.arange(len(counts)), counts)
    table = np.full((len(counts), max(int(counts.max()), 1)), -1, np.int32)
    table[rows, np.arange(len(ids)) - offsets[rows]] = ids
    return table


def smooth(element, slave_x, nodes_x, topo, face, feature, local, xi, on_surface, vertex=None):
    """Differentiable xi, point, gap, normal of the search's answer ([n] rows).

    `face`, `feature`, `local` come from the search; `xi` is its value, the Newton start and
    the point whose side of the pseudo-normal gives the sign (without gradient: as the
    search's classification, which is then left unused, so XLA drops it: the pseudo-normals
    of every row cost 0.2-0.5 ms at 2^20 on an H100); a slave within `on_surface` of an edge or
    vertex counts as on it, with the feature's pseudo-normal (differentiable). Rows without a
    face are computed at the centre of face (row mod the number of faces): finite, then
    masked by the caller; spread over the faces, because their (zero) gradients are still
    added into their face's nodes, which on a GPU are atomic adds, serialized where most
    rows share one face (steep rough surfaces: 17 % of the slaves in contact at 2^15).
    vertex: the nodes' pseudo-normals [n_points, 3] from nodes_x (differentiable), where the
    caller has them."""
    ok = face >= 0
    spread = jnp.arange(face.shape[0], dtype=face.dtype) % topo.faces.shape[0]
    face = jnp.where(ok, face, spread)
    feature = jnp.where(ok, feature, FACE)
    xi = jnp.where(ok[:, None], xi, jnp.asarray(element.centre, slave_x.dtype))
    faces = topo.faces
    if vertex is not None:
        pass
    elif topo.node_faces is not None:
        vertex = partial(vertex_normals, element, nodes_x, faces, topo.node_faces)
    else:
        vertex = node_normals(element, faces, nodes_x, jnp)
    n_pseudo = pseudo_normal(
        element,
        nodes_x,
        faces,
        topo.face_edges,
        topo.edge_faces,
        vertex,
        face,
        feature,
        jnp.maximum(local, 0),
        jax.lax.stop_gradient(xi),
        jnp,
    )
    xe = nodes_x[faces[face]]
    # The search's side (arraycontact._normals.signed_gap): x - s from nearby differences at
    # the search's xi, against the pseudo-normal.
    n = shape_functions(element, jax.lax.stop_gradient(xi), jnp)
    to_point = jnp.sum(n[..., None] * (xe - slave_x[:, None]), -2)
    side = jax.lax.stop_gradient(jnp.sum(to_point * n_pseudo, -1))
    sign = jnp.where(ok & (side > 0), -1.0, 1.0).astype(slave_x.dtype)
    return jax.vmap(partial(_one, element, on_surface))(
        slave_x, xe, feature, local, xi, n_pseudo, sign
    )
