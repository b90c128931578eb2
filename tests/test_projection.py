"""Closest point on one face: Voronoi closed form, active-set and SQP methods (seed 003)."""

import numpy as np
import pytest

import arraycontact as ac
from arraycontact._elements import get_element, interpolate, shape_functions
from arraycontact._geometry import (
    closest_point_edge,
    closest_point_face,
    closest_point_triangle,
    start_option_one,
    start_option_two,
    surely_convex,
    triangle_distance,
)
from arraycontact._projection import _best_of_starts, distance_bounds, project, project_kept
from arraycontact._select import select_closest
from arraycontact.reference import _closest_on_faces


def _face(element, noise, seed):
    e = get_element(element)
    rng = np.random.default_rng(seed)
    pts = np.c_[e.nodes, np.zeros(e.nodes_per_face)] + noise * rng.normal(
        size=(e.nodes_per_face, 3)
    )
    return e, pts, ac.Surface(pts, [np.arange(e.nodes_per_face)], element)


def _folded(e, pts):
    """The smallest cosine between the face's normal anywhere and its mean normal: negative
    where the face folds over itself (a negative Jacobian, which FE codes reject)."""
    s = np.linspace(0, 1, 41) if e.kind == "tri" else np.linspace(-1, 1, 41)
    g = np.stack(np.meshgrid(s, s), -1).reshape(-1, 2)
    g = g[g.sum(1) <= 1] if e.kind == "tri" else g
    _, dx = interpolate(e, np.broadcast_to(pts, (len(g),) + pts.shape), g)
    n = np.cross(dx[..., 0], dx[..., 1])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    return (n @ (n.mean(0) / np.linalg.norm(n.mean(0)))).min()


def _points_near(e, n, seed):
    rng = np.random.default_rng(seed)
    q = np.c_[rng.uniform(-1.3, 1.3, (n, 2)), rng.uniform(-0.8, 0.8, n)]
    if e.kind == "tri":
        q[:, :2] = (q[:, :2] + 1.3) / 2.6 * 1.4 - 0.2
    return q


def _check_face(e, pts, q):
    s = ac.Surface(pts, [np.arange(e.nodes_per_face)], e.name)
    ref = ac.reference.closest_points(q, s)
    xe = np.broadcast_to(pts, (len(q),) + pts.shape)
    xi, feat, loc, conv = _best_of_starts(np, e, q, xe, iterations=20, tol=1e-12)
    d = np.linalg.norm(shape_functions(e, xi) @ pts - q, axis=1)
    assert (xi @ e.constraints_a.T - e.constraints_b >= -1e-14).all()  # on the face
    assert (d - ref.distance >= -1e-12).all()  # never closer than the reference
    return d - ref.distance > 1e-10, conv, feat == ref.feature


@pytest.mark.parametrize("element", ["quad4", "tri6", "quad8", "quad9"])
def test_curved_and_distorted_faces_equal_the_reference(element):
    """Random faces: nodes moved by 0.1 and 0.3 element sizes, and mid-edge nodes lifted by
    0.35 out of the plane (strongly curved), points within about an element size. Every face
    that does not fold over itself: the detection's projection (multi-start Newton plus the
    exact edges) equals the brute-force reference within 1e-10, on the face, converged."""
    e = get_element(element)
    rng = np.random.default_rng(11)
    done = 0
    for trial in range(40):
        noise = (0.1, 0.3)[trial % 2]
        pts = np.c_[e.nodes, np.zeros(e.nodes_per_face)] + noise * rng.normal(
            size=(e.nodes_per_face, 3)
        )
        pts[e.n_corners :, 2] += 0.35 * rng.choice([-1.0, 1.0], e.nodes_per_face - e.n_corners)
        if _folded(e, pts) <= 0:
            continue
        missed, conv, same_feature = _check_face(e, pts, _points_near(e, 300, trial))
        assert not missed.any() and conv.all()
        assert same_feature.mean() > 0.99  # where the reference's feature is unambiguous
        done += 1
        if done == 3:
            break
    assert done == 3


