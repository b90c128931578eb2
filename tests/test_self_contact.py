"""Self-contact (detect_self) on every back end against reference.closest_points_self."""

import hashlib

import numpy as np
import pytest
from conftest import assert_matches_reference

import arraycontact as ac
from arraycontact import scenes
from arraycontact._elements import interpolate

_REFS = {}


def self_reference(surface, d_max):
    key = hashlib.sha1(
        surface.points.tobytes() + surface.faces.tobytes() + repr(d_max).encode()
    ).hexdigest()
    if key not in _REFS:
        _REFS[key] = ac.reference.closest_points_self(surface, d_max=d_max)
    return _REFS[key]


def assert_self_matches(c, surface, d_max, dtype=np.float64):
    """`c` equals the brute-force self-contact reference, and every chosen face is admissible
    (checked here in float64: it does not hold the node, and faces the node's normal)."""
    ref = self_reference(surface, d_max)
    x = surface.points[surface.nodes]
    assert np.array_equal(c.slave_ids, surface.nodes)
    assert_matches_reference(c, x, surface, ref, dtype=dtype)
    a = c.active
    f = c.face[a]
    assert not (surface.faces[f] == c.slave_ids[a][:, None]).any(), "a face holds its node"
    _, dx = interpolate(surface.element, surface.points[surface.faces[f]], c.xi[a])
    nf = np.cross(dx[..., 0], dx[..., 1])
    nf /= np.linalg.norm(nf, axis=-1, keepdims=True)
    facing = np.einsum("pk,pk->p", surface.node_normals[c.slave_ids[a]], nf)
    assert facing.max() < (0 if dtype == np.float64 else 1e-4), "a face does not face its node"
    return ref


SCENES = {
    "spiral": lambda el, n: scenes.spiral_strip(n, element=el),
    "folded": lambda el, n: scenes.folded_sheet(n, element=el),
    "coil": lambda el, n: scenes.coil_spring(n, element=el),
    "crumpled": lambda el, n: scenes.crumpled_sheet(n, element=el),
    "two_bodies": lambda el, n: scenes.two_bodies(n, element=el),
}


@pytest.mark.parametrize("name", sorted(SCENES))
def test_scenes_numpy(name):
    sc = SCENES[name]("tri3", 1500)
    d = sc.params["d_max"]
    c = ac.detect_self(sc.master, backend="numpy", d_max=d)
    ref = assert_self_matches(c, sc.master, d)
    assert c.active.sum() > 0.2 * len(c.active), "the scene should have contact"
    assert c.backend == "numpy" and c.dtype == "float64" and c.finer is not None
    assert (ref.distance <= d).sum() == c.active.sum()


@pytest.mark.parametrize(
    "scene,element,n",
    [("folded", "quad4", 400), ("two_bodies", "tri6", 60), ("two_bodies", "quad8", 50)],
)
def test_elements_numpy(scene, element, n):
    # (The folded sheet's fold is tighter than its elements: curved ones would invert there.
    # Small curved scenes: the reference's lattice of Newton starts is slow.)
    sc = SCENES[scene](element, n)
    d = sc.params["d_max"]
    c = ac.detect_self(sc.master, backend="numpy", d_max=d)
    assert c.active.sum() > 0.2 * len(c.active)
    assert_self_matches(c, sc.master, d)


def test_float32_numpy():
    sc = scenes.spiral_strip(1500, element="tri3")
    d = sc.params["d_max"]
    c = ac.detect_self(sc.master, backend="numpy", d_max=d, dtype=np.float32)
    assert c.dtype == "float32"
    assert_self_matches(c, sc.master, d, np.float32)


def _plate(thickness, n=12):
    """One flat plate (a thin solid) of `thickness`, unit elements in the plane."""
    side = float(n - 1)

    def mapping(u, v, w):
        return side * u, side * v, thickness * w

    return scenes.block_surface(mapping, (n, n, 2), "tri3")


