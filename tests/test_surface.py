"""Surface: validation with clear errors, and derived topology against closed forms."""

import numpy as np
import pytest

import arraycontact as ac
from arraycontact import scenes
from arraycontact._elements import get_element, interpolate, shape_functions

CUBE_PTS = np.array([[x, y, z] for z in (0, 1) for y in (0, 1) for x in (0, 1)], float)
# Outward-oriented quads of the unit cube (node i = x + 2 y + 4 z).
CUBE_QUADS = np.array(
    [[0, 2, 3, 1], [4, 5, 7, 6], [0, 1, 5, 4], [2, 6, 7, 3], [0, 4, 6, 2], [1, 3, 7, 5]]
)


def cube():
    return ac.Surface(CUBE_PTS, CUBE_QUADS, "quad4")


def test_cube_topology_and_normals():
    s = cube()
    assert s.closed and len(s.edges) == 12 and len(s.boundary_edges) == 0
    assert (s.edge_faces >= 0).all()
    c = s.points[s.faces].mean(1)
    assert np.allclose(s.face_normals, 2 * (c - 0.5))  # outward unit normals
    assert np.allclose(
        s.node_normals, (CUBE_PTS - 0.5) / np.linalg.norm(CUBE_PTS - 0.5, axis=1, keepdims=True)
    )
    assert s.longest_edge == pytest.approx(np.sqrt(2))  # the face diagonal (eq. 2)
    offsets, ids = s.node_faces
    assert (np.diff(offsets) == 3).all()
    for node in range(8):
        assert set(ids[offsets[node] : offsets[node + 1]]) == set(np.nonzero(s.faces == node)[0])


def test_open_grid_boundary():
    x, y = np.meshgrid(np.arange(4.0), np.arange(4.0), indexing="ij")
    s = scenes.grid_surface(x, y, 0 * x, "quad4")
    assert not s.closed
    assert len(s.boundary_edges) == 12 and len(s.boundary_nodes) == 12
    assert len(s.edges) == 24
    # Boundary edges run counter-clockwise (the faces' orientation, normal +z).
    a, b = s.points[s.boundary_edges[:, 0]], s.points[s.boundary_edges[:, 1]]
    centre = s.points.mean(0)
    assert (np.cross(a - centre, b - a)[:, 2] > 0).all()
    assert np.allclose(s.node_normals[s.nodes], [0, 0, 1])


def _domain_grid(e, n):
    """An n x n grid of the element's natural domain (the triangle's half on triangles)."""
    g = np.linspace(0, 1, n) if e.kind == "tri" else np.linspace(-1, 1, n)
    xi = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    return xi[xi.sum(1) <= 1] if e.kind == "tri" else xi


def _random_faces(e, rng, count, scale):
    """`count` faces [count, nn, 3]: the natural domain in z = 0, nodes moved by `scale`."""
    nn = e.nodes_per_face
    return np.c_[e.nodes, np.zeros(nn)][None] + scale * rng.normal(size=(count, nn, 3))


@pytest.mark.parametrize("element", ["tri3", "quad4", "tri6", "quad8", "quad9"])
def test_face_ball_holds_the_face(element):
    rng = np.random.default_rng(0)
    e = get_element(element)
    pts = np.c_[e.nodes, np.zeros(e.nodes_per_face)] + 0.4 * rng.normal(size=(e.nodes_per_face, 3))
    s = ac.Surface(pts, [np.arange(e.nodes_per_face)], element)
    c, r = s.face_bounds
    xi = _domain_grid(e, 101)
    x = shape_functions(e, xi) @ pts
    assert np.linalg.norm(x - c[0], axis=1).max() <= r[0]