@pytest.mark.parametrize("element", ["tri6", "quad8", "quad9"])
def test_folded_faces_miss_rarely(element):
    """Known limit: on faces that fold over themselves (nodes moved by 0.3 element sizes until
    the normal reverses) an interior minimum can lie in a basin no start reaches. Bounded:
    at most 1 point in 1000 (measured: 2 in 72,000 over tri6, quad8 and quad9)."""
    e = get_element(element)
    rng = np.random.default_rng(3)
    misses = total = 0
    while total < 1000:
        pts = np.c_[e.nodes, np.zeros(e.nodes_per_face)] + 0.3 * rng.normal(
            size=(e.nodes_per_face, 3)
        )
        if _folded(e, pts) > -0.3:
            continue
        missed, conv, _ = _check_face(e, pts, _points_near(e, 500, total))
        misses += missed.sum()
        total += len(missed)
    assert misses <= 0.001 * total


@pytest.mark.parametrize("element", ["quad4", "tri6", "quad8", "quad9"])
def test_closest_point_edge_is_the_global_minimum_on_the_edge(element):
    """The cubic-root edge solver against dense sampling of each edge (no tolerance to tune:
    the solver may only be closer than the sampled minimum, never farther)."""
    e = get_element(element)
    rng = np.random.default_rng(8)
    for _ in range(4):
        pts = np.c_[e.nodes, np.zeros(e.nodes_per_face)] + 0.5 * rng.normal(
            size=(e.nodes_per_face, 3)
        )
        q = rng.normal(size=(300, 3))
        xe = np.broadcast_to(pts, (len(q),) + pts.shape)
        ts = np.linspace(0, 1, 5001)
        t_all, d_all = closest_point_edge(e, q, xe)
        for k in range(e.n_corners):
            t, d = t_all[:, k], d_all[:, k]
            a, b = e.edge_nodes[k, :2]
            x = shape_functions(e, e.nodes[a] + ts[:, None] * (e.nodes[b] - e.nodes[a])) @ pts
            dense = ((q[:, None] - x[None]) ** 2).sum(-1).min(1)
            assert (d <= dense + 1e-13).all() and (t >= 0).all() and (t <= 1).all()
            xt = shape_functions(e, e.nodes[a] + t[:, None] * (e.nodes[b] - e.nodes[a])) @ pts
            assert np.allclose(((xt - q) ** 2).sum(-1), d, rtol=1e-12, atol=1e-14)


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
            e, q, xe, start(e, q, xe), iterations=30, tol=1e-12, method=method
        )
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
        *_, conv, it, _ = closest_point_face(
            e, q, xe, start_option_one(e, q, xe), iterations=10, tol=1e-12, method=method
        )
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


def test_triangle_distance_is_the_reference_distance():
    """The per-coordinate distance the JAX search measures its candidates with: the brute-force
    reference's, on random, sliver, collinear and coincident triangles, from points near and
    far, in every region (and the tuple layout: one array per coordinate)."""
    rng = np.random.default_rng(11)
    n = 4000
    tri = rng.normal(size=(n, 3, 3))
    tri[0::7, 2] = tri[0::7, 0] + 0.5 * (tri[0::7, 1] - tri[0::7, 0])  # collinear
    tri[1::7, 1:] = tri[1::7, :1]  # coincident corners
    tri[2::7, 2] = tri[2::7, 1] + 1e-6 * rng.normal(size=(len(tri[2::7]), 3))  # slivers
    scale = 10.0 ** rng.uniform(-3, 1, n)[:, None]
    p = tri.mean(1) + scale * rng.normal(size=(n, 3))
    p[3::7] = tri[3::7, 0]  # on a corner
    x0 = tri[:, 0]
    cols = [[a[:, i] for i in range(3)] for a in (p - x0, tri[:, 1] - x0, tri[:, 2] - x0)]
    with np.errstate(all="raise"):
        got = triangle_distance(*cols)
    # project's closest point, to rounding
    xi, _, _ = closest_point_triangle(p - x0, 0 * x0, tri[:, 1] - x0, tri[:, 2] - x0)
    x = x0 + xi[:, :1] * (tri[:, 1] - x0) + xi[:, 1:] * (tri[:, 2] - x0)
    np.testing.assert_allclose(got, np.linalg.norm(p - x, axis=1), rtol=1e-12, atol=1e-14)
    # The reference's distance: to rounding, but on slivers (whose interior solution loses
    # digits to cancellation, as project's does) to a millionth of the longest edge.
    _, d2 = _closest_on_faces(get_element("tri3"), p, tri)
    edge = np.linalg.norm(tri - np.roll(tri, 1, 1), axis=-1).max(1)
    err = np.abs(got - np.sqrt(d2))
    assert (err <= 1e-6 * edge).all()
    sliver = np.zeros(n, bool)
    sliver[2::7] = True
    np.testing.assert_allclose(got[~sliver], np.sqrt(d2[~sliver]), rtol=1e-10, atol=1e-12)


