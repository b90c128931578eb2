"""Closest point on one face: Voronoi closed form, active-set and SQP methods (seed 003)."""

import numpy as np
import pytest

import arraycontact as ac
from arraycontact._elements import get_element, shape_functions
from arraycontact._geometry import (closest_point_face, closest_point_triangle,
                                    start_option_one, start_option_two)
from arraycontact._projection import _best_of_starts


def _face(element, noise, seed):
    e = get_element(element)
    rng = np.random.default_rng(seed)
    pts = np.c_[e.nodes, np.zeros(e.nodes_per_face)] + noise * rng.normal(size=(e.nodes_per_face, 3))
    return e, pts, ac.Surface(pts, [np.arange(e.nodes_per_face)], element)


@pytest.mark.parametrize("element", ["quad4", "tri6", "quad8", "quad9"])
@pytest.mark.parametrize("noise", [0.1, 0.3])
def test_best_of_starts_is_the_global_closest_point(element, noise):
    """Curved and distorted faces, points within about an element size: the detection's
    multi-start Newton equals the brute-force reference, and its point lies on the face.

    Known limit (the quadratic-faces issue stays open on it): on very distorted quadratic
    faces (nodes moved by 0.3 element sizes) a few points in 1000 have a closer local
    minimum that none of the starts reaches."""
    e, pts, s = _face(element, noise, seed=int(noise * 10))
    rng = np.random.default_rng(5)
    q = np.c_[rng.uniform(-1.3, 1.3, (2000, 2)), rng.uniform(-0.8, 0.8, 2000)]
    if e.kind == "tri":
        q[:, :2] = (q[:, :2] + 1.3) / 2.6 * 1.4 - 0.2
    ref = ac.reference.closest_points(q, s)
    xe = np.broadcast_to(pts, (len(q),) + pts.shape)
    xi, feat, loc, conv = _best_of_starts(np, e, q, xe, iterations=20, tol=1e-12)
    x = shape_functions(e, xi) @ pts
    d = np.linalg.norm(x - q, axis=1)
    assert (xi @ e.constraints_a.T - e.constraints_b >= -1e-14).all()  # on the face
    missed = d - ref.distance > 1e-10
    assert (d - ref.distance >= -1e-12).all()  # never closer than the reference
    if noise <= 0.1 or e.linear:
        assert conv.all() and not missed.any()
    else:
        assert missed.mean() <= 0.003 and conv.mean() >= 0.998
    # The feature agrees wherever the reference's is unambiguous.
    assert (feat == ref.feature).mean() > 0.99


@pytest.mark.parametrize("method", ["active_set", "sqp"])
@pytest.mark.parametrize("element", ["tri3", "quad4"])
def test_linear_faces_both_methods_both_starts(method, element):
    e, pts, s = _face(element, 0.2, seed=1)
    rng = np.random.default_rng(2)
    q = 1.5 * rng.normal(size=(3000, 3))
    ref = ac.reference.closest_points(q, s)
    xe = np.broadcast_to(pts, (len(q),) + pts.shape)
    for start in (start_option_one, start_option_two):
        xi, feat, loc, conv, it, kkt = closest_point_face(
            e, q, xe, start(e, q, xe), iterations=30, tol=1e-12, method=method)
        d = np.linalg.norm(shape_functions(e, xi) @ pts - q, axis=1)
        assert conv.all() and (kkt <= 1e-12).all() and (it >= 1).all()
        assert np.abs(d - ref.distance).max() <= 1e-10
        assert (feat == ref.feature).mean() > 0.995


def test_vertex_regions_take_one_iteration():
    """Seed 003 Fig. 4: with start I, points in a corner's Voronoi region need one iteration."""
    e, pts, s = _face("tri3", 0.0, seed=0)
    q = np.array([[-1.0, -1.0, 0.5], [2.0, -0.5, 0.0], [-0.3, 2.0, 1.0]])
    xe = np.broadcast_to(pts, (3, 3, 3))
    for method in ("active_set", "sqp"):
        *_, conv, it, _ = closest_point_face(e, q, xe, start_option_one(e, q, xe),
                                             iterations=10, tol=1e-12, method=method)
        assert conv.all() and (it == 1).all()


def test_voronoi_triangle_regions():
    a, b, c = np.zeros(3), np.array([1.0, 0, 0]), np.array([0, 1.0, 0])
    p = np.array([[0.2, 0.2, 1], [-1, -1, 0], [2, -0.1, 0], [0.5, -1, 0], [1, 1, 0], [-1, 0.5, 0]])
    xi, feat, loc = closest_point_triangle(p, a, b, c)
    assert list(feat) == [0, 2, 2, 1, 1, 1] and list(loc) == [-1, 0, 1, 0, 1, 2]
    assert np.allclose(xi, [[0.2, 0.2], [0, 0], [1, 0], [0.5, 0], [0.5, 0.5], [0, 0.5]])


def test_degenerate_triangles_do_not_divide_by_zero():
    a = np.zeros((3, 3))
    b = np.array([[1.0, 0, 0], [0, 0, 0], [2.0, 0, 0]])
    c = np.array([[2.0, 0, 0], [0, 0, 0], [1.0, 0, 0]])  # collinear, coincident, collinear
    p = np.array([[1.5, 1.0, 0], [0.3, 0.4, 0], [3.0, 0, 0]])
    with np.errstate(all="raise"):
        xi, feat, loc = closest_point_triangle(p, a, b, c)
    x = a + xi[:, :1] * (b - a) + xi[:, 1:] * (c - a)
    assert np.allclose(np.linalg.norm(x - p, axis=1), [1.0, 0.5, 1.0])
