"""detect() on every back end against the brute-force reference."""

import numpy as np
import pytest
from conftest import assert_matches_reference, reference

import arraycontact as ac
from arraycontact import scenes


def random_scene(seed, element="tri3", n=8):
    """A random bumpy master patch and slaves scattered around it."""
    rng = np.random.default_rng(seed)
    m = 2 * n + 1 if element in ("tri6", "quad8", "quad9") else n + 1
    s = np.linspace(0, n, m)
    x, y = np.meshgrid(s, s, indexing="ij")
    z = 0.3 * rng.normal(size=x.shape)
    xy_noise = 0.15 * rng.uniform(-1, 1, size=(2,) + x.shape)
    master = scenes.grid_surface(x + xy_noise[0], y + xy_noise[1], z, element)
    slave = np.c_[rng.uniform(-1, n + 1, (400, 2)), rng.uniform(-1.5, 1.5, 400)]
    return master, slave


@pytest.mark.parametrize("element", ["tri3", "quad4"])
@pytest.mark.parametrize("seed", [0, 1])
def test_exact_random(backend, element, seed):
    master, slave = random_scene(seed, element)
    c = ac.detect(slave, master, backend=backend)
    assert 50 < c.active.sum() < len(slave)
    assert_matches_reference(c, slave, master)


SCENES = {
    "rough": lambda: scenes.rough_surfaces(2**8, gap=0.5),
    "rough_quad": lambda: scenes.rough_surfaces(2**8, gap=0.5, element="quad4"),
    "layers": lambda: scenes.rough_layers(2**8),
    "sphere": lambda: scenes.sphere_on_plane(2**9, radius=5.0),
    "road": lambda: scenes.cylinder_on_road(2**9, radius=6.0),
    "curved_quad4": lambda: scenes.curved_patch(6, element="quad4", n_slaves=300),
    "curved_tri6": lambda: scenes.curved_patch(5, element="tri6", n_slaves=300),
    "curved_quad8": lambda: scenes.curved_patch(4, element="quad8", n_slaves=200),
    "curved_quad9": lambda: scenes.curved_patch(5, element="quad9", n_slaves=300),
    "layers_tri6": lambda: scenes.rough_layers(2**8, quadratic=True),
    # Graded meshes: element sizes 1 .. 1000 in one surface, and a fine patch in a coarse
    # plate (the size-adaptive tree's cases).
    "graded_tri3": lambda: scenes.graded_surfaces(2**10, ratio=1000.0),
    "fine_patch_quad4": lambda: scenes.fine_patch(12, ratio=1000.0, element="quad4"),
}


@pytest.mark.parametrize("name", sorted(SCENES))
def test_exact_scenes(backend, name):
    s = SCENES[name]()
    c = ac.detect(s.slave, s.master, backend=backend)
    assert c.active.any()
    assert_matches_reference(c, s.slave, s.master)


def _on_and_just_off(element):
    """A rough master and slaves at its nodes, at random points of its faces, and 1e-9, 1e-7
    and 1e-4 edges off them."""
    m = scenes.rough_surfaces(150, rms=0.8, element=element, seed=2).master
    rng = np.random.default_rng(2)
    xi = rng.uniform(0.05, 0.3, (len(m.faces), 2))  # (inside the triangle and the square)
    inner, _ = ac._elements.interpolate(m.element, m.points[m.faces], xi)
    x = np.concatenate([m.points[m.nodes], inner])
    u = rng.normal(size=x.shape)
    u *= m.longest_edge / np.linalg.norm(u, axis=1, keepdims=True)
    return m, np.concatenate([x, x + 1e-9 * u, x + 1e-7 * u, x + 1e-4 * u])


@pytest.mark.parametrize("dtype", ["float64", "float32"])
@pytest.mark.parametrize("backend", ["numpy", "jax", "warp"])
@pytest.mark.parametrize("element", ["quad4", "tri6", "quad9"])
def test_slaves_on_and_just_off_the_surface(backend, element, dtype):
    """Slaves on the surface and just off it, in random directions: there the distance is
    first order in the projection's error in xi, and the distances must still be within
    1e-12 (float64) or 1e-5 of the longest edge (float32) of the reference's: at KKT
    tolerances of 1e-10 and 1e-4 without a last Newton step they were off by up to 2.4e-10
    and 1.7e-4 of the longest edge, in every back end. (NumPy's float32 quad9 also compared
    the distance at Newton steps it then did not take, outside the face, some large enough to
    overflow: a RuntimeWarning, an error under the suite's warnings filter.)"""
    m, slave = _on_and_just_off(element)
    c = ac.detect(slave, m, backend=backend, dtype=dtype)
    assert c.active.all()
    assert_matches_reference(c, slave, m, dtype=np.dtype(dtype))


@pytest.mark.parametrize("element", ["tri3", "quad4"])
def test_far_from_origin(backend, element):
    master, slave = random_scene(3, element, n=6)
    L = master.longest_edge
    for offset in (0.0, 1e6 * L):
        shift = np.array([offset, -0.5 * offset, 0.25 * offset])
        m2 = ac.Surface(master.points + shift, master.faces, element)
        ref = reference(slave + shift, m2)
        c = ac.detect(slave + shift, m2, backend=backend, dtype=np.float32)
        assert_matches_reference(c, slave + shift, m2, ref, dtype=np.float32)
        c64 = ac.detect(slave + shift, m2, backend=backend)
        assert_matches_reference(c64, slave + shift, m2, ref)


