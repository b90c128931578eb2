"""Swept detection (detect_swept) on every back end against reference.swept, closed forms and
the cases a static detection misses."""

import hashlib

import numpy as np
import pytest

import arraycontact as ac
from arraycontact import scenes
from arraycontact.reference import SWEPT_TOL

ALL = ["numpy", "jax", "warp"]
_REFS = {}


def swept_reference(st):
    key = hashlib.sha1(
        b"".join(
            np.ascontiguousarray(a).tobytes()
            for a in (st.slave_x0, st.slave_x1, st.master.points, st.master.faces, st.master_x1)
        )
    ).hexdigest()
    if key not in _REFS:
        _REFS[key] = ac.reference.swept(st.slave_x0, st.slave_x1, st.master, st.master_x1)
    return _REFS[key]


def assert_swept_matches(c, st, dtype=np.float64):
    """Same hits as the reference; toi never after the reference's (beyond its own tolerance)
    and at most t_tol before it; the face the reference picks or one tied with it (its own
    exact toi within the band of the earliest); the point on that face at that time."""
    ref = swept_reference(st)
    assert np.array_equal(c.hit, ref.hit), f"{(c.hit != ref.hit).sum()} slaves differ in hit"
    h = ref.hit
    assert (c.toi[h] <= ref.toi[h] + SWEPT_TOL).all(), "a toi after the exact one"
    assert (c.toi[h] >= ref.toi[h] - c.t_tol - SWEPT_TOL).all(), "a toi too early"
    assert np.isinf(c.toi[~h]).all() and (c.face[~h] == -1).all()
    for i in np.nonzero(h)[0]:
        f = int(c.face[i])
        if (i, f) not in ref.pair_toi:
            # float32: a node through a shared edge may be put on the neighbour whose edge it
            # passes within rounding of; the contact is then on that edge.
            assert dtype == np.float32 and c.feature[i] != ac.Feature.FACE, f"slave {i}: {f}"
            continue
        assert ref.pair_toi[(i, f)] <= ref.toi[i] + 2 * c.t_tol + SWEPT_TOL, f"slave {i}"
    # The point is the node at toi, and lies on the chosen face then.
    t = c.toi[h][:, None]
    np.testing.assert_allclose(
        c.point[h],
        st.slave_x0[h] + t * (st.slave_x1[h] - st.slave_x0[h]),
        atol=1e-9 if dtype == np.float64 else 1e-4,
    )
    e = st.master.element
    xe = st.master.points[st.master.faces[c.face[h]]]
    xe1 = st.master_x1[st.master.faces[c.face[h]]]
    x, _ = ac._elements.interpolate(e, xe + t[:, :, None] * (xe1 - xe), c.xi[h])
    L = st.master.longest_edge
    tol = 1e-6 * L if dtype == np.float64 else 2e-2 * L
    assert np.abs(x - c.point[h]).max() <= tol
    assert (c.status[h] == int(ac.Status.OK)).all()
    assert np.allclose(np.linalg.norm(c.normal[h], axis=1), 1)
    return ref


STEPS = {
    "closing_tri3": lambda: scenes.closing_rough_surfaces(2**8),
    "closing_quad4": lambda: scenes.closing_rough_surfaces(2**8, element="quad4"),
    "closing_tri6": lambda: scenes.closing_rough_surfaces(2**6, element="tri6"),
    "closing_quad8": lambda: scenes.closing_rough_surfaces(2**6, element="quad8"),
    "closing_quad9": lambda: scenes.closing_rough_surfaces(2**6, element="quad9"),
    "tyre": lambda: scenes.rolling_tyre(2**9, drop=1.2),
    # Faces 1/100 of the largest: the capture test grows by each face's size (capture_pads).
    "graded": lambda: scenes.closing_step(scenes.graded_surfaces(2**8, ratio=100.0)),
}