def test_thin_structure_limit():
    """Seed 000 Fig. 11: a plate alone has no contact while d_max is below its thickness; with
    d_max above it, its back side is reported (gap -thickness: seen as a penetration)."""
    t = 0.5
    plate = _plate(t)
    c = ac.detect_self(plate, backend="numpy", d_max=0.9 * t)
    assert not c.active.any()
    c = ac.detect_self(plate, backend="numpy", d_max=1.1 * t)
    assert_self_matches(c, plate, 1.1 * t)
    x = plate.points[c.slave_ids]
    # Nodes inside the broad faces (away from the rim) find the other side straight behind.
    inner = (x[:, :2].min(1) > 1.5) & (x[:, :2].max(1) < 9.5) & c.active
    assert inner.sum() > 50
    np.testing.assert_allclose(c.gap[inner], -t, atol=1e-12)


def test_multibody_pairs_cross_bodies():
    """Two plates in one surface: every contact of a node on a broad face is a face of the
    other plate, at the gap between them or more."""
    sc = scenes.two_bodies(1500, element="tri3")
    s, d = sc.master, sc.params["d_max"]
    c = ac.detect_self(s, backend="numpy", d_max=d)
    n_lower = len(s.points) // 2
    body_node = c.slave_ids >= n_lower
    body_face = s.faces[np.maximum(c.face, 0), 0] >= n_lower
    a = c.active
    assert a.sum() > 100
    assert (body_node[a] != body_face[a]).all()
    assert c.gap[a].min() >= sc.params["gap"] - 1e-9


def test_finer_flag_and_node_mode_density():
    """A fine plate under a coarse one: rows of fine nodes are `finer`, of coarse ones not;
    in node mode the coarse side is the master side of its pairs (seed 000 section 3, item
    5) and every active row is a fine node."""
    t, gap = 1.0, 0.2

    def lower(u, v, w):
        return 20 * u, 20 * v, t * (w - 1)

    def upper(u, v, w):
        return 20 * u, 20 * v, gap + t * w

    a = scenes.block_surface(lower, (41, 41, 2), "tri3")  # h = 0.5
    b = scenes.block_surface(upper, (11, 11, 2), "tri3")  # h = 2
    s = ac.Surface(
        np.concatenate([a.points, b.points]), np.concatenate([a.faces, b.faces + len(a.points)])
    )
    c = ac.detect_self(s, backend="numpy", d_max=0.6)
    assert_self_matches(c, s, 0.6)
    fine = c.slave_ids < len(a.points)
    both = c.active
    assert c.finer[both & fine].all() and not c.finer[both & ~fine].any()
    n = ac.detect_self(s, backend="numpy", mode="node", d_max=0.6)
    c_ids_fine = n.slave_ids < len(a.points)
    assert n.active.sum() > 100
    assert c_ids_fine[n.active].all()
    coarse = ~c_ids_fine & (n.master_node >= 0)
    assert (n.status[coarse] == int(ac.Status.MASTER_SIDE)).all()


def test_node_mode_closest_obtuse_node():
    """Node mode's closest node is the closest other node with an obtuse normal (item 4),
    found here by brute force; an active row's face holds that node."""
    sc = scenes.folded_sheet(1500, element="tri3")
    s, d = sc.master, sc.params["d_max"]
    c = ac.detect_self(s, backend="numpy", mode="node", d_max=d)
    x = s.points[c.slave_ids]
    nn = s.node_normals[c.slave_ids]
    dist = np.linalg.norm(x[:, None] - x[None], axis=-1)
    ok = (nn @ nn.T <= ac.reference.FACING_TOL) & (dist <= d)  # the rule's margin
    dist = np.where(ok, dist, np.inf)
    want = np.where(np.isfinite(dist.min(1)), c.slave_ids[np.argmin(dist, 1)], -1)
    assert np.array_equal(c.master_node, want)
    a = c.active
    assert a.sum() > 100
    assert (s.faces[c.face[a]] == c.master_node[a][:, None]).any(1).all()


def test_bad_input():
    with pytest.raises(ValueError, match="Surface"):
        ac.detect_self(np.zeros((3, 3)))
    sc = scenes.folded_sheet(300)
    with pytest.raises(ValueError, match="mode"):
        ac.detect_self(sc.master, mode="nearest")
    with pytest.raises(ValueError, match="d_max"):
        ac.detect_self(sc.master, d_max=-1.0)


# ---------------------------------------------------------------------------------------------
# JAX and Warp: the one-shot call against the reference, plan/detect against NumPy.