def test_select_over_slots_equals_the_segment_reduction():
    """The selection over K slots a slave (the JAX search's layout, reduced column by column):
    the pair the segment reductions pick, with the tie rule (within `tie` of the smallest
    distance, the smallest face id, then the first pair), empty slots and slaves without any."""
    rng = np.random.default_rng(12)
    n, k, tie = 500, 7, 0.05
    dist = rng.choice([1.0, 1.02, 1.04, 1.1, 2.0], size=n * k) + rng.uniform(0, 1e-3, n * k)
    face = rng.integers(0, 20, n * k).astype(np.int32)
    valid = rng.uniform(size=n * k) < 0.6
    valid[: 5 * k] = False  # slaves without a candidate
    slave = np.repeat(np.arange(n), k)
    want = select_closest(np, n, slave, face, valid, dist, tie)
    got = select_closest(np, n, slave, face, valid, dist, tie, slots=k)
    assert np.array_equal(got[1], want[1]) and got[1].sum() < n
    assert np.array_equal(got[0], want[0])


@pytest.mark.parametrize("element", ["quad4", "tri6", "quad8", "quad9"])
def test_distance_bounds_hold_the_reference_distance(element):
    """The bounds that decide which pairs a detection projects hold the brute-force
    reference's distance between them, on distorted and curved faces at every distance."""
    e = get_element(element)
    rng = np.random.default_rng(5)
    for trial in range(6):
        pts = np.c_[e.nodes, np.zeros(e.nodes_per_face)] + (0.05, 0.3)[trial % 2] * rng.normal(
            size=(e.nodes_per_face, 3)
        )
        q = _points_near(e, 200, trial) * (1, 1, 4)[trial % 3]
        face = np.arange(e.nodes_per_face)[None]
        ref = ac.reference.closest_points(q, ac.Surface(pts, face, e.name))
        ids = np.zeros(len(q), np.int64)
        lo, hi = distance_bounds(np, e, q, pts, face, np.arange(len(q)), ids)
        assert (lo <= ref.distance + 1e-12).all() and (hi >= ref.distance - 1e-12).all()


def test_quad4_bounds_are_exact_on_a_flat_parallelogram():
    """No twist (x0 - x1 + x2 - x3 = 0): the bilinear face is its two triangles, so both
    bounds are the distance itself (the closed form of a point above a flat face)."""
    e = get_element("quad4")
    pts = np.array([[0.0, 0, 0], [2, 0.5, 0], [3, 2.5, 0], [1, 2, 0]])
    q = np.array([[1.5, 1.2, 0.7], [1.5, 1.2, -2.0], [10.0, 1.0, 0.0]])
    lo, hi = distance_bounds(np, e, q, pts, np.arange(4)[None], np.arange(3), np.zeros(3, int))
    assert np.allclose(lo, hi) and np.allclose(lo[:2], [0.7, 2.0])