@pytest.mark.parametrize("element", ["tri3", "tri6"])
def test_search_from_the_most_orthogonal_corner(element):
    """The certified search's (s, w) start at the triangle's corner whose edges are nearest
    orthogonal (a sliver's right corner, whichever its label), and its (s, w) in that order
    name the same point of the face in the face's own order."""
    from arraycontact._sweep import corner_shift, shifted, unshifted

    e = ac._elements.ELEMENTS[element]
    rng = np.random.default_rng(2)
    # Slivers 80 long and 1 wide with the right angle at corner 0, 1 or 2.
    right = np.array([[0.0, 0.0, 0.0], [80.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    corners = np.stack([np.roll(right, k, 0) for k in range(3)])
    assert corner_shift(corners).tolist() == [0, 1, 2]
    xe = rng.normal(size=(200, 3, 3))
    if element == "tri6":  # curved: midsides off the chords
        mid = 0.5 * (xe + np.roll(xe, -1, 1)) + 0.1 * rng.normal(size=(200, 3, 3))
        xe = np.concatenate([xe, mid], 1)
    r = corner_shift(xe)
    assert set(r.tolist()) == {0, 1, 2}
    sw = rng.uniform(0, 0.5, (200, 2))
    x_shifted, _ = ac._elements.interpolate(e, shifted(xe, r), sw)
    x_own, _ = ac._elements.interpolate(e, xe, unshifted(sw, r))
    np.testing.assert_allclose(x_shifted, x_own, atol=1e-12)


@pytest.mark.parametrize("name", sorted(STEPS))
def test_numpy_against_reference(name):
    st = STEPS[name]()
    c = ac.detect_swept(st.slave_x0, st.slave_x1, st.master, st.master_x1, backend="numpy")
    ref = assert_swept_matches(c, st)
    assert ref.hit.sum() >= 4, "the step should have contact"
    assert c.backend == "numpy" and c.dtype == "float64" and c.t_tol == 1e-6


@pytest.mark.parametrize("backend", ["jax", "warp"])
@pytest.mark.parametrize("name", ["closing_tri3", "closing_quad4", "closing_tri6", "tyre"])
@pytest.mark.parametrize("dtype", ["float64", "float32"])
def test_backends_against_reference(backend, name, dtype):
    _against_reference_and_numpy(backend, name, dtype)


@pytest.mark.parametrize("name", ["closing_quad8", "closing_quad9"])
@pytest.mark.parametrize("dtype", ["float64", "float32"])
def test_warp_quadratic_quads_against_reference(name, dtype):
    """Warp's quad8 and quad9 pairs (their nodes past the sixth, read in the order of a
    triangle's corner shift, were nodes 3-5 again: 9 of 64 slaves missed or hit at another
    time). JAX runs NumPy's search on every element; its programs cost more than this adds."""
    ref = _against_reference_and_numpy("warp", name, dtype)
    assert ref.hit.sum() >= 16


def _against_reference_and_numpy(backend, name, dtype):
    st = STEPS[name]()
    c = ac.detect_swept(
        st.slave_x0, st.slave_x1, st.master, st.master_x1, backend=backend, dtype=dtype
    )
    assert c.backend == backend and c.dtype == dtype
    ref = assert_swept_matches(c, st, np.dtype(dtype))
    if dtype == "float64":  # the same answer as NumPy's, row for row
        n = ac.detect_swept(st.slave_x0, st.slave_x1, st.master, st.master_x1, backend="numpy")
        assert np.array_equal(c.face, n.face)
        # JAX visits NumPy's boxes; Warp narrows a triangle's and a bilinear quad's search to
        # a slab of time first (_sweep.earliest), whose boxes give another toi within the
        # tolerance (curved faces: NumPy's boxes).
        tol = c.t_tol if backend == "warp" and name != "closing_tri6" else 1e-12
        np.testing.assert_allclose(c.toi[c.hit], n.toi[n.hit], rtol=0, atol=tol)
    return ref


@pytest.mark.parametrize("backend", ["jax", "warp"])
def test_graded_against_reference(backend):
    """Faces from 1 to 100 long (float64): the capture test grown by each face's own size
    keeps every pair the reference hits."""
    st = STEPS["graded"]()
    c = ac.detect_swept(
        st.slave_x0, st.slave_x1, st.master, st.master_x1, backend=backend, dtype="float64"
    )
    ref = assert_swept_matches(c, st)
    assert ref.hit.sum() > len(st.slave_x0) // 2


@pytest.mark.parametrize("backend", ["numpy", "warp"])
def test_graded_float32_hits_are_the_references(backend):
    """float32 on the graded scene's sliver triangles (Jacobian singular values 143, 108, 1.1):
    Krawczyk's box keeps a radius of 2e-3 in s and in w, so a proven box may stay across the
    diagonal with its zero 0.03-0.26 outside a face 100 long (slaves 111, 246, 251 were hits
    before s + w was bounded on its own). The hits must be the float64 reference's. (JAX runs
    NumPy's `krawczyk` and passes here too, but its float32 program's compilation, 6 s, is
    more than the suite's time allows for one scene.)"""
    st = STEPS["graded"]()
    c = ac.detect_swept(
        st.slave_x0, st.slave_x1, st.master, st.master_x1, backend=backend, dtype="float32"
    )
    ref = swept_reference(st)
    assert np.array_equal(c.hit, ref.hit), np.nonzero(c.hit != ref.hit)[0]


def _tumbling_triangles(n_slaves=400, seed=3, grazing=True):
    """Disjoint triangles that tumble and stretch over the step (the coplanarity cubic of a
    pair may have three roots), some still; slaves that reach a random point of a random face
    at a random time (dyadic times among them: the ends of Warp's time slabs), some of them
    crossing a still face at a grazing angle (1e-3; float32's toi may then be early by its
    space tolerance over that speed)."""
    rng = np.random.default_rng(seed)
    m = 30
    x0 = rng.uniform(-1, 1, (m, 3))[:, None] + rng.normal(0, 0.4, (m, 3, 3))
    x1 = x0 + rng.normal(0, 0.5, (m, 1, 3)) + rng.normal(0, 0.3, (m, 3, 3))
    x1[:6] = x0[:6]  # still faces
    master = ac.Surface(x0.reshape(-1, 3), np.arange(3 * m).reshape(m, 3), "tri3")
    f = rng.integers(0, m, n_slaves)
    lam = rng.dirichlet([2, 2, 2], n_slaves)
    t = rng.uniform(0, 1, n_slaves)
    t[::3] = rng.choice([0.0, 0.25, 0.5, 0.75, 1.0, 1 / 64, 3 / 64, 0.5 + 1 / 128], n_slaves)[::3]
    xt = x0[f] + t[:, None, None] * (x1[f] - x0[f])
    hit = np.einsum("nk,nkd->nd", lam, xt)
    v = rng.normal(0, 1.0, (n_slaves, 3))
    slide = np.nonzero(f < 6)[0][:: 2 if grazing else n_slaves + 1]  # along a still face
    nrm = np.cross(x0[f[slide], 1] - x0[f[slide], 0], x0[f[slide], 2] - x0[f[slide], 0])
    nrm /= np.linalg.norm(nrm, axis=1)[:, None]
    v[slide] -= (np.einsum("nd,nd->n", v[slide], nrm) - 1e-3)[:, None] * nrm
    p0 = hit - t[:, None] * v
    # The rest cross their face's plane three times, the first two within one of Warp's
    # root-finding samples (1/16 of the step) and inside the face at the first: p0 and v
    # from the conditions g(t_k) = 0, linear in them, and the point at t_1.
    for i in range(n_slaves - 40, n_slaves):
        f[i] = rng.integers(6, m)  # a tumbling face (a still one's g is linear)
        t1 = rng.uniform(0.1, 0.3)
        times = (t1 + 0.02, t1 + rng.uniform(0.4, 0.6))
        e0, e1 = x0[f[i]], x1[f[i]]
        rows, rhs = [np.c_[np.eye(3), t1 * np.eye(3)]], [None]
        for tk in times:
            xk = e0 + tk * (e1 - e0)
            nk = np.cross(xk[1] - xk[0], xk[2] - xk[0])
            rows.append(np.r_[nk, tk * nk][None])
            rhs.append([nk @ xk[0]])
        xt1 = e0 + t1 * (e1 - e0)
        rhs[0] = lam[i] @ xt1
        hit[i] = rhs[0]
        sol = np.linalg.lstsq(np.concatenate(rows), np.concatenate(rhs), rcond=None)[0]
        p0[i], v[i] = sol[:3], sol[3:]
    return scenes.Step("tumbling", master, x1.reshape(-1, 3), p0, p0 + v)


def test_warp_far_slabs_hold_no_contact():
    """`_sweep._far` (a time slab that the Warp CPU path's search skips): on random moving
    triangles and nodes in float32, every slab it calls far keeps the node from the face
    (the distance sampled densely in float64, less the worst motion between samples, above
    the search's contact tolerance); a slab holding a contact (the node built to reach a point
    of the face inside it) is never far; and most slabs of nodes passing by are."""
    import warp as wp
    from arraycontact_warp import _sweep as sw
    from arraycontact_warp._geometry import triangle_data

    from arraycontact._elements import get_element
    from arraycontact.reference import _closest_on_faces

    rng = np.random.default_rng(11)
    n = 4000
    c0 = rng.uniform(-1, 1, (n, 1, 3)) + rng.normal(0, 0.5, (n, 3, 3))
    c1 = c0 + rng.normal(0, 0.4, (n, 1, 3)) + rng.normal(0, 0.1, (n, 3, 3))
    k = rng.integers(0, 64, n)
    lo, hi = k / 64, (k + 1) / 64
    v = rng.normal(0, 1.0, (n, 3))
    hits = np.arange(n) < n // 2  # a node reaching the face inside the slab
    t = lo + rng.uniform(0, 1, n) * (hi - lo)
    ab = rng.dirichlet([1, 1, 1], n)
    target = np.einsum("ni,nij->nj", ab, c0 + t[:, None, None] * (c1 - c0))
    p0 = np.where(hits[:, None], target - t[:, None] * v, rng.uniform(-2, 2, (n, 3)))
    p1 = p0 + v
    f32 = [np.ascontiguousarray(a, np.float32) for a in (c0.reshape(-1, 3), c1.reshape(-1, 3),
                                                         p0, p1)]  # fmt: skip

    @wp.kernel(module="unique")
    def far(el: sw.Triangles, x0: wp.array(dtype=wp.vec3), x1: wp.array(dtype=wp.vec3),
            faces: wp.array2d(dtype=int), s0: wp.array(dtype=wp.vec3),
            s1: wp.array(dtype=wp.vec3), lo: wp.array(dtype=float), hi: wp.array(dtype=float),
            out: wp.array(dtype=int)):  # fmt: skip
        i = wp.tid()
        q = sw._pair(el, x0, x1, faces, i, s0[i], s1[i], wp.float32(1.0e-5))
        out[i] = int(sw._far(q, sw.Box6(0.0, 1.0, 0.0, 1.0, lo[i], hi[i])))

    arr = [wp.array(a, dtype=wp.vec3, device="cpu") for a in f32]
    faces = wp.array(np.arange(3 * n, dtype=np.int32).reshape(n, 3), dtype=int, device="cpu")
    got = wp.zeros(n, dtype=int, device="cpu")
    bounds = [wp.array(a.astype(np.float32), dtype=float, device="cpu") for a in (lo, hi)]
    wp.launch(far, n, inputs=[triangle_data("cpu"), arr[0], arr[1], faces, arr[2], arr[3],
                              *bounds, got], device="cpu")  # fmt: skip
    got = got.numpy().astype(bool)
    assert not got[hits].any()
    # float64 distances at 65 times of each slab of the float32 inputs, less the face's
    # largest speed relative to the node times half the sampling step.
    x0, x1, q0, q1 = (a.astype(float) for a in f32)
    x0, x1 = x0.reshape(n, 3, 3), x1.reshape(n, 3, 3)
    speed = np.linalg.norm((x1 - x0) - (q1 - q0)[:, None], axis=-1).max(1)
    u = np.linspace(0, 1, 65)
    tt = lo[:, None] + u[None] * (hi - lo)[:, None]  # [n, 65]
    xe = x0[:, None] + tt[..., None, None] * (x1 - x0)[:, None]
    r = q0[:, None] + tt[..., None] * (q1 - q0)[:, None]
    d2 = _closest_on_faces(get_element("tri3"), r.reshape(-1, 3), xe.reshape(-1, 3, 3))[1]
    least = np.sqrt(d2.reshape(n, 65).min(1)) - 0.5 * (hi - lo) / 64 * speed
    scale = np.abs(np.concatenate([x0, x1], 1)).max((1, 2)) + np.abs(q0).max(1) + 1
    assert (least[got] > 1e-5 * scale[got]).all()
    passing = ~hits & (least > 0.2)
    assert got[passing].mean() > 0.5, got[passing].mean()


@pytest.mark.parametrize("dtype", ["float64", "float32"])
def test_warp_time_slabs_against_reference(dtype):
    """Warp's triangle search first narrows time by the coplanarity cubic (_sweep.earliest):
    each of its branches (no crossing, a crossing in a slab, several crossings, a root at a
    slab's end, coplanar motion) against the exact reference."""
    st = _tumbling_triangles(grazing=dtype == "float64")
    c = ac.detect_swept(
        st.slave_x0, st.slave_x1, st.master, st.master_x1, backend="warp", dtype=dtype
    )
    if dtype == "float64":
        assert assert_swept_matches(c, st).hit.all()
        return
    # float32: toi is early by up to the space tolerance over the normal speed (the module
    # docstring of arraycontact._sweep), which these slow tumbling faces make larger than
    # t_tol for NumPy's search as for Warp's; so the hits against the reference, never late,
    # and the faces against NumPy's.
    ref = swept_reference(st)
    n = ac.detect_swept(
        st.slave_x0, st.slave_x1, st.master, st.master_x1, backend="numpy", dtype=dtype
    )
    assert ref.hit.all() and c.hit.all()
    assert (c.toi <= ref.toi + SWEPT_TOL).all()
    assert np.array_equal(c.face, n.face)


def _tumbling_quads(n_slaves=64, seed=5):
    """Disjoint bilinear quads that tumble, stretch and twist over the step, some still;
    slaves that reach a random point of a random face at a random time (dyadic times among
    them, 0 too: a node on its face at the start, inside the face's twist band)."""
    rng = np.random.default_rng(seed)
    m = 12
    square = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], float)
    x0 = rng.uniform(-2, 2, (m, 1, 3)) + 0.5 * square + rng.normal(0, 0.15, (m, 4, 3))
    x1 = x0 + rng.normal(0, 0.6, (m, 1, 3)) + rng.normal(0, 0.3, (m, 4, 3))
    x1[:3] = x0[:3]  # still faces
    master = ac.Surface(x0.reshape(-1, 3), np.arange(4 * m).reshape(m, 4), "quad4")
    f = rng.integers(0, m, n_slaves)
    xi = rng.uniform(-1, 1, (n_slaves, 2))
    t = rng.uniform(0, 1, n_slaves)
    t[::3] = rng.choice([0.0, 0.25, 0.5, 1.0, 1 / 64, 3 / 64, 0.5 + 1 / 128], n_slaves)[::3]
    xt = x0[f] + t[:, None, None] * (x1[f] - x0[f])
    hit, _ = ac._elements.interpolate(master.element, xt, xi)
    v = rng.normal(0, 1.0, (n_slaves, 3))
    p0 = hit - t[:, None] * v
    return scenes.Step("tumbling_quads", master, x1.reshape(-1, 3), p0, p0 + v)


@pytest.mark.parametrize("dtype", ["float64", "float32"])
def test_warp_quad_band_against_reference(dtype):
    """Warp's bilinear search first narrows time by the quad's twist band (_sweep._band): a
    contact needs the node within it. Twisted, tumbling quads, nodes on their face at the
    start among them: the reference's hits, NumPy's faces (its search takes the whole step),
    toi within t_tol of NumPy's and of the reference's. (The reference's quad roots are the
    first times within its own tolerance: up to 7e-8 before the exact contact, which both
    searches report, where a node approaches its face slowly.)"""
    st = _tumbling_quads()
    c = ac.detect_swept(
        st.slave_x0, st.slave_x1, st.master, st.master_x1, backend="warp", dtype=dtype
    )
    n = ac.detect_swept(
        st.slave_x0, st.slave_x1, st.master, st.master_x1, backend="numpy", dtype=dtype
    )
    ref = swept_reference(st)
    assert ref.hit.all() and c.hit.all() and n.hit.all()
    assert np.array_equal(c.face, n.face)
    assert (c.toi <= ref.toi + c.t_tol).all()
    if dtype == "float64":
        np.testing.assert_allclose(c.toi, n.toi, rtol=0, atol=c.t_tol)
        assert (c.toi >= ref.toi - c.t_tol).all()
    # (float32: toi may be early by the space tolerance over the normal speed, as the
    # tumbling triangles' test says: up to 2.7e-3 in both searches on a larger draw.)


def _plane(n=4, element="tri3", z=0.0):
    s = np.linspace(-1, 1, n + 1)
    x, y = np.meshgrid(s, s, indexing="ij")
    return scenes.grid_surface(x, y, np.full_like(x, z), element)


@pytest.mark.parametrize("backend", ALL)
@pytest.mark.parametrize("element", ["tri3", "quad4", "quad9"])
def test_closed_form_impact(backend, element):
    """A node falling at speed 3 onto a plane rising at speed 1 from 2 apart: contact at
    t = 2 / 4, at the node's position then, normal +z, normal velocity -4."""
    m = _plane(4, element)
    m1 = m.points + [0, 0, 1.0]
    x0 = np.array([[0.13, -0.27, 2.0], [0.5, 0.5, 5.0]])
    x1 = x0 + [0.2, 0.1, -3.0]
    c = ac.detect_swept(x0, x1, m, m1, backend=backend)
    assert c.hit.tolist() == [True, False]
    assert 0.5 - c.t_tol <= c.toi[0] <= 0.5
    np.testing.assert_allclose(c.point[0], x0[0] + 0.5 * (x1[0] - x0[0]), atol=1e-5)
    np.testing.assert_allclose(c.normal[0], [0, 0, 1], atol=1e-9)
    np.testing.assert_allclose(c.normal_velocity[0], -4.0, rtol=1e-9)
    assert c.feature[0] == ac.Feature.FACE
    assert c.status.tolist() == [int(ac.Status.OK), int(ac.Status.OUT_OF_RANGE)]


@pytest.mark.parametrize("backend", ALL)
def test_through_a_thin_plate(backend):
    """A node that passes through a plate of thickness 0.01 within the step: the end-of-step
    static detection (d_max below the thickness, as for thin bodies) sees it past the plate
    and out of range; the swept detection reports the hit on the near side at its time."""
    top = _plane(4, "tri3", 0.01)
    bottom = _plane(4, "tri3", 0.0)
    pts = np.r_[top.points, bottom.points]
    faces = np.r_[top.faces, bottom.faces[:, ::-1] + len(top.points)]
    plate = ac.Surface(pts, faces, "tri3")
    x0 = np.array([[0.1, 0.2, 0.5]])
    x1 = np.array([[0.1, 0.2, -0.5]])
    c = ac.detect_swept(x0, x1, plate, pts, backend=backend, static=True, d_max=0.005)
    assert c.hit[0] and not c.static.active[0]
    assert c.face[0] < len(top.faces), "the near side, first"
    assert 0.49 - c.t_tol <= c.toi[0] <= 0.49
    assert c.normal_velocity[0] < 0


@pytest.mark.parametrize("backend", ALL)
def test_edge_vertex_grazing_and_sliding(backend):
    """Through a shared edge (a tie: the smaller face id, feature EDGE), through a shared
    vertex (VERTEX), sliding in the plane from outside onto the surface (hit at the moment it
    enters), grazing past above it (no hit) and at rest on it (hit at t = 0)."""
    m = _plane(2, "tri3")  # nodes on a 3 x 3 lattice of spacing 1
    x0 = np.array(
        [
            [0.5, 0.5, 1.0],  # the diagonal of cell (1, 1): the shared edge of two triangles
            [0.0, 0.0, 1.0],  # the centre vertex
            [-2.0, 0.3, 0.0],  # in the plane, sliding in from x = -2 (enters at x = -1)
            [-2.0, 0.3, 1e-3],  # the same, 1e-3 above: never touches
            [0.2, 0.1, 0.0],  # at rest on the surface
        ]
    )
    x1 = x0 + [[0, 0, -2], [0, 0, -2], [2, 0, 0], [2, 0, 0], [0, 0, 0]]
    c = ac.detect_swept(x0, x1, m, m.points, backend=backend)
    ref = ac.reference.swept(x0, x1, m, m.points)
    assert c.hit.tolist() == [True, True, True, False, True] == ref.hit.tolist()
    assert c.feature[0] == ac.Feature.EDGE and c.feature[1] == ac.Feature.VERTEX
    assert c.face[0] == ref.face[0] and c.face[1] == ref.face[1]
    on_edge = [f for (i, f) in ref.pair_toi if i == 0]
    assert len(on_edge) == 2 and c.face[0] == min(on_edge)
    assert 0.5 - c.t_tol <= c.toi[0] <= 0.5 and 0.5 - c.t_tol <= c.toi[1] <= 0.5
    assert 0.5 - c.t_tol <= c.toi[2] <= 0.5 and c.feature[2] == ac.Feature.EDGE
    assert c.toi[4] == 0.0


@pytest.mark.parametrize("backend", ALL)
def test_degenerate_inputs(backend):
    """Nothing moves (only a node lying on a face hits, at t = 0); a zero-area face (its three
    nodes on a line) is hit only by the segment that meets that line. Such a face meets the
    node along a curve of its parameters, which the search cannot enclose in few boxes: it
    may stop at its budget (NOT_CONVERGED), still never late."""
    m = _plane(2, "tri3")
    x = np.array([[0.3, 0.2, 0.0], [0.3, 0.2, 0.5]])
    c = ac.detect_swept(x, x, m, m.points, backend=backend)
    assert c.hit.tolist() == [True, False] and c.toi[0] == 0.0
    flat = ac.Surface(np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0.0]]), np.array([[0, 1, 2]]))
    x0 = np.array([[0.5, 0.0, 1.0], [0.5, 0.5, 1.0]])
    x1 = np.array([[0.5, 0.0, -1.0], [0.5, 0.5, -1.0]])
    c = ac.detect_swept(x0, x1, flat, flat.points, backend=backend)
    assert c.hit.tolist() == [True, False]  # (the reference's subdivision cannot take it)
    assert c.toi[0] <= 0.5
    if c.status[0] == int(ac.Status.OK):
        assert 0.5 - c.t_tol <= c.toi[0]
    else:
        assert c.status[0] == int(ac.Status.NOT_CONVERGED)