@pytest.mark.parametrize("backend", ["jax", "warp"])
@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_backends_against_reference(backend, dtype):
    sc = scenes.crumpled_sheet(800, element="tri3")
    d = sc.params["d_max"]
    c = ac.detect_self(sc.master, backend=backend, d_max=d, dtype=dtype)
    assert c.backend == backend and c.dtype == np.dtype(dtype).name
    assert_self_matches(c, sc.master, d, dtype)
    a = ac.detect_self(sc.master, backend="numpy", d_max=d, dtype=dtype)
    np.testing.assert_array_equal(c.finer, a.finer)


@pytest.mark.parametrize("backend", ["numpy", "warp"])  # (JAX: NumPy's projection code)
def test_warped_quad4_faces(backend):
    """A coarse crumpled quad4 sheet: node 55's distance to face 58 has two local minima, the
    farther one (the answer of a single Newton start) on a part of the face that does not
    face the node, the nearer one 0.249 (facing) inside it; and (Warp) a node whose closest
    obtuse node has no face that surely faces it, where the scan must not start at that
    node's distance."""
    sc = scenes.crumpled_sheet(300, element="quad4")
    d = sc.params["d_max"]
    assert_self_matches(ac.detect_self(sc.master, backend=backend, d_max=d), sc.master, d)


@pytest.mark.parametrize("element", ["tri3", "quad4", "tri6", "quad8", "quad9"])
def test_warp_face_slab_holds_its_face(element):
    """Self-contact's `Slab` (Warp: skips a face whose slab is beyond the scan's reach) and
    normal boxes (equal to NumPy's) on every element. The slab: the
    unit normal n and the range of n . x over a straight-edged face's corners (a curved face's
    Bernstein control points) holds every point of the face (sampled densely, the crumpled
    sheet's warped quads and its curved faces among them)."""
    import arraycontact_warp as acw

    sc = scenes.crumpled_sheet(300, element=element)
    m = sc.master
    p = acw.plan_self(m, d_max=sc.params["d_max"], dtype="float64")  # (the GPU where there is one)
    acw.detect_self(p, m.points)
    slab = p.face_slab.numpy()
    n, lo, hi = slab[:, :3], slab[:, 3], slab[:, 4]
    g = np.linspace(-1.0, 1.0, 9) if m.element.kind == "quad" else np.linspace(0.0, 1.0, 9)
    xi = np.stack(np.meshgrid(g, g, indexing="ij"), -1).reshape(-1, 2)
    if m.element.kind == "tri":
        xi = xi[xi.sum(1) <= 1.0]
    x, _ = interpolate(m.element, m.points[m.faces][:, None], xi[None])  # [F, samples, 3]
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, rtol=1e-12)
    h = np.einsum("fk,fsk->fs", n, x - p.origin)  # (the plan's frame)
    tol = 1e-12 * np.abs(m.points).max()
    assert np.all(h >= lo[:, None] - tol) and np.all(h <= hi[:, None] + tol)
    assert element == "tri3" or np.ptp(hi - lo) > 0  # (warped quads: slabs of some thickness)
    # and thin beside the faces (a slab bounds only as far as it is tight)
    assert np.median(hi - lo) < 0.5 * np.median(m.face_bounds[1])
    # The same plan's normal boxes are NumPy's (tests/test_surface.py checks those).
    from arraycontact._surface import normal_boxes

    want = normal_boxes(m.element, m.points[m.faces] - p.origin)
    np.testing.assert_allclose(p.face_nlo.numpy(), want[0], rtol=0, atol=1e-12)
    np.testing.assert_allclose(p.face_nhi.numpy(), want[1], rtol=0, atol=1e-12)


def _warp_cpu_compiles() -> bool:
    import warp as wp

    return wp.is_cpu_available()


#: Tests that run Warp's CPU device: a GPU machine's Warp may have no LLVM to compile for it
#: (a failed compile there left the next tests' GPU launches failing).
needs_warp_cpu = pytest.mark.skipif(
    not _warp_cpu_compiles(), reason="Warp's CPU device cannot compile here (no LLVM)"
)