@pytest.mark.parametrize("size", [64, 8])
def test_project_kept_equals_project_on_the_kept_pairs(size):
    """JAX: the kept pairs gathered into `size` rows, once (room for them) or several times
    (size 8): both give JAX `project`'s answers on the kept pairs, as NumPy's gather gives
    NumPy's: the closest point on every kept pair, xi, feature and local id on those whose
    four nodes differ (random node ids make degenerate quads too, with coincident corners
    and edges, whose xi and edge ids are ambiguous: a rounding names another)."""
    import jax
    import jax.numpy as jnp

    e = get_element("quad4")
    rng = np.random.default_rng(2)
    nodes = np.c_[rng.uniform(0, 4, (40, 2)), 0.3 * rng.normal(size=40)]
    faces = rng.integers(0, 40, (30, 4))
    slave, face = rng.integers(0, 50, 96), rng.integers(0, 30, 96)
    x = rng.normal(size=(50, 3)) + [2, 2, 0]
    keep = rng.random(96) < 0.3
    assert 8 < keep.sum() <= 64
    kw = dict(iterations=12, tol=1e-10)
    ref = project(np, e, x, nodes, faces, slave, face, **kw)
    distinct = (np.diff(np.sort(faces, 1), axis=1) > 0).all(1)[face]
    with jax.enable_x64(True):
        args = [jnp.asarray(a) for a in (x, nodes, faces, slave, face, keep)]
        got = project_kept(jnp, e, *args, size, **kw)
    for k, (r, g) in enumerate(zip(ref, got)):
        rows = keep if k in (1, 2) else keep & distinct  # (point and slave - point)
        assert np.allclose(np.asarray(g)[rows], r[rows], atol=1e-9)
    got = project_kept(np, e, x, nodes, faces, slave, face, keep, None, **kw)
    for r, g in zip(ref, got):
        assert np.allclose(g[keep], r[keep], atol=1e-12)


@pytest.mark.parametrize(
    "spec, a, b",
    [
        ("...ka,...k->...a", (5, 7, 3, 2), (5, 7, 3)),
        ("...ka,...kb->...ab", (5, 3, 2), (5, 3, 2)),
        ("cn,...nk->...ck", (4, 9), (6, 9, 3)),
        ("c,...ck->...k", (4,), (2, 5, 4, 3)),
        ("etn,...nk->...etk", (3, 3, 9), (7, 9, 3)),
        ("...j,ja->...a", (8, 4), (4, 2)),
        ("cn,pnk->pck", (25, 4), (10, 4, 3)),
        ("...k,mk->...m", (3, 5, 2), (4, 2)),
    ],
)
def test_fused_einsum_equals_numpy(spec, a, b):
    """The JAX spelling of the small contractions (a broadcast product and a sum, which XLA
    fuses) gives np.einsum's values and shapes."""
    import jax
    import jax.numpy as jnp

    from arraycontact._xp import einsum

    rng = np.random.default_rng(0)
    x, y = rng.normal(size=a), rng.normal(size=b)
    with jax.enable_x64(True):
        got = np.asarray(einsum(jnp, spec, jnp.asarray(x), jnp.asarray(y)))
    want = np.einsum(spec, x, y)
    assert got.shape == want.shape and np.allclose(got, want, rtol=1e-13, atol=1e-13)