def test_static_from_the_same_call():
    st = STEPS["closing_tri3"]()
    c = ac.detect_swept(
        st.slave_x0, st.slave_x1, st.master, st.master_x1, backend="numpy", static=True
    )
    end = ac.detect(st.slave_x1, st.master.with_points(st.master_x1), backend="numpy")
    assert np.array_equal(c.static.face, end.face) and np.array_equal(c.static.active, end.active)


def test_surface_slaves_and_pairs():
    st = STEPS["closing_tri3"]()
    s = st.slave_surface
    c = ac.detect_swept(s, st.slave_x1, st.master, st.master_x1, backend="numpy")
    assert np.array_equal(c.slave_ids, s.nodes)
    assert c.pairs().shape == (c.hit.sum(), 2)


def test_bad_input():
    m = _plane(2)
    x = np.zeros((3, 3))
    with pytest.raises(ValueError, match="master_x1"):
        ac.detect_swept(x, x, m, m.points[:-1])
    with pytest.raises(ValueError, match="differ in shape"):
        ac.detect_swept(x, x[:2], m, m.points)
    with pytest.raises(ValueError, match="slave_x1"):
        ac.detect_swept(x, np.full((3, 3), np.nan), m, m.points)
    with pytest.raises(ValueError, match="master must be"):
        ac.detect_swept(x, x, m.points, m.points)
    with pytest.raises(ValueError, match="dtype"):
        ac.detect_swept(x, x, m, m.points, dtype="int32")
    with pytest.raises(ValueError, match="backend"):
        ac.detect_swept(x, x, m, m.points, backend="cuda")
    empty = ac.detect_swept(np.zeros((0, 3)), np.zeros((0, 3)), m, m.points)
    assert len(empty) == 0


