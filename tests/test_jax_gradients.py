"""The JAX back end's gradients: finite differences for every element and feature, vertex
normals, Hessians, and the differentiable penalty example (a file of its own so that the two
pytest-xdist workers, a file each at a time, share the JAX tests)."""

import arraycontact_jax as acj
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_jax import _compare

import arraycontact as ac
from arraycontact import scenes
from arraycontact._contacts import Feature

ELEMENTS = ["tri3", "quad4", "tri6", "quad8", "quad9"]


@pytest.fixture(autouse=True)
def x64():
    with jax.enable_x64(True):
        yield


# --- gradients ------------------------------------------------------------------------------


def _grid_master(element, z):
    """A 5 x 5 grid of nodes (tri3: 32 faces, quad4: 16, quadratic: 4) at heights z(x, y)."""
    g = np.linspace(-1, 1, 5)
    x, y = np.meshgrid(g, g, indexing="ij")
    return scenes.grid_surface(x, y, z(x, y), element)


def _z(slope):
    """A peak (slope < 0) or a pit (slope > 0) at the origin, gently curved; flat for 0."""
    c = 0 if slope == 0 else 1
    return lambda x, y: (
        slope * (np.abs(x) + np.abs(y)) + c * (0.1 * x**2 + 0.05 * y**2 + 0.05 * x * y)
    )


# (slope, x, y, dz, feature, gap sign): a peak for vertex and edge at positive gaps, a pit for
# them at negative gaps (below a pit's bottom the closest feature is that vertex or edge);
# faces on both sides.
CASES = {
    -0.8: [
        (0.0, 0.0, 0.3, Feature.VERTEX, 1),
        (0.25, 0.01, 0.3, Feature.EDGE, 1),
        (0.4, 0.55, 0.15, Feature.FACE, 1),
    ],
    0.8: [
        (0.01, 0.02, -0.3, Feature.VERTEX, -1),
        (0.25, 0.01, -0.3, Feature.EDGE, -1),
        (0.4, 0.55, -0.15, Feature.FACE, -1),
    ],
}