def test_unfinished_pairs_go_on_gathered_with_the_same_answers():
    """NumPy: once at most 1/8 of 1024 or more pairs still iterate, they go on gathered. Each
    pair's arithmetic is its own, so the answers equal those of calls too small to gather
    (chunks of 500 pairs), bit for bit."""
    e = get_element("quad8")
    rng = np.random.default_rng(4)
    P = 3000
    pts = np.c_[e.nodes, np.zeros(e.nodes_per_face)]
    xe = pts[None] + rng.normal(size=(P, e.nodes_per_face, 3)) * rng.choice([0.05, 0.3], (P, 1, 1))
    r = rng.normal(size=(P, 3)) * [1.2, 1.2, 0.6]
    xi0 = start_option_one(e, r, xe)
    kw = dict(iterations=20, tol=1e-12)
    whole = closest_point_face(e, r, xe, xi0, **kw)
    left = [(whole[4] > k).sum() for k in range(kw["iterations"])]  # still iterating after k
    assert any(0 < 8 * n <= P for n in left)  # so they were gathered
    parts = [
        closest_point_face(e, r[i : i + 500], xe[i : i + 500], xi0[i : i + 500], **kw)
        for i in range(0, P, 500)
    ]
    for a, b in zip(whole, zip(*parts)):
        assert np.array_equal(a, np.concatenate(b))


def _quads(P, seed):
    """Flat, warped and strongly warped quads, collapsed edges (rows 0::11) and coincident
    corners (1::11), and points near and far, some on a corner (2::11)."""
    e = get_element("quad4")
    rng = np.random.default_rng(seed)
    xe = np.c_[e.nodes, np.zeros(4)][None] + rng.normal(scale=0.3, size=(P, 4, 3))
    xe[:, :, 2] += rng.choice([0.0, 0.3, 1.5], (P, 1)) * rng.normal(size=(P, 4))
    xe[0::11, 1] = xe[0::11, 0]
    xe[1::11, 1:] = xe[1::11, :1]
    r = rng.normal(scale=1.5, size=(P, 3))
    r[2::11] = xe[2::11, 3]
    proper = np.ones(P, bool)
    proper[0::11] = proper[1::11] = False
    return e, xe, r, proper


def _quad_distance(e, xe, r, xi):
    x = np.einsum("pn,pnk->pk", shape_functions(e, xi), xe)
    return np.linalg.norm(x - r, axis=1)


def test_bilinear_best_of_starts_makes_the_generic_choices():
    """JAX's quad4 `_best_of_starts` (`bilinear_best_of_starts`: the starts, the convexity
    bounds, the lattice start and the edges on one array a coordinate) against the generic
    code in NumPy: the same features, local ids and convergence on proper quads, xi within the
    KKT tolerance's reach, the same distance everywhere; warped quads take the lattice start
    (both branches of its cond run)."""
    import jax
    import jax.numpy as jnp

    e, xe, r, proper = _quads(6000, 22)
    kw = dict(iterations=12, tol=1e-10)
    want = _best_of_starts(np, e, r, xe, **kw)
    assert not surely_convex(e, r, xe).all()  # the lattice start's branch
    with jax.enable_x64(True):
        f = jax.jit(lambda a, b: _best_of_starts(jnp, e, a, b, **kw))
        got = [np.asarray(g) for g in f(r, xe)]
        flat = [np.asarray(g) for g in f(r[proper][:100], xe[proper][:100] * [1, 1, 0])]
    assert np.array_equal(got[1][proper], want[1][proper])
    assert np.array_equal(got[2][proper], want[2][proper])
    assert np.array_equal(got[3][proper], want[3][proper])
    assert np.abs(got[0] - want[0])[proper].max() < 1e-8
    np.testing.assert_allclose(
        _quad_distance(e, xe, r, got[0]), _quad_distance(e, xe, r, want[0]), rtol=1e-10, atol=1e-12
    )
    # Flat quads: every pair proven convex (the one-start branch)
    flat_want = _best_of_starts(np, e, r[proper][:100], xe[proper][:100] * [1, 1, 0], **kw)
    assert np.array_equal(flat[1], flat_want[1]) and np.abs(flat[0] - flat_want[0]).max() < 1e-8