@pytest.mark.parametrize("pairs", [0, 10**5])
def test_warp_worlds(pairs):
    """Two worlds in one launch: each world's slaves see only that world's master (searched
    one thread a slave, and one thread a pair)."""
    import arraycontact_warp as acw

    st = STEPS["closing_tri3"]()
    m = st.master
    n, npts = len(st.slave_x0), len(m.points)
    both = ac.Surface(np.r_[m.points, m.points], np.r_[m.faces, m.faces + npts], "tri3")
    p = acw.plan_swept(
        both,
        np.r_[st.slave_x0, st.slave_x0],
        slave_world=np.r_[np.zeros(n, int), np.ones(n, int)],
        master_world=np.r_[np.zeros(npts, int), np.ones(npts, int)],
        dtype="float64",
        pairs=pairs,
    )
    # World 1's master does not move: its answer is another step.
    out = acw.detect_swept(
        p,
        np.r_[st.slave_x0, st.slave_x0],
        np.r_[st.slave_x1, st.slave_x1],
        both.points,
        np.r_[st.master_x1, m.points],
    )
    one = ac.detect_swept(st.slave_x0, st.slave_x1, m, st.master_x1, backend="numpy")
    still = ac.detect_swept(st.slave_x0, st.slave_x1, m, m.points, backend="numpy")
    assert np.array_equal(out["face"][:n], one.face)
    f1 = out["face"][n:]
    assert np.array_equal(np.where(f1 >= 0, f1 - len(m.faces), -1), still.face)
    assert not np.array_equal(one.face, still.face)