def test_fig2a_closest_face_not_attached_to_closest_node(backend):
    # Seed 003 Fig. 2a: the slave hovers over the middle of a large face whose nodes are far,
    # while a small face nearby has a node closer than any of them but is itself farther.
    pts = np.array(
        [
            [-5.0, -5, 0],
            [5.0, -5, 0],
            [0.0, 5, 0],  # large face 0, 1 below
            [1.2, 0, 1],
            [1.5, 0.3, 1],
            [1.5, -0.3, 1],
        ]
    )  # small face 1, 1.2 away
    master = ac.Surface(pts, [[0, 1, 2], [3, 4, 5]], "tri3")
    slave = np.array([[0.0, 0.0, 1.0]])
    # The closest node is on face 1, but face 0 holds the closest point.
    node_d = np.linalg.norm(pts - slave, axis=1)
    assert np.argmin(node_d) == 3
    ref = ac.reference.closest_points(slave, master)
    assert ref.face[0] == 0 and ref.distance[0] == pytest.approx(1.0)
    c = ac.detect(slave, master, backend=backend)
    assert c.face[0] == 0 and c.master_node[0] == 3 and c.gap[0] == pytest.approx(1.0)
    # The published node procedure only looks at the faces of the closest node.
    assert ac.detect(slave, master, backend=backend, mode="node").face[0] == 1
    assert_matches_reference(c, slave, master, ref)


def test_far_apart_returns_before_any_grid(backend, monkeypatch):
    from arraycontact import _grid

    def no_grid(*a, **k):
        raise AssertionError("a grid was built")

    monkeypatch.setattr(_grid, "build", no_grid)
    s = scenes.rough_surfaces(2**8, gap=0.0)
    c = ac.detect(s.slave + np.array([0, 0, 1e3]), s.master, backend=backend)
    assert not c.active.any() and (c.status == ac.Status.OUT_OF_RANGE).all()
    assert c.counts.slaves_in_box == 0


def test_far_apart_patches_cost_what_adjacent_ones_cost():
    # Two patches 1e6 box widths apart: the trees are sized by the item counts, not by the
    # extent, and the answer is the reference's.
    master, slave = random_scene(5, "tri3", n=4)
    far = np.array([1e6 * 6.0, 0, 0])
    m2 = ac.Surface(
        np.r_[master.points, master.points + far],
        np.r_[master.faces, master.faces + len(master.points)],
        "tri3",
    )
    s2 = np.r_[slave, slave + far]
    near = np.array([12.0, 0, 0])
    m3 = ac.Surface(
        np.r_[master.points, master.points + near],
        np.r_[master.faces, master.faces + len(master.points)],
        "tri3",
    )
    s3 = np.r_[slave, slave + near]
    from arraycontact._prepare import prepare

    p2 = prepare(s2, m2, m2.longest_edge)
    p3 = prepare(s3, m3, m3.longest_edge)
    # The slots follow the items' Morton groups, whose count does not depend on the gap: the
    # far-apart trees are no larger (they may be smaller: a top whose groups merge, so a
    # level fewer, `_grid._top`).
    for a, b in ((p2.node_levels, p3.node_levels), (p2.face_levels, p3.face_levels)):
        assert len(a) <= len(b) and sum(a) / sum(b) < 1.25
    c2 = ac.detect(s2, m2, backend="numpy")
    c3 = ac.detect(s3, m3, backend="numpy")
    # The pairs each tree level keeps differ only by the rounding slack of the pruning test
    # (proportional to the coordinates).
    for tree in ("node_level", "face_level"):
        n2, n3 = (sum(v for k, v in c.counts.count.items() if k.startswith(tree)) for c in (c2, c3))
        assert 0.8 < n2 / n3 < 1.25
    assert_matches_reference(c2, s2, m2)


def _pairs_per_slave(scene):
    c = ac.detect(scene.slave, scene.master, backend="numpy")
    return sum(c.counts.count.values()) / len(scene.slave)


def test_work_per_slave_does_not_grow_with_grading():
    # The tree's cost model (arraycontact._grid): the pairs each level keeps depend on the
    # local face size, not on the ratio of the largest to the smallest face. A uniform grid
    # sized by the longest edge kept ~ratio^2 more faces per slave on the graded members.
    uniform = _pairs_per_slave(scenes.graded_surfaces(2**12, ratio=1.0))
    for ratio in (10.0, 100.0, 1000.0):
        graded = _pairs_per_slave(scenes.graded_surfaces(2**12, ratio=ratio))
        assert graded <= 2.0 * uniform, (ratio, graded, uniform)
    # Nor with d_max beyond the answers it adds: 10x the default on the same slaves (the
    # pairs per slave with an answer; 10x gives an answer to 40 % more of them).
    s = scenes.rough_surfaces(2**12)
    c1 = ac.detect(s.slave, s.master, backend="numpy")
    c10 = ac.detect(s.slave, s.master, d_max=10 * s.master.longest_edge, backend="numpy")
    assert c10.active.sum() > 1.2 * c1.active.sum()
    per1, per10 = (sum(c.counts.count.values()) / c.active.sum() for c in (c1, c10))
    assert per10 <= 1.5 * per1


def test_displacement_raises_d_max():
    master, slave = random_scene(0)
    u = np.zeros((10, 3))
    u[3] = [0, 0, 5.0]
    c = ac.detect(slave, master, displacement=u, backend="numpy")
    assert c.d_max == pytest.approx(10.0)
    assert ac.detect(slave, master, backend="numpy").d_max == pytest.approx(master.longest_edge)


def test_pairs_and_slave_ids():
    s = scenes.rough_surfaces(2**8, gap=0.3)
    c = ac.detect(s.slave_surface, s.master, backend="numpy")
    p = c.pairs()
    assert p.shape == (c.active.sum(), 2)
    assert np.array_equal(p[:, 0], s.slave_surface.nodes[c.active])
    assert (p[:, 1] >= 0).all()