def test_bilinear_solver_takes_the_generic_steps():
    """JAX's quad4 solver (`_closest_point_bilinear`: the active-set method on one array a
    coordinate, closed-form tangents) against the generic `closest_point_face` (NumPy) from
    start option I: the same features and local ids, the same convergence and xi within the
    KKT tolerance's reach on proper quads, and the same distance to rounding everywhere (where
    an edge is collapsed, the parametrisation is singular: a rounding can cost a pair its
    convergence within the iterations, not its distance)."""
    import jax
    import jax.numpy as jnp

    from arraycontact._geometry import _closest_point_bilinear

    e, xe, r, proper = _quads(6000, 21)
    xi0 = start_option_one(e, r, xe)
    kw = dict(iterations=12, tol=1e-10)
    want = closest_point_face(e, r, xe, xi0, **kw)
    with jax.enable_x64(True):
        got = jax.jit(lambda a, b, c: _closest_point_bilinear(a, b, c, xp=jnp, **kw))(r, xe, xi0)
        got = [np.asarray(g) for g in got]
    assert np.array_equal(got[1], want[1]) and np.array_equal(got[2], want[2])
    assert np.array_equal(got[3][proper], want[3][proper]) and want[3][proper].all()
    assert np.abs(got[0] - want[0])[proper].max() < 1e-8
    np.testing.assert_allclose(
        _quad_distance(e, xe, r, got[0]), _quad_distance(e, xe, r, want[0]), rtol=1e-10, atol=1e-12
    )


def _start_one_on_the_face(backend, e, r, xe, iterations, tol):
    """Start I's active set (closest_point_face) on the back end's own code: NumPy, JAX
    (jitted, float64) or Warp's exported @wp.func (float64, on the test device). xi, converged."""
    start = start_option_one(e, r, xe)
    kw = dict(iterations=iterations, tol=tol)
    if backend == "numpy":
        out = closest_point_face(e, r, xe, start, **kw)
        return out[0], out[3]
    if backend == "jax":
        import jax
        import jax.numpy as jnp

        with jax.enable_x64(True):
            f = jax.jit(lambda a, b, c: closest_point_face(e, a, b, c, xp=jnp, **kw)[::3])
            return tuple(np.asarray(v) for v in f(r, xe, start))
    import arraycontact_warp as acw
    import warp as wp

    g = acw.geometry("float64")
    device = "cuda:0" if wp.get_cuda_device_count() else "cpu"

    # (A compact signature: see test_warp's test_exported_geometry_in_a_user_kernel.)
    # fmt: off
    @wp.kernel(module="unique")
    def face(el: g.Element, pts: wp.array2d(dtype=wp.vec3d), q: wp.array(dtype=wp.vec3d),
             xi0: wp.array(dtype=wp.vec2d), xi_out: wp.array(dtype=wp.vec2d),
             ok: wp.array(dtype=int)):
        i = wp.tid()
        xn = g.FaceNodes()
        for k in range(pts.shape[1]):
            xn = g.set_node(xn, k, pts[i, k])
        xi, feature, local, converged = g.closest_point_face(
            el, q[i], xn, xi0[i], iterations, wp.float64(tol))
        xi_out[i] = xi
        ok[i] = converged
    # fmt: on

    n = len(r)
    xi = wp.zeros(n, dtype=wp.vec2d, device=device)
    ok = wp.zeros(n, dtype=int, device=device)
    args = [wp.array(xe, dtype=wp.vec3d, device=device), wp.array(r, dtype=wp.vec3d, device=device)]
    args += [wp.array(start, dtype=wp.vec2d, device=device)]
    wp.launch(face, n, inputs=[g.element_data(e.name, device), *args], outputs=[xi, ok],
              device=device)  # fmt: skip
    return xi.numpy(), ok.numpy().astype(bool)