def _fd_check(
    fn,
    slave,
    master_points,
    h=1e-6,
    tol=2e-8,
    outs=("gap", "point", "normal", "xi"),
    skip=(),
    master_axes=False,
):
    """jacrev of the differentiable outputs with respect to slave and master coordinates against
    central differences of the whole detection; returns the detection and the Jacobians
    {("x" | "m", output): array}.

    Slaves are independent: a slave's outputs must not depend on another slave (exactly zero
    blocks), so each axis is differenced for all slaves at once, checking every entry of the
    diagonal blocks. Master nodes off the faces touching the chosen faces must get exactly zero
    (the closest point depends on its face's nodes, a pseudo-normal on the faces around its
    edge or vertex); the others are differenced along random directions of +-1 entries (as
    jax.test_util.check_grads does), each entry's error entering every direction in full, or
    (`master_axes`, where joint motions of several nodes cross a kink) one coordinate at a
    time. (One
    reverse-mode Jacobian for both arguments: one compilation. Reverse mode transposes the
    forward rules, so it checks them too; jacfwd itself is checked in
    test_hessian_of_a_penalty_energy.)"""
    val = fn(slave, master_points)
    faces = np.asarray(fn.faces)
    near = np.isin(faces, faces[np.asarray(val.face)]).any(1)
    used = np.unique(faces[near])

    def outputs(s, m):
        c = fn(s, m)
        return tuple(getattr(c, out) for out in outs)

    jac2 = jax.jacrev(outputs, (0, 1))(slave, master_points)
    jac = {}
    n = len(slave)
    for out, (a, b) in zip(outs, jac2):
        a, b = np.asarray(a), np.asarray(b)
        assert np.isfinite(a).all() and np.isfinite(b).all(), out
        assert not np.delete(b, used, axis=-2).any(), out
        others = ~np.eye(n, dtype=bool).reshape((n,) + (1,) * (a.ndim - 3) + (n, 1))
        assert not np.where(others, a, 0).any(), f"d{out}_i/dx_j nonzero for i != j"
        jac["x", out], jac["m", out] = a, b
    directions = [("x", np.eye(3)[k][None].repeat(n, 0)) for k in range(3)]
    rng = np.random.default_rng(0)
    for i in range(len(used) * 3 if master_axes else 4):
        v = np.zeros(master_points.shape)
        if master_axes:
            v[used[i // 3], i % 3] = 1.0
        else:
            v[used] = rng.choice([-1.0, 1.0], size=(len(used), 3))
        directions.append(("m", v))
    for which, v in directions:
        pm = [
            fn(slave + sg * h * v, master_points)
            if which == "x"
            else fn(slave, master_points + sg * h * v)
            for sg in (1, -1)
        ]
        for out in (o for o in outs if (which, o) not in skip):
            fd = (np.asarray(getattr(pm[0], out)) - np.asarray(getattr(pm[1], out))) / (2 * h)
            jv = np.tensordot(jac[which, out], v, axes=2)  # along v, all slaves' rows at once
            err = np.abs(jv - fd).max()
            assert err <= tol, f"d{out}/d{which} along a direction off by {err:.2g}"
    return val, jac


@pytest.mark.parametrize("element", ELEMENTS)
def test_gradients_match_finite_differences_for_every_feature_and_at_zero_gap(element):
    """Every feature at positive and negative gaps on a peak and a pit, then slaves exactly on
    a vertex, an edge and a face of a flat master (zero gap: finite gradients equal to the
    differences of the signed distance, smooth there). One plan serves the three masters (same
    connectivity), so each derivative compiles once."""
    peak = _grid_master(element, _z(-0.8))
    slaves = {
        sl: np.array([[x, y, _z(sl)(x, y) + dz] for x, y, dz, _, _ in c]) for sl, c in CASES.items()
    }
    p = acj.plan(peak, slaves[-0.8], d_max=2.0, growth=2.0)

    def fn(s, m):
        return acj.detect(p, s, m)

    fn.faces = peak.faces
    for slope, cases in CASES.items():
        master = _grid_master(element, _z(slope))
        c, _ = _fd_check(fn, jnp.asarray(slaves[slope]), jnp.asarray(master.points))
        assert not bool(c.overflow)
        assert list(np.asarray(c.feature)) == [int(f) for *_, f, _ in cases]
        assert (np.sign(np.asarray(c.gap)) == [sg for *_, sg in cases]).all()

    flat = _grid_master(element, _z(0))
    k = 0.5 if flat.element.linear else 1.0  # a corner node next to the centre
    on = jnp.asarray(
        [[0.0, 0.0, 0.0], [k / 2 if element[:3] == "tri" else k / 3, 0, 0], [0.3, 0.2, 0.0]]
    )
    # Differenced except where the function has a kink: xi (a slave moving off an edge or
    # vertex changes faces) and the normal against master nodes (moving the vertex a slave sits
    # on up or down makes a peak or a pit: one-sided derivatives differ); master coordinates
    # one at a time (moving several nodes at once can cross such a kink). Wider steps: above a
    # flat edge the normal is the direction of a tiny offset, whose solver-tolerance noise
    # would swamp a 1e-6 difference quotient.
    c, jac = _fd_check(
        fn,
        on,
        jnp.asarray(flat.points),
        h=1e-4,
        tol=1e-6,
        skip=(("m", "normal"), ("x", "xi"), ("m", "xi")),
        master_axes=True,
    )
    assert np.asarray(c.active).all() and np.abs(np.asarray(c.gap)).max() == 0
    assert list(np.asarray(c.feature)) == [
        int(Feature.VERTEX),
        int(Feature.EDGE),
        int(Feature.FACE),
    ]
    dgap = np.einsum("iik->ik", jac["x", "gap"])  # d gap_i / d slave_i
    assert np.allclose(dgap, [[0, 0, 1]] * 3)


@pytest.mark.parametrize("element", ELEMENTS)
def test_vertex_normals_per_slave_equal_the_node_normals(element):
    """The smooth outputs' vertex pseudo-normals, gathered per slave from the node -> faces
    table, equal the NumPy scatter over all faces at every corner node."""
    from arraycontact_jax._gradients import padded_node_faces, vertex_normals

    m = _grid_master(element, _z(-0.8))
    corners = np.unique(m.faces[:, : m.element.n_corners])
    got = vertex_normals(
        m.element,
        jnp.asarray(m.points),
        jnp.asarray(m.faces),
        jnp.asarray(padded_node_faces(m)),
        jnp.asarray(corners),
    )
    assert np.allclose(got, m.node_normals[corners], atol=1e-12)


def test_a_pole_of_high_valence_takes_the_scatter_and_equals_numpy():
    """A cone of 40 faces around its apex: the padded node -> faces table would be 40 wide, so
    the smooth outputs take the scatter of every node's pseudo-normal; contacts (a slave above
    the apex on its vertex) equal NumPy's and the gradient is finite."""
    from arraycontact_jax._gradients import MAX_VALENCE

    k = 40
    assert k > MAX_VALENCE
    t = np.linspace(0, 2 * np.pi, k, endpoint=False)
    pts = np.r_[[[0.0, 0.0, 0.5]], np.c_[np.cos(t), np.sin(t), np.zeros(k)]]
    faces = [[0, 1 + i, 1 + (i + 1) % k] for i in range(k)]
    master = ac.Surface(pts, faces, "tri3")
    slave = np.array([[0.0, 0.0, 0.9], [0.3, 0.1, 0.6], [0.5, -0.2, 0.1], [0.2, 0.2, 0.2]])
    p = acj.plan(master, slave, d_max=1.0)
    assert p.topology.node_faces is None
    c = acj.detect(p, jnp.asarray(slave), jnp.asarray(pts))
    r = ac.detect(slave, master, d_max=1.0, backend="numpy")
    _compare(c, r)
    assert int(np.asarray(c.feature)[0]) == int(Feature.VERTEX)
    g = jax.grad(lambda m: jnp.sum(acj.detect(p, jnp.asarray(slave), m).gap))(jnp.asarray(pts))
    assert np.isfinite(np.asarray(g)).all() and np.abs(np.asarray(g)).max() > 0


def test_hessian_of_a_penalty_energy():
    s = scenes.rough_surfaces(2**8, seed=2)
    slave = s.slave - [0, 0, 1.2]
    p = acj.plan(s.master, slave, d_max=1.0)
    mp = jnp.asarray(s.master.points)

    def energy(q):
        c = acj.detect(p, jnp.asarray(slave) + q[None, :], mp)
        g = jnp.where(c.active, c.gap, 0.0)
        return 0.5 * 100.0 * jnp.sum(jnp.minimum(g, 0) ** 2)

    q = jnp.zeros(3)
    grad = jax.jit(jax.grad(energy))  # one compilation for the six differences
    hess = jax.jit(jax.hessian(energy))(q)  # jacfwd of jacrev
    h = 1e-6
    fd = np.stack([(grad(q + h * e) - grad(q - h * e)) / (2 * h) for e in np.eye(3)], 1)
    assert np.isfinite(hess).all() and np.abs(hess).max() > 0
    assert np.allclose(hess, fd, rtol=1e-7, atol=1e-6 * np.abs(fd).max())


def test_penalty_example_reaches_zero_penetration():
    from arraycontact_jax.example import push_out

    res = push_out(n_nodes=2**8, steps=30)
    assert res["min_gap_before"] < -0.1
    assert res["min_gap_after"] >= -1e-6 * res["length"]
    assert res["energy_after"] <= 1e-12 and not res["overflow"]