@needs_warp_cpu
def test_warp_first_reach_needs_a_surely_facing_face():
    """Warp self-contact's first reach (`_projection.first_reach` for `Own`): the closest obtuse
    node's distance (0.25 here) only through a face of that node that does not hold the
    slave's node and whose whole normal box faces the slave's normal (n . n_f < -0.01 over
    it); else d_max (1.0). Node 5 of a flat 4 x 4 quad4 grid holds faces 0, 1, 3, 4; node 0
    only face 0, node 15 only face 8."""
    import warp as wp
    from arraycontact_warp import _detect, _geometry, _grid, _projection

    u = np.arange(4.0)
    x, y = np.meshgrid(u, u, indexing="xy")
    pts = np.c_[x.ravel(), y.ravel(), np.zeros(16)]
    faces = np.array([[r * 4 + c, r * 4 + c + 1, r * 4 + c + 5, r * 4 + c + 4]
                      for r in range(3) for c in range(3)])  # fmt: skip
    surface = ac.Surface(pts, faces)
    p = _detect.plan_self(surface, d_max=1.0, device="cpu")

    @wp.kernel(module="unique")
    def reach(
        el: _geometry.Element,
        m: _detect.Master,
        own: wp.array(dtype=int),
        normal: wp.array(dtype=wp.vec3),
        node: wp.array(dtype=int),
        nlo: wp.array(dtype=wp.vec3),
        nhi: wp.array(dtype=wp.vec3),
        out: wp.array(dtype=float),
    ):
        i = wp.tid()
        o = _grid.Own()
        o.node = own[i]
        o.normal = normal[i]
        out[i] = _projection.first_reach(o, el, m, node[i], 0.25, 1.0, nlo, nhi)

    def first_reach(own, normal, node, lo, hi):
        out = wp.zeros(1, dtype=float, device="cpu")
        n = np.asarray(normal, float) / np.linalg.norm(normal)
        ints = [wp.array([v], dtype=int, device="cpu") for v in (own, node)]
        vecs = [wp.array(np.asarray(v, float), dtype=wp.vec3, device="cpu") for v in ([n], lo, hi)]
        args = [p.kernel_element, p.m, ints[0], vecs[0], ints[1], vecs[1], vecs[2]]
        wp.launch(reach, 1, inputs=args, outputs=[out], device="cpu")
        return float(out.numpy()[0])

    up = np.tile([0.0, 0.0, 1.0], (9, 1))  # every face's normal +z
    assert first_reach(15, [0, 0, -1], 5, up, up) == 0.25  # all face the slave
    assert first_reach(15, [0, 0, 1], 5, up, up) == 1.0  # none does
    assert first_reach(15, [0, 0, -1], -1, up, up) == 1.0  # no obtuse node
    assert first_reach(15, [1, 0, -0.005], 5, up, up) == 1.0  # facing, not surely
    assert first_reach(15, [1, 0, -0.02], 5, up, up) == 0.25
    wide = np.tile([1.0, 1.0, 1.0], (9, 1))
    assert first_reach(15, [0, 0, -1], 5, -wide, wide) == 1.0  # a box that faces every way
    # Only face 0 faces the slave: it counts unless it holds the slave's node (node 0).
    side = np.tile([1.0, 0.0, 0.0], (9, 1))
    side[0] = [0.0, 0.0, 1.0]
    assert first_reach(15, [0, 0, -1], 5, side, side) == 0.25
    assert first_reach(0, [0, 0, -1], 5, side, side) == 1.0


@pytest.mark.parametrize("backend", ["jax", "warp"])
def test_backends_quad4_and_node_mode(backend):
    """quad4 exact against the reference; node mode equal to NumPy's row for row (on a
    crumpled sheet: no slave exactly on a Voronoi boundary, where the feature of a closest
    point on an edge is rounding)."""
    sc = scenes.two_bodies(600, element="quad4")
    d = sc.params["d_max"]
    assert_self_matches(ac.detect_self(sc.master, backend=backend, d_max=d), sc.master, d)
    sc = scenes.crumpled_sheet(1200, element="tri3")
    d = sc.params["d_max"]
    a = ac.detect_self(sc.master, backend="numpy", mode="node", d_max=d)
    c = ac.detect_self(sc.master, backend=backend, mode="node", d_max=d)
    assert (a.status == int(ac.Status.MASTER_SIDE)).any() or a.active.any()
    for k in ("active", "face", "status", "master_node", "feature", "finer"):
        np.testing.assert_array_equal(getattr(c, k), getattr(a, k), err_msg=k)
    np.testing.assert_allclose(c.gap, a.gap, atol=1e-12)


