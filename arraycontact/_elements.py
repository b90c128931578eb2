"""Element library: shape functions and reference domains for tri3, quad4, tri6, quad8, quad9.

Node order is meshio's / VTK's: corners first, then the mid-edge nodes (edge 0-1, 1-2, ...),
then the centre. Triangles live on the unit simplex with N = (1 - xi - eta, xi, eta) for tri3;
quads on [-1, 1]^2 (seed 003, section 4.2).

Every shape function is a polynomial in (xi, eta). Each element names its monomial space and its
nodes; the coefficients are the inverse of the Vandermonde matrix at the nodes, so one code path
evaluates N, dN and d2N for all five elements, with any array namespace (NumPy or jax.numpy).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from ._xp import einsum

FACE, EDGE, VERTEX = 0, 1, 2


def _powers(x):
    """x**p for p = 0, 1, 2 and their first and second derivatives, constants as Python
    numbers. (x**0 would give NaN gradients at 0 under JAX autodiff.)"""
    return (1, x, x * x), (0, 1, 2 * x), (0, 0, 2)


def _product(a, b, zero, one):
    """a * b with products by the constants 0 and 1 left out (zero and one: arrays shared by
    every column): the monomials of a quad9 point are then 9 products, not 27 small
    expressions, which were most of a JAX program's size on curved faces and of its compile
    time."""
    if isinstance(b, int):
        a, b = b, a
    if not isinstance(a, int):  # both arrays
        return a * b
    if isinstance(b, int):  # both constant
        return zero if a * b == 0 else one if a * b == 1 else a * b * one
    return zero if a == 0 else b if a == 1 else a * b


@dataclass(frozen=True, eq=False)
class Element:
    name: str
    kind: str  # "tri" or "quad"
    nodes: np.ndarray  # natural coordinates of the nodes, [nn, 2]
    monomials: tuple  # exponents (p, q) of xi**p * eta**q spanning the shape functions
    constraints_a: np.ndarray = field(repr=False)  # domain is {xi : A xi >= b}
    constraints_b: np.ndarray = field(repr=False)

    @property
    def nodes_per_face(self) -> int:
        return len(self.nodes)

    @property
    def n_corners(self) -> int:
        return 3 if self.kind == "tri" else 4

    @property
    def linear(self) -> bool:
        return self.nodes_per_face == self.n_corners

    @property
    def corners(self) -> np.ndarray:
        return self.nodes[: self.n_corners]

    @property
    def centre(self) -> np.ndarray:
        return np.array([1 / 3, 1 / 3]) if self.kind == "tri" else np.zeros(2)

    @cached_property
    def coefficients(self) -> np.ndarray:
        """C with N_i(xi) = sum_j C[i, j] m_j(xi); C = inv(V), V[k, j] = m_j(node_k)."""
        v = np.array([[x**p * y**q for p, q in self.monomials] for x, y in self.nodes])
        c = np.linalg.inv(v).T
        c[np.abs(c) < 1e-13] = 0.0
        return c

    @cached_property
    def edge_nodes(self) -> np.ndarray:
        """Local node ids along each edge [n_edges, 2 or 3]: start corner, end corner, mid node."""
        k = self.n_corners
        e = [[i, (i + 1) % k] for i in range(k)]
        if not self.linear:
            e = [a + [k + i] for i, a in enumerate(e)]
        return np.array(e, np.int32)

    @cached_property
    def constraint_edge(self) -> np.ndarray:
        """Local edge id on which constraint j is active."""
        out = []
        for a, b in zip(self.constraints_a, self.constraints_b):
            on = [
                i
                for i, (s, e) in enumerate(self.edge_nodes[:, :2])
                if abs(a @ self.nodes[s] - b) < 1e-12 and abs(a @ self.nodes[e] - b) < 1e-12
            ]
            out.append(on[0])
        return np.array(out, np.int32)

    @cached_property
    def lebesgue(self) -> float:
        """max over the domain of sum_i |N_i|: |x(xi) - c| <= lebesgue * max_i |x_i - c| for any c.

        Found on a dense lattice and raised by 1 %, which bounds the sampling error of these
        low-degree polynomials with room to spare (the bound is used only to prune, never to
        decide the answer)."""
        s = np.linspace(0.0, 1.0, 201) if self.kind == "tri" else np.linspace(-1.0, 1.0, 201)
        g = np.stack(np.meshgrid(s, s, indexing="ij"), -1).reshape(-1, 2)
        if self.kind == "tri":
            g = g[g.sum(1) <= 1.0 + 1e-12]
        n = shape_functions(self, g, np)
        lam = float(np.abs(n).sum(-1).max())
        return 1.0 if self.linear else 1.01 * lam


def _element(name, kind, nodes, monomials):
    nodes = np.asarray(nodes, float)
    if kind == "tri":
        a = np.array([[1.0, 0.0], [0.0, 1.0], [-1.0, -1.0]])
        b = np.array([0.0, 0.0, -1.0])
    else:
        a = np.array([[1.0, 0.0], [-1.0, 0.0], [0.0, 1.0], [0.0, -1.0]])
        b = np.array([-1.0, -1.0, -1.0, -1.0])
    return Element(name, kind, nodes, tuple(monomials), a, b)


_TRI_CORNERS = [[0, 0], [1, 0], [0, 1]]
_TRI_MIDS = [[0.5, 0], [0.5, 0.5], [0, 0.5]]
_QUAD_CORNERS = [[-1, -1], [1, -1], [1, 1], [-1, 1]]
_QUAD_MIDS = [[0, -1], [1, 0], [0, 1], [-1, 0]]

ELEMENTS = {
    e.name: e
    for e in (
        _element("tri3", "tri", _TRI_CORNERS, [(0, 0), (1, 0), (0, 1)]),
        _element("quad4", "quad", _QUAD_CORNERS, [(0, 0), (1, 0), (0, 1), (1, 1)]),
        _element(
            "tri6",
            "tri",
            _TRI_CORNERS + _TRI_MIDS,
            [(0, 0), (1, 0), (0, 1), (2, 0), (1, 1), (0, 2)],
        ),
        _element(
            "quad8",
            "quad",
            _QUAD_CORNERS + _QUAD_MIDS,
            [(0, 0), (1, 0), (0, 1), (2, 0), (1, 1), (0, 2), (2, 1), (1, 2)],
        ),
        _element(
            "quad9",
            "quad",
            _QUAD_CORNERS + _QUAD_MIDS + [[0, 0]],
            [(p, q) for p in range(3) for q in range(3)],
        ),
    )
}
NODES_PER_FACE = {e.nodes_per_face: e.name for e in ELEMENTS.values()}


def get_element(name) -> Element:
    if isinstance(name, Element):
        return name
    try:
        return ELEMENTS[name]
    except KeyError:
        raise ValueError(f"unknown element {name!r}; expected one of {sorted(ELEMENTS)}") from None


def _monomials(element, xi, xp, order):
    x, y = xi[..., 0], xi[..., 1]
    px, py = _powers(x), _powers(y)
    zero, one = xp.zeros_like(x), xp.ones_like(x)
    # (order in xi, order in eta) of each column: N; d/dxi, d/deta; d2/dxi2, d2/dxi deta, d2/deta2.
    orders = {0: [(0, 0)], 1: [(1, 0), (0, 1)], 2: [(2, 0), (1, 1), (0, 2)]}[order]
    cols = [
        xp.stack([_product(px[a][p], py[b][q], zero, one) for p, q in element.monomials], -1)
        for a, b in orders
    ]
    return cols[0] if order == 0 else xp.stack(cols, -1)  # [..., m] or [..., m, 2 or 3]


def shape_functions(element, xi, xp=np):
    """N [..., nn] at natural coordinates xi [..., 2]."""
    c = xp.asarray(element.coefficients, dtype=xi.dtype)
    m = _monomials(element, xi, xp, 0)
    # (NumPy: matmul; einsum's broadcast loops were 1.4-3x slower and most of the brute-force
    # reference's time on curved faces. JAX: _xp.einsum, fused.)
    return m @ c.T if xp is np else einsum(xp, "...m,nm->...n", m, c)


def _derivatives(element, xi, xp, order):
    c = xp.asarray(element.coefficients, dtype=xi.dtype)
    m = _monomials(element, xi, xp, order)  # [..., m, k]
    return c @ m if xp is np else einsum(xp, "nm,...mk->...nk", c, m)


def shape_derivatives(element, xi, xp=np):
    """dN/dxi [..., nn, 2]."""
    return _derivatives(element, xi, xp, 1)


def shape_second_derivatives(element, xi, xp=np):
    """[..., nn, 3]: d2N/dxi2, d2N/dxi deta, d2N/deta2."""
    return _derivatives(element, xi, xp, 2)


def interpolate(element, xe, xi, xp=np):
    """Point x(xi) [..., 3] and tangents x_xi, x_eta [..., 3, 2] of faces with nodes xe
    [..., nn, 3]."""
    n = shape_functions(element, xi, xp)
    dn = shape_derivatives(element, xi, xp)
    if xp is np:
        return (n[..., None, :] @ xe)[..., 0, :], np.swapaxes(xe, -1, -2) @ dn
    return einsum(xp, "...n,...nk->...k", n, xe), einsum(xp, "...na,...nk->...ka", dn, xe)