@pytest.mark.parametrize(
    "name, dtype", [("closing_quad4", "float64"), ("tumbling", "float32"), ("graded", "float64")]
)
def test_warp_pair_list_equals_one_thread_a_slave(monkeypatch, name, dtype):
    """The search one thread a pair (the GPU's default) gives the answers of the search one
    thread a slave (the CPU's, checked against the reference above), with a list that holds
    every pair (on the graded step some slaves meet more faces than a walk's window keeps,
    and walk again), with one too short, whose slaves left out are searched one thread a
    slave, and with the long searches deferred to later launches (a GPU's way: here every
    triangle search of more than 1 box, as on a GPU, or other face's of more than 2, to a
    second, of more than 4 to a third, in whatever order); a negative length is named."""
    import arraycontact_warp as acw
    from arraycontact_warp._real import precision
    from arraycontact_warp._sweep import WINDOW

    st = _tumbling_triangles() if name == "tumbling" else STEPS[name]()
    n = len(st.slave_x0)
    xs = (st.slave_x0, st.slave_x1, st.master.points, st.master_x1)
    runs = {}
    for pairs in (0, 40 * n, n):
        p = acw.plan_swept(st.master, st.slave_x0, dtype=dtype, pairs=pairs)
        runs[pairs] = acw.detect_swept(p, *xs)
        lost = p.lost.numpy()
        if pairs == 0:
            assert lost.all() and p.pairs_needed() == 0
        elif pairs == n:  # too short
            assert 0 < lost.sum() < n and p.pairs_needed() > n
        else:
            assert not lost.any() and n < p.pairs_needed() <= pairs
            more = (p.pairs.count.numpy() > WINDOW).sum()
            assert p.pairs.n_more.numpy()[0] == more and (more > 0) == (name == "graded")
    tiers = {"tri3": (1, 4), "other": (2, 4)}
    monkeypatch.setattr(precision(dtype), "SWEPT_BUDGET", {"cpu": tiers, "cuda": tiers})
    p = acw.plan_swept(st.master, st.slave_x0, dtype=dtype, pairs=40 * n)
    runs["deferred"] = acw.detect_swept(p, *xs)
    later = p.pairs.n_later.numpy()
    assert p.pairs_needed() > later[0] > later[1] > 0  # some deferred once and twice, not all
    one = runs[0]
    assert one["hit"].sum() > n // 4
    # The same kernels' arithmetic in another kernel: a GPU compiler may fuse its multiplies
    # and adds otherwise (a CUDA device: curved faces' toi and points differ in the last bit).
    eps = np.finfo(dtype).eps
    hit = one["hit"] == 1
    for pairs in (40 * n, n, "deferred"):
        for k, v in runs[pairs].items():
            if k == "visits":  # (a pair's search may be bounded by another's find or not)
                continue
            if v.dtype.kind == "f":  # (the rows hit; the others' toi is a placeholder)
                a, b = v[hit], one[k][hit]
                tol = 8 * eps * max(1.0, float(np.abs(b).max()))
                np.testing.assert_allclose(a, b, rtol=0, atol=tol, err_msg=f"{pairs} {k}")
            else:
                assert np.array_equal(v, one[k]), (pairs, k)
    with pytest.raises(ValueError, match="pairs"):
        acw.plan_swept(st.master, st.slave_x0, pairs=-1)