def test_jax_plan_detect_grad_vmap():
    import arraycontact_jax as acj
    import jax
    import jax.numpy as jnp

    sc = scenes.crumpled_sheet(500, element="tri3")
    s, d = sc.master, sc.params["d_max"]
    a = ac.detect_self(s, backend="numpy", d_max=d)
    with jax.enable_x64(True):
        p = acj.plan_self(s, d_max=d, dtype=np.float64)
        x = jnp.asarray(s.points)
        c = acj.detect_self(p, x)
        assert not bool(c.overflow)
        for k in ("active", "face", "feature", "finer", "slave_ids", "master_node"):
            np.testing.assert_array_equal(np.asarray(getattr(c, k)), getattr(a, k), err_msg=k)
        np.testing.assert_allclose(np.asarray(c.gap), a.gap, atol=1e-12)

        def energy(y):
            c = acj.detect_self(p, y)
            return jnp.sum(jnp.where(c.active, (d - jnp.where(c.active, c.gap, 0.0)) ** 2, 0.0))

        e, g = jax.jit(jax.value_and_grad(energy))(x)
        energy = jax.jit(energy)
        assert np.isfinite(np.asarray(g)).all() and float(jnp.abs(g).max()) > 0
        rng = np.random.default_rng(1)
        for _ in range(3):
            v = jnp.asarray(rng.normal(size=x.shape))
            h = 1e-6
            fd = (energy(x + h * v) - energy(x - h * v)) / (2 * h)
            np.testing.assert_allclose(float(jnp.sum(g * v)), float(fd), rtol=1e-5)
        moved = jnp.stack([x, x + jnp.asarray([0.0, 0.0, 0.05])[None, :]])
        cs = jax.vmap(lambda y: acj.detect_self(p, y))(moved)
        np.testing.assert_array_equal(np.asarray(cs.active[0]), a.active)
        b = ac.detect_self(s.with_points(np.asarray(moved[1])), backend="numpy", d_max=d)
        np.testing.assert_array_equal(np.asarray(cs.face[1]), b.face)
    with pytest.raises(ValueError, match="plan_self"):
        acj.detect_self(acj.plan(s, s.points[s.nodes], d_max=d), s.points)


@needs_warp_cpu
@pytest.mark.parametrize(
    "name, element", [("spiral_strip", "quad4"), ("coil_spring", "quad4"), ("two_bodies", "tri6")]
)
def test_warp_closest_obtuse_node_equals_numpy(name, element, node_search):
    """Warp's exact self-contact, with a node tree or with the face scan's walk (which meets a
    counting node through a face whose normal box may face the slave), gives NumPy's closest
    obtuse node, face and status on every row (float64)."""
    import arraycontact_warp as acw

    sc = getattr(scenes, name)(600, element=element)
    s, d = sc.master, sc.params["d_max"]
    p = acw.plan_self(s, d_max=d, dtype="float64", device="cpu")
    assert p.nodes_too == node_search
    got = acw.detect_self(p, s.points)
    want = ac.detect_self(s, backend="numpy", d_max=d)
    assert (want.master_node >= 0).sum() >= 100  # (rows with an obtuse node within d_max)
    for k in ("master_node", "face", "status"):
        np.testing.assert_array_equal(got[k], getattr(want, k), err_msg=k)