@pytest.mark.parametrize("element", ["tri6", "quad8", "quad9"])
def test_face_box_holds_the_face_and_fits_a_flat_one(element):
    """face_boxes of curved faces (the Bernstein control points' box cut by the Lebesgue box
    and the ball's cube) hold every point of the face, and on a flat face with its mid nodes
    halfway along the edges equal the corners' box (the Lebesgue box alone was up to 3x it)."""
    from arraycontact._surface import face_boxes

    rng = np.random.default_rng(1)
    e = get_element(element)
    nn = e.nodes_per_face
    xi = _domain_grid(e, 101)
    xe = _random_faces(e, rng, 200, 0.4)
    lo, hi = face_boxes(e, xe)
    x = np.einsum("gn,fnk->fgk", shape_functions(e, xi), xe)
    assert (x >= lo[:, None] - 1e-12).all() and (x <= hi[:, None] + 1e-12).all()
    # Near the face's own extent (the Lebesgue box and ball alone: 1.55-2.96x on average).
    assert ((hi - lo) / (x.max(1) - x.min(1))).mean() < 1.4
    flat = np.c_[3 * e.nodes, np.zeros(nn)][None]
    lo, hi = face_boxes(e, flat)
    np.testing.assert_allclose(lo[0], flat[0].min(0), atol=1e-12)
    np.testing.assert_allclose(hi[0], flat[0].max(0), atol=1e-12)


def test_global_ids_and_unused_points():
    pts = np.r_[CUBE_PTS, [[9.0, 9, 9]]]  # an interior / unused node
    s = ac.Surface(pts, CUBE_QUADS)
    assert s.element.name == "quad4" and np.array_equal(s.nodes, np.arange(8))
    assert np.allclose(s.node_normals[8], 0)


@pytest.mark.parametrize(
    "points, faces, element, match",
    [
        (np.zeros((3, 2)), [[0, 1, 2]], None, r"shape \[n, 3\]"),
        ([[0, 0, 0], [1, 0, 0], [0, np.nan, 0]], [[0, 1, 2]], None, "points row 2 is not finite"),
        ([[0, 0, 0], [1, 0, 0], [0, np.inf, 0]], [[0, 1, 2]], None, "points row 2"),
        (np.array([["a", "b", "c"]]), [[0, 0, 0]], None, "real numeric"),
        (np.eye(3), [[0, 1, 3]], None, "faces row 0 references a node outside"),
        (np.eye(3), [[0, 1, 2], [0, -1, 2]], None, "faces row 1 references"),
        (np.eye(3), [[0, 1, 1]], None, "faces row 0 repeats a node"),
        (np.eye(3), [[0, 1, 1.5]], None, "faces row 0 holds a non-integral"),
        (np.eye(3), [[0, 1, 2]], "quad4", "has 4 nodes per face"),
        (np.eye(3), [[0, 1, 2]], "hex8", "unknown element"),
        (np.eye(3), [0, 1, 2], None, r"shape \[n_faces"),
        (np.eye(3), [[0, 1]], None, "no element has 2 nodes"),
        (np.eye(3), np.array([["0", "1", "2"]]), None, "integer array"),
    ],
)
def test_bad_input(points, faces, element, match):
    with pytest.raises(ValueError, match=match):
        ac.Surface(points, faces, element)


def test_integral_floats_accepted_and_immutable():
    s = ac.Surface(np.eye(3), np.array([[0.0, 1.0, 2.0]]))
    assert s.faces.dtype == np.int64
    with pytest.raises(ValueError):
        s.points[0, 0] = 1.0
    with pytest.raises(AttributeError):
        s.points = np.zeros((3, 3))


@pytest.mark.parametrize("element", ["tri3", "quad4", "tri6"])
def test_empty_surface_is_valid(element):
    """No faces: every table empty (the edge table raised IndexError before)."""
    nn = {"tri3": 3, "quad4": 4, "tri6": 6}[element]
    s = ac.Surface(np.zeros((2, 3)), np.zeros((0, nn), int), element)
    assert s.n_faces == 0 and not s.closed and s.longest_edge == 0.0
    assert s.edges.shape == (0, 2) and s.edge_faces.shape == (0, 2) and len(s.boundary_nodes) == 0
    assert s.face_normals.shape == (0, 3) and s.face_bounds[1].shape == (0,)
    assert np.array_equal(s.node_normals, np.zeros((2, 3)))