def _capture_centres(m0, m1, faces):
    """The centre of each triangle's box over both ends of the step (its capture key's)."""
    a, b = m0[faces], m1[faces]
    return 0.5 * (np.minimum(a.min(1), b.min(1)) + np.maximum(a.max(1), b.max(1)))


@pytest.mark.parametrize("way", ["graph", "launches"])
def test_warp_swept_refit_and_rebuild(way):
    """Where the device chooses (a CUDA graph with conditional nodes, the caller's; on a GPU
    outside a graph, through the plan's graph of the rebuild alone; the CPU), a detect after
    the first keeps the capture tree's order while every capture box's centre stays within the
    plan's margin of where it was sorted, and sorts again otherwise: the path taken is the one
    the centres call for, and the answers are those of a plan that sorts every call."""
    import arraycontact_warp as acw
    import warp as wp

    st = STEPS["closing_tri3"]()
    L = st.master.longest_edge
    faces = st.master.faces
    with pytest.raises(ValueError, match="growth"):
        acw.plan_swept(st.master, st.slave_x0, growth=0.5)
    p = acw.plan_swept(st.master, st.slave_x0, dtype="float64")
    q = acw.plan_swept(st.master, st.slave_x0, dtype="float64", refit=False)
    assert p.refit and not q.refit
    margin = float(p.grid.margin)
    assert margin > 0
    xs = [st.slave_x0, st.slave_x1, st.master.points, st.master_x1]
    arrays = [wp.array(a - p.origin, dtype=wp.vec3d, device=p.device) for a in xs]
    origin, p.origin = p.origin, np.zeros(3)  # (arrays in the plan's frame)
    acw.detect_swept(p, *arrays)  # the first call builds
    run = lambda: acw.detect_swept(p, *arrays)  # noqa: E731
    if p.device.is_cuda and not wp.is_conditional_graph_supported():
        pytest.skip("this CUDA driver has no conditional graph nodes (12.4+)")
    if p.device.is_cuda and way == "graph":
        with wp.ScopedCapture(device=p.device) as cap:
            acw.detect_swept(p, *arrays)
        run = lambda: wp.capture_launch(cap.graph)  # noqa: E731
    sorted_at = _capture_centres(st.master.points, st.master_x1, faces)
    rng = np.random.default_rng(5)
    small, large = np.array([0.013, -0.007, 0.02]) * L, np.array([1.7, 0.4, -0.05]) * L
    for step, shift in enumerate([small, large, large + small]):
        moved = [a + shift + rng.normal(0, 0.002 * L, a.shape) for a in xs]
        c = _capture_centres(moved[2], moved[3], faces)
        stale = bool((np.linalg.norm(c - sorted_at, axis=1) > margin).any())
        assert stale == (step == 1)  # small motions stay within the margin, the large not
        for a, m in zip(arrays, moved):
            a.assign(m - origin)
        run()
        assert int(p.rebuild.numpy()[0]) == int(stale)
        assert (p.build_graph is not None) == (p.device.is_cuda and way == "launches")
        got = {k: v.numpy() for k, v in p.out.items()}
        built = acw.detect_swept(q, *[m - origin for m in moved])
        hit = built["hit"] == 1
        assert hit.sum() > len(hit) // 4
        for k in got:
            if k == "visits":  # (the pairs' order differs: a search may be bounded sooner)
                continue
            if got[k].dtype.kind == "f":  # (the rows hit; the others' toi is a placeholder)
                np.testing.assert_allclose(got[k][hit], built[k][hit], rtol=0, atol=1e-12 * L)
            else:
                assert np.array_equal(got[k], built[k]), (step, k)
        if stale:
            sorted_at = c