@pytest.mark.parametrize("backend", ["numpy", "jax", "warp"])
def test_start_one_leaves_an_edge_into_a_convex_curved_face(backend):
    """The crumpled tri6 sheet's node 3479 (2^13 nodes) against its face 668: `curved_convex`
    proves the distance strictly convex there. Start I's active set reaches the edge s = 0 and
    must leave it (a negative multiplier): the Newton step points into the face, but its
    second-order correction pointed back out, so the constraint was kept and the iterate stayed
    1.15 from the closest point, unconverged at any iteration count, on every back end (until
    the correction had to stay on the face). Start I now converges to the reference's 0.3605;
    a detection (which also falls back to every start where start I does not converge) too."""
    from arraycontact import scenes
    from arraycontact._geometry import curved_convex
    from arraycontact.reference import closest_points

    m = scenes.crumpled_sheet(2**13, element="tri6").master
    xe = m.points[m.faces[668]]
    r = m.points[m.nodes[3479]][None]
    e = m.element
    assert curved_convex(e, r, xe[None])[0]
    face = ac.Surface(xe, [np.arange(6)], "tri6")
    want = closest_points(r, face).distance[0]
    assert abs(want - 0.3605) < 1e-4
    xi, converged = _start_one_on_the_face(backend, e, r, xe[None], iterations=20, tol=1e-12)
    assert converged[0]
    got = np.linalg.norm(shape_functions(e, xi)[0] @ xe - r[0])
    assert abs(got - want) < 1e-9
    c = ac.detect(r, face, backend=backend, d_max=1.0, dtype="float64")
    assert c.active[0] and abs(c.distance[0] - want) < 1e-9


@pytest.mark.parametrize("backend", ["numpy", "jax", "warp"])
def test_float32_on_stretched_curved_faces(backend):
    """Three crumpled tri6 faces (2^14 nodes) stretched 50-100 to 1 (J^T J's eigenvalues at the
    closest point) and a node 0.03-0.2 from each: in float32 the active set stopped at its
    tolerance (1e-4) 3e-3 from the point in xi while its residual was scaled by the trace of
    J^T J, the distance up to 3e-4 too large (Warp). Every back end's float32 detection now
    gives the float64 reference's distance to float32 rounding (the faces are 18 across)."""
    from arraycontact import scenes
    from arraycontact.reference import closest_points

    m = scenes.crumpled_sheet(2**14, element="tri6").master
    for node, f in ((8090, 3043), (20145, 3669), (21266, 2110)):
        face = ac.Surface(m.points[m.faces[f]], [np.arange(6)], "tri6")
        r = m.points[node][None]
        want = closest_points(r, face).distance[0]
        c = ac.detect(r, face, backend=backend, d_max=1.0, dtype="float32")
        assert c.active[0] and abs(c.distance[0] - want) < 1e-5, (node, c.distance[0], want)


def test_least_eigenvalue_of_stretched_metrics():
    """`_least` (the KKT residual's scale) against LAPACK's eigenvalues on random J^T J of
    faces stretched up to 1e6 to 1 and turned every way (float64; float32 to its rounding of
    the determinant, eps times the stretch), and never below tiny on a singular one."""
    from arraycontact._geometry import _least

    rng = np.random.default_rng(5)
    n = 2000
    stretch = 10.0 ** rng.uniform(0, 6, n)
    angle = rng.uniform(0, np.pi, n)
    size = 10.0 ** rng.uniform(-3, 3, n)
    c, s = np.cos(angle), np.sin(angle)
    rot = np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)
    m = rot @ (np.eye(2) * np.stack([size, size / stretch], -1)[:, None, :]) @ rot.swapaxes(-1, -2)
    want = np.linalg.eigvalsh(m)[:, 0]
    got = _least(m[:, 0, 0], m[:, 0, 1], m[:, 1, 1], 1e-300, np)
    np.testing.assert_allclose(got, want, rtol=1e-9)
    m32 = m.astype(np.float32)
    got32 = _least(m32[:, 0, 0], m32[:, 0, 1], m32[:, 1, 1], np.float32(1e-30), np)
    ok = stretch < 1e3  # (the determinant's rounding: about eps32 x stretch of it)
    np.testing.assert_allclose(got32[ok], want[ok], rtol=1e-3)
    assert _least(np.float64(1.0), np.float64(2.0), np.float64(4.0), 1e-300, np) == 1e-300