@needs_warp_cpu
@pytest.mark.parametrize("element", ["quad4", "tri3"])
def test_warp_face_tree_sorts_each_cell_by_normal_class(monkeypatch, element):
    """Self-contact's face tree keys each face by its cell and, within cells of 4 d_max, by
    its normal's class (largest component's axis and sign): on the spiral strip, a thin solid
    whose two sides are an element apart, under a quarter of the leaves mix classes (cells of
    few faces), where most do with the cells alone; the answer is the same bit for bit."""
    import arraycontact_warp as acw
    from arraycontact_warp._real import precision

    sc = scenes.spiral_strip(2**12, element=element)
    s, d = sc.master, sc.params["d_max"]
    x = s.points[s.faces]
    if element == "quad4":  # (the corner normal Warp keys by: the diagonals' cross product)
        n = np.cross(x[:, 2] - x[:, 0], x[:, 3] - x[:, 1])
    else:
        n = np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0])
    axis = np.argmax(np.abs(n), 1)
    cls = 2 * axis + (n[np.arange(len(n)), axis] < 0)

    grid = precision("float32")._grid

    def run():
        p = acw.plan_self(s, d_max=d, device="cpu")
        out = acw.detect_self(p, s.points)
        g, w = p.face_grid, grid.W  # (W item slots a leaf)
        ids = g.items.numpy()["id"][: w * int(g.counts.numpy()[1])].reshape(-1, w)
        assert np.array_equal(np.sort(ids[ids >= 0]), np.arange(len(s.faces)))
        mixed = np.mean([len(set(cls[r[r >= 0]])) > 1 for r in ids])
        return out, mixed

    out, mixed = run()
    plain = grid.new_grid
    monkeypatch.setattr(grid, "new_grid", lambda *a, sides=0.0, **k: plain(*a, **k))
    want, mixed_plain = run()
    assert mixed < 0.25 and mixed_plain > 0.6, (mixed, mixed_plain)
    for k in want:
        np.testing.assert_array_equal(out[k], want[k], err_msg=k)


@needs_warp_cpu
def test_warp_plan_detect_worlds(node_search):
    """arraycontact_warp.plan_self / detect_self: equal to NumPy at the plan's and at moved
    coordinates (a refit), and with two worlds in one surface, each world alone."""
    import arraycontact_warp as acw

    sc = scenes.crumpled_sheet(800, element="tri3")
    s, d = sc.master, sc.params["d_max"]
    p = acw.plan_self(s, d_max=d, dtype="float64", device="cpu")
    assert p.nodes_too == node_search
    for x in (s.points, s.points + np.array([0.0, 0.0, 0.01]) * s.points[:, :1]):
        want = ac.detect_self(s.with_points(x), backend="numpy", d_max=d)
        got = acw.detect_self(p, x)
        for k in ("face", "feature", "master_node", "status"):
            np.testing.assert_array_equal(got[k], getattr(want, k), err_msg=k)
        np.testing.assert_array_equal(got["active"].astype(bool), want.active)
        np.testing.assert_array_equal(got["finer"].astype(bool), want.finer)
        np.testing.assert_allclose(got["gap"], want.gap, atol=1e-12)
    # Two worlds: the sheet and a copy moved onto it (which, in one world, would touch it).
    n = len(s.points)
    both = ac.Surface(np.concatenate([s.points, s.points + 0.1]), np.r_[s.faces, s.faces + n])
    world = np.r_[np.zeros(n, np.int32), np.ones(n, np.int32)]
    p = acw.plan_self(both, world=world, d_max=d, dtype="float64", device="cpu")
    got = acw.detect_self(p, both.points)
    alone = ac.detect_self(s, backend="numpy", d_max=d)
    moved = ac.detect_self(s.with_points(s.points + 0.1), backend="numpy", d_max=d)
    rows = both.nodes
    first = rows < n
    np.testing.assert_array_equal(got["face"][first], alone.face)
    np.testing.assert_array_equal(
        got["face"][~first], np.where(moved.face >= 0, moved.face + len(s.faces), -1)
    )
    with pytest.raises(ValueError, match="detect_self"):
        acw.detect(p, both.points[rows], both.points)
    with pytest.raises(ValueError, match="plan_self"):
        acw.detect_self(acw.plan(s, s.points[s.nodes], d_max=d, device="cpu"), s.points)