def test_warp_swept_graph_replays_after_other_plans():
    """A swept detection captured as a CUDA graph replays with the same answers after a
    static and a self-contact plan of other shapes were made and run (their kernels loaded,
    their trees sorted, their own graphs captured). On the CPU, without graphs, the same
    sequence. (The orders a benchmark uses; its one failure on an H100 was a graph whose plan
    had been collected: benchmarks/RESULTS.md, "The graph that broke, diagnosed".)"""
    import arraycontact_warp as acw
    import warp as wp

    st = STEPS["closing_tri3"]()
    p = acw.plan_swept(st.master, st.slave_x0)
    xs = [st.slave_x0, st.slave_x1, st.master.points, st.master_x1]
    arrays = [wp.array(a - p.origin, dtype=wp.vec3, device=p.device) for a in xs]
    p.origin = np.zeros(3)
    acw.detect_swept(p, *arrays)
    run = lambda: acw.detect_swept(p, *arrays)  # noqa: E731
    if p.device.is_cuda:
        with wp.ScopedCapture(device=p.device) as cap:
            acw.detect_swept(p, *arrays)
        run = lambda: wp.capture_launch(cap.graph)  # noqa: E731
    run()
    before = {k: v.numpy().copy() for k, v in p.out.items()}
    big = scenes.closing_rough_surfaces(2**10, element="quad4")
    r = acw.plan(big.master, big.slave_x1)
    for _ in range(3):  # (the second call captures the static plan's graph)
        acw.detect(r, big.slave_x1, big.master.points)
    s = scenes.spiral_strip(2**9, element="quad4")
    q = acw.plan_self(s.master, d_max=s.params["d_max"])
    for _ in range(3):
        acw.detect_self(q, s.master.points)
    run()
    for k, v in p.out.items():
        assert np.array_equal(v.numpy(), before[k]), k


def test_jax_gradients_and_overflow():
    """toi and the impact point differentiated with respect to all four coordinate arrays
    against central finite differences of the reference's toi (float64), and a plan sized for
    a slower step reports overflow, which update_swept_plan mends."""
    import arraycontact_jax as acj
    import jax
    import jax.numpy as jnp

    m = _plane(3, "quad4")
    rng = np.random.default_rng(3)
    m0 = m.points + rng.normal(0, 0.05, m.points.shape)
    m1 = m0 + [0, 0, 0.4] + rng.normal(0, 0.05, m.points.shape)
    x0 = np.array([[0.11, -0.23, 1.0], [-0.41, 0.37, 0.8]])
    x1 = x0 + [[0.05, 0.02, -1.5], [-0.03, 0.04, -1.2]]
    mm = m.with_points(m0)
    with jax.enable_x64(True):
        p = acj.plan_swept(mm, x0, x1, m1, dtype="float64")
        args = [jnp.asarray(a) for a in (x0, x1, m0, m1)]
        res = acj.detect_swept(p, *args)
        assert bool(res.hit.all()) and not bool(res.counts.overflow)

        def f(a, b, c, d):
            r = acj.detect_swept(p, a, b, c, d)
            return jnp.sum(r.toi * jnp.array([1.0, 2.0])) + jnp.sum(r.point[:, 2] * 0.3)

        grads = jax.grad(f, argnums=(0, 1, 2, 3))(*args)

    def g(arrs):
        r = ac.reference.swept(arrs[0], arrs[1], mm.with_points(arrs[2]), arrs[3])
        pt = arrs[0] + r.toi[:, None] * (arrs[1] - arrs[0])
        return np.sum(r.toi * [1.0, 2.0]) + np.sum(pt[:, 2] * 0.3)

    h = 1e-5
    base = [x0, x1, m0, m1]
    for k, grad in enumerate(grads):
        # One coordinate across the step's plane, one along it (a node; a face node).
        for idx in [(5, 2), (6, 0)] if k >= 2 else [(0, 2), (1, 0)]:
            plus = [a.copy() for a in base]
            minus = [a.copy() for a in base]
            plus[k][idx] += h
            minus[k][idx] -= h
            fd = (g(plus) - g(minus)) / (2 * h)
            assert abs(float(grad[idx]) - fd) <= 1e-4 * max(1, abs(fd)), (k, idx, grad[idx], fd)
    # Overflow: planned for a still step, run on a moving one.
    with jax.enable_x64(True):
        p0 = acj.plan_swept(mm, x0, dtype="float64", growth=1.0)
        r0 = acj.detect_swept(p0, *args)
        assert bool(r0.counts.overflow)
        p1 = acj.update_swept_plan(p0, r0, *args)
        r1 = acj.detect_swept(p1, *args)
        assert not bool(r1.counts.overflow)
        np.testing.assert_array_equal(np.asarray(r1.face), np.asarray(res.face))
        batched = jax.vmap(lambda b: acj.detect_swept(p, args[0], b, args[2], args[3]).toi)(
            jnp.stack([args[1], args[0]])
        )
        assert np.isfinite(np.asarray(batched[0])).all() and np.isinf(np.asarray(batched[1])).all()


