"""The brute-force oracle against closed forms and dense sampling."""

import numpy as np
import pytest
from test_surface import cube

import arraycontact as ac
from arraycontact._elements import get_element, shape_functions
from arraycontact._geometry import closest_point_triangle


def _dense(e, pts, q, m):
    g = np.linspace(0, 1, m) if e.kind == "tri" else np.linspace(-1, 1, m)
    xi = np.stack(np.meshgrid(g, g, indexing="ij"), -1).reshape(-1, 2)
    if e.kind == "tri":
        xi = xi[xi.sum(1) <= 1 + 1e-12]
    x = shape_functions(e, xi) @ pts
    return np.array([np.linalg.norm(x - p, axis=1).min() for p in q])


@pytest.mark.parametrize("element", ["tri3", "quad4", "tri6", "quad8", "quad9"])
def test_against_dense_sampling(element):
    """Sampling never beats the reference, and its excess shrinks as sampling gets denser."""
    rng = np.random.default_rng(1)
    e = get_element(element)
    for _ in range(3):
        pts = np.c_[e.nodes, np.zeros(e.nodes_per_face)] + 0.3 * rng.normal(
            size=(e.nodes_per_face, 3)
        )
        s = ac.Surface(pts, [np.arange(e.nodes_per_face)], element)
        q = 1.5 * rng.normal(size=(60, 3))
        d = ac.reference.closest_points(q, s).distance
        coarse, fine = _dense(e, pts, q, 41), _dense(e, pts, q, 321)
        assert (coarse >= d - 1e-12).all() and (fine >= d - 1e-12).all()
        assert (fine - d).max() < 0.25 * (coarse - d).max() + 1e-12
        assert (fine - d).max() < 2e-3


def test_square_closed_forms():
    s = ac.Surface([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], [[0, 1, 2, 3]], "quad4")
    q = np.array(
        [
            [0.3, 0.6, 0.5],  # above the face
            [0.3, 0.6, -0.2],  # below it: negative gap
            [1.5, 0.5, 0.0],  # beside edge x = 1
            [-1.0, -2.0, 2.0],  # beyond the corner (0, 0)
            [1.0, 0.4, 0.0],
        ]
    )  # exactly on an edge
    r = ac.reference.closest_points(q, s)
    assert np.allclose(r.distance, [0.5, 0.2, 0.5, 3.0, 0.0], atol=1e-14)
    assert np.allclose(r.gap, [0.5, -0.2, 0.5, 3.0, 0.0], atol=1e-14)
    assert list(r.feature) == [
        ac.Feature.FACE,
        ac.Feature.FACE,
        ac.Feature.EDGE,
        ac.Feature.VERTEX,
        ac.Feature.EDGE,
    ]
    assert np.allclose(r.point[2], [1, 0.5, 0]) and np.allclose(r.point[3], 0)
    assert np.allclose(r.xi[0], [-0.4, 0.2])
    assert np.allclose(r.normal[:2], [0, 0, 1]) and np.allclose(
        r.normal[3], np.array([-1, -2, 2]) / 3.0
    )


def test_cube_signed_distance():
    rng = np.random.default_rng(2)
    q = rng.uniform(-0.5, 1.5, (500, 3))
    r = ac.reference.closest_points(q, cube())
    inside = ((q > 0) & (q < 1)).all(1)
    outside_d = np.linalg.norm(np.maximum(np.maximum(-q, q - 1), 0), axis=1)
    inside_d = np.minimum(q, 1 - q).min(1)
    assert np.allclose(r.distance, np.where(inside, inside_d, outside_d), atol=1e-14)
    assert np.allclose(r.gap, np.where(inside, -inside_d, outside_d), atol=1e-14)


def test_ties_go_to_the_smallest_face_id():
    # A point above the shared vertex of 6 triangles (a hexagonal fan).
    a = np.linspace(0, 2 * np.pi, 7)[:-1]
    pts = np.r_[[[0, 0, 0]], np.c_[np.cos(a), np.sin(a), 0 * a]]
    faces = np.array([[0, 1 + i, 1 + (i + 1) % 6] for i in range(6)])[[3, 1, 5, 0, 2, 4]]
    s = ac.Surface(pts, faces, "tri3")
    r = ac.reference.closest_points([[0, 0, 1.0]], s)
    assert r.face[0] == 0 and r.feature[0] == ac.Feature.VERTEX and r.distance[0] == 1.0


def test_voronoi_and_reference_agree_on_random_triangles():
    """Two independent closed forms: Voronoi regions (detection) and projection + edges."""
    rng = np.random.default_rng(3)
    tri = rng.normal(size=(2000, 3, 3))
    q = 2 * rng.normal(size=(2000, 3))
    xi, feat, _ = closest_point_triangle(q, tri[:, 0], tri[:, 1], tri[:, 2])
    x = tri[:, 0] + xi[:, :1] * (tri[:, 1] - tri[:, 0]) + xi[:, 1:] * (tri[:, 2] - tri[:, 0])
    for k in range(0, 2000, 500):
        s = ac.Surface(tri[k : k + 500].reshape(-1, 3), np.arange(1500).reshape(-1, 3), "tri3")
        # one point per triangle: compare against that triangle alone
        from arraycontact.reference import _closest_on_faces

        _, d2 = _closest_on_faces(s.element, q[k : k + 500], tri[k : k + 500])
        assert np.allclose(
            np.linalg.norm(x[k : k + 500] - q[k : k + 500], axis=1), np.sqrt(d2), atol=1e-12
        )


def test_chunking_does_not_change_the_answer():
    from arraycontact import scenes

    sc = scenes.rough_surfaces(2**8, gap=0.2)
    a = ac.reference.closest_points(sc.slave, sc.master)
    b = ac.reference.closest_points(sc.slave, sc.master, chunk_points=7, chunk_faces=13)
    assert np.array_equal(a.face, b.face) and np.allclose(a.distance, b.distance, atol=0)


def test_bad_input():
    with pytest.raises(ValueError, match="points row 1 is not finite"):
        ac.reference.closest_points([[0, 0, 0], [np.nan, 0, 0]], cube())
    with pytest.raises(ValueError, match="Surface"):
        ac.reference.closest_points([[0, 0, 0]], np.eye(3))
