"""Numerical-stability stress tests on every back end and dtype (issue 7): far translations and
extreme scales, degenerate and coincident geometry, slaves exactly on edges and vertices,
equidistant faces, nearly parallel surfaces, strongly warped quads. Expected values come from
the brute-force reference or closed forms."""

import numpy as np
import pytest
from conftest import reference

import arraycontact as ac
from arraycontact import scenes

RUNS = [
    ("numpy", "float64"),
    ("numpy", "float32"),
    ("jax", "float64"),
    ("jax", "float32"),
    ("warp", "float32"),
]


def _tol(dtype, L, offset=0.0):
    # float32 runs in a local frame: 1e-5 of the element size at any offset. float64 keeps the
    # global frame: rounding of the coordinates themselves, 64 eps of their magnitude.
    if dtype == "float32":
        return 1e-5 * L
    return 1e-12 * L + 64 * np.finfo(float).eps * offset


def _check(c, slave, master, dtype, offset=0.0, ref=None):
    """Active set, distance and gap against the reference; the chosen face holds a point at
    the minimal distance."""
    ref = ref if ref is not None else reference(slave, master)
    L = master.longest_edge
    tol = _tol(dtype, L, offset)
    want = ref.distance <= c.d_max
    border = np.abs(ref.distance - c.d_max) <= tol
    assert np.array_equal(c.active[~border], want[~border])
    a = c.active & want
    assert np.abs(c.distance[a] - ref.distance[a]).max() <= tol
    assert np.abs(c.gap[a] - ref.gap[a]).max() <= tol
    _, d2 = ac.reference._closest_on_faces(
        master.element, slave[a], master.points[master.faces[c.face[a]]]
    )
    assert np.abs(np.sqrt(d2) - ref.distance[a]).max() <= tol
    return ref


@pytest.fixture(scope="module")
def small():
    return scenes.rough_surfaces(2**8, seed=11)


@pytest.mark.parametrize("backend, dtype", RUNS)
def test_translated_far_away(small, backend, dtype):
    L = small.master.longest_edge
    for offset in (1e3, 1e5, 1e8):
        shift = np.array([1.0, -0.7, 0.4]) * offset * L
        master = small.master.with_points(small.master.points + shift)
        slave = small.slave + shift
        c = ac.detect(slave, master, backend=backend, dtype=dtype)
        _check(c, slave, master, dtype, offset * L)


@pytest.mark.parametrize("backend, dtype", RUNS)
def test_scaled(small, backend, dtype):
    for scale in (1e-6, 1e6):
        master = small.master.with_points(small.master.points * scale)
        slave = small.slave * scale
        c = ac.detect(slave, master, backend=backend, dtype=dtype)
        _check(c, slave, master, dtype)


def _degenerate():
    """A quad4 grid with a collapsed face (two coincident nodes with different ids), a sliver
    face and a zero-area face (all four nodes on a line)."""
    g = np.linspace(0, 4, 5)
    x, y = np.meshgrid(g, g, indexing="ij")
    s = scenes.grid_surface(x, y, 0.1 * np.sin(x + y), "quad4")
    pts = s.points.copy()
    pts[6] = pts[1]  # coincident nodes: the first face collapses to a triangle
    pts[18, :2] = pts[13, :2] + [1e-9, 0.0]  # a sliver
    faces = np.concatenate([s.faces, [[20, 21, 22, 23]]])
    pts = np.concatenate([pts, [[0, 6, 0], [1, 6, 0], [2, 6, 0], [3, 6, 0]]])  # a line
    return ac.Surface(pts, faces, "quad4")


@pytest.mark.parametrize("backend, dtype", RUNS)
def test_degenerate_and_coincident_geometry(backend, dtype):
    master = _degenerate()
    rng = np.random.default_rng(0)
    slave = rng.uniform([-0.5, -0.5, -1], [4.5, 6.5, 1], (400, 3))
    c = ac.detect(slave, master, backend=backend, dtype=dtype, d_max=1.0)
    assert np.isfinite(c.gap[c.active]).all() and np.isfinite(c.normal[c.active]).all()
    _check(c, slave, master, dtype)


@pytest.mark.parametrize("backend, dtype", RUNS)
def test_slaves_exactly_on_vertices_and_edges(small, backend, dtype):
    m = small.master
    e = m.edges
    slave = np.concatenate([m.points[m.nodes], 0.5 * (m.points[e[:, 0]] + m.points[e[:, 1]])])
    c = ac.detect(slave, m, backend=backend, dtype=dtype)
    assert c.active.all()
    assert np.abs(c.gap).max() <= _tol(dtype, m.longest_edge) * 10
    assert np.isfinite(c.normal).all() and np.allclose(
        np.linalg.norm(c.normal, axis=1), 1, atol=1e-5
    )


@pytest.mark.parametrize("backend, dtype", RUNS)
def test_equidistant_faces_go_to_the_smallest_id(backend, dtype):
    # A symmetric roof: slaves on the symmetry plane are equidistant from both slopes.
    pts = np.array([[-1, 0, 0], [0, 0, 1], [1, 0, 0], [-1, 1, 0], [0, 1, 1], [1, 1, 0]], float)
    roof = ac.Surface(pts, [[1, 4, 5, 2], [0, 3, 4, 1]], "quad4")  # ids: right 0, left 1
    slave = np.array([[0.0, y, z] for y in (0.2, 0.5, 0.8) for z in (0.2, 0.5, 0.7)])
    c = ac.detect(slave, roof, backend=backend, dtype=dtype, d_max=2.0)
    assert c.active.all() and (c.face == 0).all()
    ref = ac.reference.closest_points(slave, roof)
    assert (ref.face == 0).all()
    assert np.abs(c.gap - ref.gap).max() <= _tol(dtype, roof.longest_edge)


@pytest.mark.parametrize("backend, dtype", RUNS)
def test_nearly_parallel_surfaces(backend, dtype):
    g = np.linspace(0, 8, 9)
    x, y = np.meshgrid(g, g, indexing="ij")
    master = scenes.grid_surface(x, y, 1e-3 * x, "tri3")  # a slightly tilted plane
    n = np.array([-1e-3, 0, 1]) / np.linalg.norm([-1e-3, 0, 1])
    rng = np.random.default_rng(1)
    base = rng.uniform(1, 7, (60, 2))
    on = np.c_[base, 1e-3 * base[:, 0]]
    gaps = np.repeat([1e-9, 1e-6, 1e-3, -1e-6], 15)
    slave = on + gaps[:, None] * n
    c = ac.detect(slave, master, backend=backend, dtype=dtype)
    assert c.active.all()
    assert np.abs(c.gap - gaps).max() <= _tol(dtype, master.longest_edge, 8)


@pytest.mark.parametrize("backend, dtype", RUNS)
def test_strongly_warped_quads(backend, dtype):
    g = np.linspace(0, 3, 4)
    x, y = np.meshgrid(g, g, indexing="ij")
    rng = np.random.default_rng(2)
    z = 0.45 * rng.standard_normal(x.shape)  # neighbouring nodes out of plane by ~0.5 edges
    master = scenes.grid_surface(x, y, z, "quad4")
    slave = rng.uniform([-0.5, -0.5, -1.5], [3.5, 3.5, 1.5], (300, 3))
    c = ac.detect(slave, master, backend=backend, dtype=dtype, d_max=1.0)
    _check(c, slave, master, dtype)