@pytest.mark.parametrize("element", ["tri3", "quad4"])
def test_jax_search_gathers_the_busy_pairs(monkeypatch, element):
    """The JAX search goes on with the pairs still searching gathered into 1/8 of the lanes
    (here from 8 lanes up, so at every level the scene allows): each pair visits the same
    boxes, so the answers are NumPy's, row for row."""
    from arraycontact_jax import _sweep as js

    monkeypatch.setattr(js, "MIN_LANES", {"cpu": 8, "gpu": 8})
    lanes = []
    run = js._run

    def spy(element, state, inputs, t_tol):
        lanes.append(state[1].shape[0])
        return run(element, state, inputs, t_tol)

    monkeypatch.setattr(js, "_run", spy)
    st = scenes.closing_rough_surfaces(2**9, element=element, seed=7)
    args = (st.slave_x0, st.slave_x1, st.master, st.master_x1)
    c = ac.detect_swept(*args, backend="jax", dtype="float64")
    assert len(lanes) >= 3 and lanes[1] == lanes[0] // 8  # gathered twice at least
    n = ac.detect_swept(*args, backend="numpy")
    assert np.array_equal(c.hit, n.hit) and np.array_equal(c.face, n.face)
    np.testing.assert_allclose(c.toi[c.hit], n.toi[n.hit], rtol=0, atol=1e-12)
    assert_swept_matches(c, st)


@pytest.mark.parametrize("element", ["tri3", "quad4"])
def test_capture_pads_cover_every_contact_the_search_reports(element):
    """The capture test's growth, relative to each face's and path's own size
    (`capture_pads`), holds every pair whose certified search reports a contact, near misses
    within the search's tolerance included: float32 flat faces sliding in their plane and
    nodes sliding parallel to them at heights around the tolerance, faces from 1e-2 to 1e2.
    Each pair is a scene of its own (its frame: its largest coordinate). Without the relative
    growth the near misses would be left out: the bound is what keeps them."""
    from arraycontact import _sweep
    from arraycontact._detect import capture_boxes
    from arraycontact._elements import ELEMENTS

    e = ELEMENTS[element]
    rng = np.random.default_rng(3)
    n = 1000
    size = 10.0 ** rng.uniform(-2, 2, n)
    ref = e.nodes if e.nodes.shape[1] == 3 else np.c_[e.nodes, np.zeros(len(e.nodes))]
    ref = ref[: e.n_corners] * (0.5 if element == "quad4" else 1.0)  # edges of 1
    turn = rng.uniform(0, 2 * np.pi, n)
    c, s = np.cos(turn), np.sin(turn)
    rot = np.zeros((n, 3, 3))
    rot[:, 0, 0], rot[:, 0, 1], rot[:, 1, 0], rot[:, 1, 1], rot[:, 2, 2] = c, -s, s, c, 1
    centre = rng.normal(0, 1, (n, 3)) * size[:, None]
    xe0 = centre[:, None] + size[:, None, None] * (ref @ rot.transpose(0, 2, 1))
    slide = np.c_[rng.normal(0, 1, (n, 2)), np.zeros(n)] * size[:, None]
    xe1 = xe0 + slide[:, None]
    # Nodes crossing above the face, parallel to it, at heights of 0.05 to 0.5 times the
    # contact tolerance of 3 faces' sizes (`pair_frame`: about where it reports them), or below.
    scale = np.maximum(np.abs(xe0 - xe0[:, :1]).max((1, 2)), 3 * size)
    eps = float(np.finfo(np.float32).eps)
    tol = max(_sweep.SPACE_RTOL[np.dtype(np.float32)], 4 * _sweep.ROUND * eps) * scale
    h = tol * 10.0 ** rng.uniform(-1.3, -0.3, n)
    h *= rng.choice([-1, 1], n)
    mid = xe0.mean(1) + 0.5 * slide + np.c_[np.zeros((n, 2)), h]
    path = np.c_[rng.normal(0, 1, (n, 2)), np.zeros(n)] * size[:, None]
    p0, p1 = mid - path, mid + path
    f32 = [a.astype(np.float32) for a in (xe0, xe1, p0, p1)]
    toi = _sweep.roots(e, *f32)[0]
    hit = np.isfinite(toi)
    xe0, xe1, p0, p1 = (a.astype(np.float64) for a in f32)  # the coordinates it saw

    def candidates(rel, rounding):
        lo, hi = _sweep.grown_boxes(*capture_boxes(e, xe0, xe1), rel, rounding)
        grow = rel * np.linalg.norm(p1 - p0, axis=1)[:, None]
        lo, hi = lo - grow, hi + grow
        d = p1 - p0
        with np.errstate(divide="ignore", invalid="ignore"):
            u, v = (lo - p0) / d, (hi - p0) / d
        inside = (p0 >= lo) & (p0 <= hi)
        t0 = np.where(d != 0, np.minimum(u, v), np.where(inside, -np.inf, np.inf)).max(1)
        t1 = np.where(d != 0, np.maximum(u, v), np.where(inside, np.inf, -np.inf)).min(1)
        return np.maximum(t0, 0) <= np.minimum(t1, 1)

    rel, rounding = _sweep.capture_pads(np.float32)
    frame = np.abs(np.concatenate([xe0, xe1, p0[:, None], p1[:, None]], 1)).max((1, 2))
    near_miss = hit & ~candidates(0.0, 0.0)
    assert near_miss.sum() > n // 20, "too few near misses to test the bound"
    assert candidates(rel, rounding * frame[:, None])[hit].all()
    assert not candidates(0.0, rounding * frame[:, None])[near_miss].all()