def test_jax_search_warp_self():
    import arraycontact_jax as acj
    import jax
    import jax.numpy as jnp

    sc = scenes.two_bodies(600, element="tri3")
    s, d = sc.master, sc.params["d_max"]
    a = ac.detect_self(s, backend="numpy", d_max=d)
    with jax.enable_x64(True):
        p = acj.plan_self(s, d_max=d, dtype=np.float64, search="warp")
        c = acj.detect_self(p, jnp.asarray(s.points))
        for k in ("active", "face", "feature", "finer", "master_node"):
            np.testing.assert_array_equal(np.asarray(getattr(c, k)), getattr(a, k), err_msg=k)
        np.testing.assert_allclose(np.asarray(c.gap), a.gap, atol=1e-12)


@pytest.mark.parametrize("backend", ["jax", "warp"])
def test_backends_quadratic(backend):
    """tri6 (curved faces; the reference of test_elements_numpy's case)."""
    sc = SCENES["two_bodies"]("tri6", 60)
    d = sc.params["d_max"]
    c = ac.detect_self(sc.master, backend=backend, d_max=d)
    assert c.active.sum() > 0.2 * len(c.active)
    assert_self_matches(c, sc.master, d)


@pytest.mark.parametrize("backend", ["numpy", "jax", "warp"])
def test_smallest_surfaces(backend):
    """One face alone has nothing to touch; two facing triangles touch each other (each node
    the other's face interior or edge, at the gap); a triangle facing away does not count."""
    one = ac.Surface([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]])
    c = ac.detect_self(one, backend=backend, d_max=1.0)
    assert not c.active.any() and (c.face == -1).all()
    pts = [[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 0.5], [1, 0, 0.5], [0, 1, 0.5]]
    facing = ac.Surface(pts, [[0, 1, 2], [3, 5, 4]])  # normals +z below, -z above
    c = ac.detect_self(facing, backend=backend, d_max=1.0)
    assert c.active.all()
    np.testing.assert_array_equal(c.face, [1, 1, 1, 0, 0, 0])
    np.testing.assert_allclose(c.gap, 0.5, atol=1e-12)
    away = ac.Surface(pts, [[0, 2, 1], [3, 5, 4]])  # the lower one turned over: both -z
    assert not ac.detect_self(away, backend=backend, d_max=1.0).active.any()


def test_jax_self_overflow_reported_and_update_plan():
    """A plan made with the bodies apart is outgrown when they close in: the overflow is
    reported, and update_plan gives a plan whose answer equals NumPy's."""
    import arraycontact_jax as acj
    import jax
    import jax.numpy as jnp

    sc = scenes.two_bodies(400, element="tri3")
    s, d = sc.master, sc.params["d_max"]
    upper = s.points[:, 2] > 0.1
    apart = s.points + np.where(upper[:, None], [0.0, 0.0, 5.0], 0.0)
    closer = s.points - np.where(upper[:, None], [0.0, 0.0, 0.25], 0.0)  # gap 0.05
    with jax.enable_x64(True):
        p = acj.plan_self(s.with_points(apart), d_max=d, dtype=np.float64, growth=1.0)
        c = acj.detect_self(p, jnp.asarray(closer))
        assert bool(c.overflow)
        q = acj.update_plan(p, c, closer[s.nodes], closer)
        c = acj.detect_self(q, jnp.asarray(closer))
        assert not bool(c.overflow)
        want = ac.detect_self(s.with_points(closer), backend="numpy", d_max=d)
        np.testing.assert_array_equal(np.asarray(c.face), want.face)
        np.testing.assert_allclose(np.asarray(c.gap), want.gap, atol=1e-12)


def test_every_back_end_puts_edge_projections_on_the_edge():
    """On the spiral many nodes project exactly onto an edge of the facing layer: every back
    end reports the reference's feature (XLA's fused multiply-adds once put 122 of them inside
    a face by 1e-19 in natural coordinates: the same face and gap, another feature)."""
    s = scenes.spiral_strip(700, element="tri3")
    d = s.params["d_max"]
    r = self_reference(s.master, d)
    for backend in ("numpy", "jax", "warp"):
        c = ac.detect_self(s.master, backend=backend, d_max=d)
        a = c.active  # (the active set itself: test_elements_numpy and test_backends_*)
        assert (r.feature[a] == ac.Feature.EDGE).sum() > 50
        np.testing.assert_array_equal(c.face[a], r.face[a], err_msg=backend)
        np.testing.assert_array_equal(c.feature[a], r.feature[a], err_msg=backend)