def test_with_points_shares_the_connectivity_and_remakes_the_geometry():
    """A deformed configuration (with_points) keeps the connectivity's tables (the same
    arrays) and computes its geometry from its own points: every table as a fresh Surface's
    of those points."""
    m = scenes.rough_surfaces(2**10, seed=3).master.prepare()
    x = m.points + np.random.default_rng(0).normal(scale=0.2, size=m.points.shape)
    moved, fresh = m.with_points(x), ac.Surface(x, m.faces, m.element)
    assert moved._edge_table is m._edge_table and moved.node_faces is m.node_faces
    for name in ("nodes", "edges", "edge_faces", "boundary_nodes", "node_normals",
                 "face_normals", "longest_edge"):  # fmt: skip
        assert np.array_equal(getattr(moved, name), getattr(fresh, name)), name
    assert not np.allclose(moved.node_normals, m.node_normals)
    more = m.with_points(np.vstack([x, [[0.0, 0.0, 0.0]]]))  # an unused point more
    assert len(more.node_faces[0]) == len(x) + 2  # made again: its CSR spans every point


@pytest.mark.parametrize("element", ["tri3", "quad8"])
def test_prepare_in_threads_gives_the_lazy_tables(monkeypatch, element):
    """Surface.prepare (its tables in threads) leaves every table equal to the
    one a fresh Surface computes on first use, and the edges' corner pairs equal the faces'
    own (each local edge i from corner i to i + 1)."""
    import arraycontact._surface as surface

    monkeypatch.setattr(surface, "PREPARE_IN_THREADS", 1)  # threads at any size
    m = scenes.rough_surfaces(2**12, seed=2, element=element).master
    fresh = ac.Surface(m.points, m.faces, m.element)
    done = ac.Surface(m.points, m.faces, m.element).prepare()
    for name in ("nodes", "edges", "face_edges", "edge_faces", "boundary_nodes", "node_normals",
                 "face_normals", "longest_edge"):  # fmt: skip
        assert np.array_equal(getattr(done, name), getattr(fresh, name)), name
    for a, b in zip(done.node_faces + done.face_bounds, fresh.node_faces + fresh.face_bounds):
        assert np.array_equal(a, b)
    k = m.element.n_corners
    corners = np.sort(np.stack([m.faces[:, :k], np.roll(m.faces[:, :k], -1, 1)], -1), -1)
    assert np.array_equal(done.edges[done.face_edges], corners)


@pytest.mark.parametrize("end", [1, 2, 1 << 16, (1 << 16) + 1, 1 << 33, 1 << 40])
def test_stable_order_is_a_stable_argsort(end):
    """The radix passes give NumPy's stable argsort, ties in input order, whatever the keys'
    width (one pass up to 16 bits, more beyond)."""
    from arraycontact._surface import _stable_order

    rng = np.random.default_rng(end % 1000)
    for n in (0, 1, 1000, 70000):
        keys = rng.integers(0, end, n, dtype=np.int64)
        keys[: n // 2] = keys[n // 2 : 2 * (n // 2)]  # many equal keys
        assert np.array_equal(_stable_order(keys, end), np.argsort(keys, kind="stable"))


@pytest.mark.parametrize("element", ["tri3", "quad4", "tri6", "quad8", "quad9"])
def test_normal_boxes_hold_the_normals_and_fit_a_flat_face(element):
    """normal_boxes (self-contact's pruning: a face is nowhere facing n where the box's least
    n . v is not negative): for random faces and directions, wherever the box says so every
    sampled normal x_xi x x_eta agrees; a flat face's box is its normal alone (quad8 and quad9
    had the box of all unit vectors)."""
    from arraycontact._surface import min_dot, normal_boxes

    rng = np.random.default_rng(2)
    e = get_element(element)
    nn = e.nodes_per_face
    xi = _domain_grid(e, 41)
    xe = _random_faces(e, rng, 100, 0.15)
    lo, hi = normal_boxes(e, xe)
    _, dx = interpolate(e, xe[:, None], xi[None])
    n = np.cross(dx[..., 0], dx[..., 1])  # [F, samples, 3]
    v = rng.normal(size=(500, 3))
    says = min_dot(v[None], lo[:, None], hi[:, None]) >= 0  # [F, directions]
    assert says.any() and (~says).any()
    worst = np.einsum("fsk,dk->fds", n, v).min(-1)
    assert (worst[says] >= -1e-9).all()
    flat = np.c_[2 * e.nodes, np.zeros(nn)][None]
    lo, hi = normal_boxes(e, flat)
    np.testing.assert_allclose(lo[0], [0, 0, 1], atol=1e-12)
    np.testing.assert_allclose(hi[0], [0, 0, 1], atol=1e-12)
