"""Shape functions: partition of unity, interpolation, derivatives, closed forms."""

import numpy as np
import pytest

from arraycontact._elements import (
    ELEMENTS,
    get_element,
    shape_derivatives,
    shape_functions,
    shape_second_derivatives,
)

NAMES = sorted(ELEMENTS)


def _samples(e, n=50, seed=0):
    rng = np.random.default_rng(seed)
    if e.kind == "tri":
        u = rng.uniform(0, 1, (n, 2))
        u = np.where(u.sum(1, keepdims=True) > 1, 1 - u[:, ::-1], u)
        return u
    return rng.uniform(-1, 1, (n, 2))


@pytest.mark.parametrize("name", NAMES)
def test_partition_of_unity_and_interpolation(name):
    e = get_element(name)
    xi = _samples(e)
    assert np.allclose(shape_functions(e, xi).sum(-1), 1.0, atol=1e-14)
    assert np.allclose(shape_derivatives(e, xi).sum(-2), 0.0, atol=1e-13)
    assert np.allclose(shape_functions(e, e.nodes), np.eye(e.nodes_per_face), atol=1e-14)
    # Linear completeness: sum_i N_i x_i reproduces x for linear fields.
    assert np.allclose(shape_functions(e, xi) @ e.nodes, xi, atol=1e-13)


@pytest.mark.parametrize("name", NAMES)
def test_derivatives_against_finite_differences(name):
    e = get_element(name)
    xi = _samples(e, 20, seed=1) * 0.9
    h = 1e-6
    for a in range(2):
        d = np.zeros(2)
        d[a] = h
        fd = (shape_functions(e, xi + d) - shape_functions(e, xi - d)) / (2 * h)
        assert np.allclose(shape_derivatives(e, xi)[..., a], fd, atol=1e-8)
        fd2 = (shape_derivatives(e, xi + d) - shape_derivatives(e, xi - d)) / (2 * h)
        sec = shape_second_derivatives(e, xi)
        # d/dxi_a of dN/dxi_b: (a, b) = (0, 0) -> 0, (0, 1) and (1, 0) -> 1, (1, 1) -> 2
        assert np.allclose(sec[..., a], fd2[..., 0], atol=1e-7)
        assert np.allclose(sec[..., a + 1], fd2[..., 1], atol=1e-7)


def test_closed_forms():
    """Textbook formulas, written out independently of the Vandermonde construction."""
    rng = np.random.default_rng(2)
    t = rng.uniform(0, 0.5, (10, 2))
    x, y = t[:, 0], t[:, 1]
    L0, L1, L2 = 1 - x - y, x, y
    tri3 = np.stack([L0, L1, L2], -1)
    tri6 = np.stack(
        [
            L0 * (2 * L0 - 1),
            L1 * (2 * L1 - 1),
            L2 * (2 * L2 - 1),
            4 * L0 * L1,
            4 * L1 * L2,
            4 * L2 * L0,
        ],
        -1,
    )
    assert np.allclose(shape_functions(get_element("tri3"), t), tri3)
    assert np.allclose(shape_functions(get_element("tri6"), t), tri6)
    q = rng.uniform(-1, 1, (10, 2))
    x, y = q[:, 0], q[:, 1]
    c = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]])
    quad4 = np.stack([(1 + x * a) * (1 + y * b) / 4 for a, b in c], -1)
    corners8 = [(1 + x * a) * (1 + y * b) * (x * a + y * b - 1) / 4 for a, b in c]
    mids8 = [
        (1 - x**2) * (1 - y) / 2,
        (1 + x) * (1 - y**2) / 2,
        (1 - x**2) * (1 + y) / 2,
        (1 - x) * (1 - y**2) / 2,
    ]
    assert np.allclose(shape_functions(get_element("quad4"), q), quad4)
    assert np.allclose(shape_functions(get_element("quad8"), q), np.stack(corners8 + mids8, -1))

    def lagrange(s, k):  # 1-D quadratic Lagrange polynomials at -1, 0, 1
        return [s * (s - 1) / 2, 1 - s**2, s * (s + 1) / 2][k]

    idx = [(0, 0), (2, 0), (2, 2), (0, 2), (1, 0), (2, 1), (1, 2), (0, 1), (1, 1)]
    quad9 = np.stack([lagrange(x, i) * lagrange(y, j) for i, j in idx], -1)
    assert np.allclose(shape_functions(get_element("quad9"), q), quad9)


@pytest.mark.parametrize("name", NAMES)
def test_domain_constraints_and_lebesgue(name):
    e = get_element(name)
    # Corners and centre are inside the domain; corners sit on two constraints.
    assert (e.nodes @ e.constraints_a.T - e.constraints_b >= -1e-15).all()
    act = np.abs(e.corners @ e.constraints_a.T - e.constraints_b) < 1e-15
    assert (act.sum(1) == 2).all()
    xi = _samples(e, 2000, seed=3)
    assert np.abs(shape_functions(e, xi)).sum(-1).max() <= e.lebesgue + 1e-12
    known = {"tri3": 1.0, "quad4": 1.0, "tri6": 5 / 3, "quad9": 1.5625, "quad8": 3.0}
    assert known[name] <= e.lebesgue <= 1.011 * known[name]


def test_unknown_element():
    with pytest.raises(ValueError, match="unknown element"):
        get_element("hex8")


def test_same_code_on_jax():
    import jax
    import jax.numpy as jnp

    with jax.enable_x64(True):
        for name in NAMES:
            e = get_element(name)
            xi = _samples(e)
            assert np.allclose(
                np.asarray(shape_functions(e, jnp.asarray(xi), jnp)),
                shape_functions(e, xi),
                atol=1e-14,
            )
            assert np.allclose(
                np.asarray(shape_second_derivatives(e, jnp.asarray(xi), jnp)),
                shape_second_derivatives(e, xi),
                atol=1e-13,
            )
