"""The JAX plan / detect API: static shapes, no recompilation, vmap, exact gradients."""

import arraycontact_jax as acj
import jax
import jax.monitoring
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import assert_matches_reference

import arraycontact as ac
from arraycontact import scenes

ELEMENTS = ["tri3", "quad4", "tri6", "quad8", "quad9"]


@pytest.fixture(autouse=True)
def x64():
    with jax.enable_x64(True):
        yield


def _compare(c, r):
    """JAX contacts `c` equal NumPy contacts `r`: same integers, floats to rounding."""
    for k in ("active", "face", "feature", "status", "master_node"):
        assert np.array_equal(np.asarray(getattr(c, k)), getattr(r, k)), k
    a = r.active
    for k in ("gap", "point", "normal", "xi", "distance"):
        assert np.allclose(np.asarray(getattr(c, k))[a], getattr(r, k)[a], atol=1e-12), k
        assert np.isnan(np.asarray(getattr(c, k))[~a & (r.status != 3)]).all(), k


@pytest.mark.parametrize("mode", ["exact", "node"])
@pytest.mark.parametrize(
    "make",
    [
        lambda: scenes.rough_surfaces(2**10, seed=3),
        lambda: scenes.rough_layers(2**8, quadratic=True, seed=1),
    ],
    ids=["rough_tri3", "layers_tri6"],
)
def test_plan_detect_equals_numpy(make, mode):
    s = make()
    p = acj.plan(s.master, s.slave, mode=mode)
    c = acj.detect(p, jnp.asarray(s.slave), jnp.asarray(s.master.points))
    assert not bool(c.overflow)
    r = ac.detect(s.slave, s.master, mode=mode, backend="numpy")
    _compare(c, r)
    if mode == "exact":
        assert_matches_reference(jax.tree.map(np.asarray, c), s.slave, s.master)


def test_float32_plan_is_close_to_float64_far_from_the_origin():
    s = scenes.rough_surfaces(2**10, seed=4)
    shift = np.array([1e6, -3e6, 2e6]) * s.master.longest_edge
    master = s.master.with_points(s.master.points + shift)
    slave = s.slave + shift
    p = acj.plan(master, slave, dtype=np.float32)
    c = acj.detect(p, jnp.asarray(slave), jnp.asarray(master.points))
    assert c.gap.dtype == jnp.float32
    r = ac.detect(slave, master, backend="numpy")
    same = np.asarray(c.active) == r.active
    assert same.mean() > 0.999
    a = r.active & np.asarray(c.active)
    assert np.abs(np.asarray(c.gap)[a] - r.gap[a]).max() <= 1e-5 * master.longest_edge


def test_no_recompilation_over_20_steps_of_a_moving_scene(search="jax"):
    s = scenes.rough_surfaces(2**10, seed=5)
    p = acj.plan(s.master, s.slave, search=search)
    rng = np.random.default_rng(0)
    steps = []
    for k in range(20):  # rigid motion of the slave and a small deformation of the master
        a = 0.01 * k
        rot = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
        slave = (s.slave - s.slave.mean(0)) @ rot.T + s.slave.mean(0) + [0.02 * k, 0, -0.02 * k]
        master = s.master.points + 0.01 * rng.standard_normal(s.master.points.shape)
        steps.append((jax.device_put(slave), jax.device_put(master)))
    compiles = []
    jax.monitoring.register_event_duration_secs_listener(
        lambda name, *a, **kw: (
            compiles.append(name) if name == "/jax/core/compile/backend_compile_duration" else None
        )
    )
    first = None
    for k, (slave, master) in enumerate(steps):
        c = acj.detect(p, slave, master)
        assert not bool(c.overflow)
        if k == 0:
            first = len(compiles)
        if k in (0, 19):
            r = ac.detect(
                np.asarray(slave),
                s.master.with_points(np.asarray(master)),
                d_max=p.d_max,
                backend="numpy",
            )
            _compare(c, r)
    assert first >= 1 and len(compiles) == first, f"{len(compiles) - first} recompilations"


def test_overflow_is_reported_and_update_plan_fixes_it():
    s = scenes.rough_surfaces(2**10, seed=6)
    # Planned with the slaves far above the master (no candidate faces), then moved onto it.
    p = acj.plan(s.master, s.slave + [0, 0, 20.0], growth=1.0, d_max=s.master.longest_edge)
    slave = s.slave - [0, 0, 1.0]
    c = acj.detect(p, jnp.asarray(slave), jnp.asarray(s.master.points))
    assert bool(c.overflow)
    over = [k for k, v in c.counts.capacity.items() if c.counts.count[k] > v]
    assert over
    p2 = acj.update_plan(p, c, slave, s.master.points)
    assert p2 is not p
    c2 = acj.detect(p2, jnp.asarray(slave), jnp.asarray(s.master.points))
    assert not bool(c2.overflow)
    _compare(c2, ac.detect(slave, s.master, backend="numpy"))
    assert acj.update_plan(p2, c2, slave, s.master.points) is p2
    # A master deformed far from the plan's configuration: the trees keep the plan's order
    # (their boxes refitted), which stays exact; whatever no longer fits its capacity is
    # reported, and update_plan orders and sizes them again.
    stretched = s.master.points * [1.5, 1.5, 1]
    c3 = acj.detect(p2, jnp.asarray(slave), jnp.asarray(stretched))
    p3 = acj.update_plan(p2, c3, slave, stretched)
    c4 = acj.detect(p3, jnp.asarray(slave), jnp.asarray(stretched))
    assert not bool(c4.overflow)
    _compare(c4, ac.detect(slave, s.master.with_points(stretched), d_max=p.d_max, backend="numpy"))


def test_plans_count_with_a_program_compiled_once_per_shapes():
    """The plan's counting program, compiled apart (on a GPU at XLA's lowest backend
    optimisation), is compiled once for a scene's shapes, and counts what the detection (its
    own program) counts at the plan's coordinates."""
    from arraycontact_jax import _detect as jd

    s = scenes.rough_surfaces(2**9, seed=4, gap=0.2)
    p = acj.plan(s.master, s.slave, growth=1.0)
    n = len(jd._ONCE)
    assert acj.plan(s.master, s.slave, growth=1.0).capacity == p.capacity
    assert len(jd._ONCE) == n
    c = acj.detect(p, jnp.asarray(s.slave), jnp.asarray(s.master.points))
    count = int(c.counts.count["face_candidates"])
    assert count > jd.MIN_CANDIDATES  # (so that the capacity is the count itself)
    assert dict(p.capacity)["face_candidates"] == count and not bool(c.overflow)


def test_plan_rejects_bad_input():
    s = scenes.rough_surfaces(2**8, seed=0)
    with pytest.raises(ValueError, match="mode"):
        acj.plan(s.master, s.slave, mode="fast")
    with pytest.raises(ValueError, match="slave_points"):
        acj.plan(s.master, s.slave[:, :2])
    with pytest.raises(ValueError, match="empty"):
        acj.plan(s.master, np.zeros((0, 3)))
    with pytest.raises(ValueError, match="growth"):
        acj.plan(s.master, s.slave, growth=0.5)
    p = acj.plan(s.master, s.slave)
    with pytest.raises(ValueError, match="master_points"):
        acj.detect(p, jnp.asarray(s.slave), jnp.asarray(s.master.points[:-1]))
    with jax.enable_x64(False):
        with pytest.raises(ValueError, match="x64"):
            acj.plan(s.master, s.slave, dtype=np.float64)


def test_vmap_over_scenes_equals_one_by_one(search="jax"):
    s = scenes.rough_surfaces(2**10, seed=7)
    p = acj.plan(s.master, s.slave, search=search)
    shifts = np.array([[0, 0, 0], [0.1, 0, 0.1], [0, -0.2, 0.3]])
    masters = jnp.asarray(s.master.points[None] + shifts[:, None])
    slaves = jnp.asarray(np.stack([s.slave] * 3))
    cb = jax.vmap(acj.detect, in_axes=(None, 0, 0))(p, slaves, masters)
    assert cb.gap.shape == (3, len(s.slave)) and not np.asarray(cb.overflow).any()
    for i in range(3):
        ci = acj.detect(p, slaves[i], masters[i])
        for k in ("face", "feature", "status"):
            assert np.array_equal(getattr(cb, k)[i], getattr(ci, k))
        assert np.allclose(cb.gap[i], ci.gap, equal_nan=True, atol=1e-14)


def test_scans_on_fewer_lanes_equal_numpy(monkeypatch):
    """The scans go on with the busy slaves gathered into fewer lanes (`_grid.MIN_LANES`
    lowered so that this small graded scene takes that path twice): the same contacts as
    NumPy (both scans)."""
    import arraycontact_jax._grid as jg

    monkeypatch.setattr(jg, "MIN_LANES", 4)
    jax.clear_caches()  # (programs compiled with the default would be reused)
    try:
        s = scenes.graded_surfaces(2**9, ratio=100.0, seed=2)
        p = acj.plan(s.master, s.slave)
        c = acj.detect(p, jnp.asarray(s.slave), jnp.asarray(s.master.points))
        assert not bool(c.overflow)
        _compare(c, ac.detect(s.slave, s.master, backend="numpy"))
    finally:
        jax.clear_caches()


def test_scan_kernel_equals_the_while_loop(monkeypatch):
    """The scans as the Pallas kernel (GPUs; here interpreted): the same contacts as the
    while_loop scans and as NumPy, the same counts (candidates, steps of the busiest slave;
    so the plan's capacities too), on a graded scene; and under vmap. (quad4 too until the
    suite reached 8 minutes here: 19 s, the kernel's face scan without the triangles'
    distances, which tests/test_grid.py's kernel tests check against brute force; quad4's
    contacts through the kernel: the GPU runs of tests/test_jax.py, benchmarks/GPU.md.)"""
    import arraycontact_jax._grid as jg

    s = scenes.graded_surfaces(2**8, ratio=100.0, seed=3, element="tri3")
    xs, xm = jnp.asarray(s.slave), jnp.asarray(s.master.points)
    out = {}
    try:
        for kernel in (False, True):
            monkeypatch.setattr(jg, "INTERPRET", kernel)
            jax.clear_caches()
            p = acj.plan(s.master, s.slave)
            out[kernel] = (p.capacity, acj.detect(p, xs, xm))
        shifted = jnp.stack([xm, xm + jnp.asarray([[0.05, 0.0, 0.1]])])
        both = jax.vmap(acj.detect, in_axes=(None, None, 0))(p, xs, shifted)
        second = acj.detect(p, xs, shifted[1])
    finally:
        jax.clear_caches()
    (cap_w, c_w), (cap_k, c_k) = out[False], out[True]
    assert cap_k == cap_w and not bool(c_k.overflow)
    assert {k: int(v) for k, v in c_k.counts.count.items()} == {
        k: int(v) for k, v in c_w.counts.count.items()
    }
    for k in ("active", "face", "feature", "master_node", "status"):
        assert np.array_equal(getattr(c_k, k), getattr(c_w, k)), k
    # (the float fields come from the same faces by the same code, in two programs that XLA
    # may fuse apart: equal to rounding)
    for k in ("gap", "xi"):
        np.testing.assert_allclose(getattr(c_k, k), getattr(c_w, k), rtol=0, atol=1e-12, err_msg=k)
    _compare(c_k, ac.detect(s.slave, s.master, backend="numpy"))
    for k in ("face", "feature", "status"):
        assert np.array_equal(getattr(both, k)[1], getattr(second, k)), k


def test_candidate_distances_are_the_reference_distances(monkeypatch):
    """The triangles' candidate slots with their distances (measured by the kernel, here
    interpreted, and after the while_loop): each slave's faces are candidate_faces', each
    slot's distance the brute-force reference's from the slave to its face."""
    import arraycontact_jax._grid as jg
    from arraycontact_jax._detect import build_grids, master_geometry

    from arraycontact.reference import _closest_on_faces

    s = scenes.graded_surfaces(2**8, ratio=100.0, seed=5)
    p = acj.plan(s.master, s.slave)
    st, sc, cap = p.static, p.constants, dict(p.capacity)
    xs = jnp.asarray(s.slave - np.asarray(p.origin))
    xm = jnp.asarray(s.master.points - np.asarray(p.origin))
    m = master_geometry(jnp, st.element, p.topology, xm)
    tree = build_grids(jnp, st, m).face
    node, dn, _ = jg.closest_node(jnp, build_grids(jnp, st, m).node, m.nodes_x, xs,
                                  d_max=sc.d_max, tie=sc.tie, slack=sc.slack)  # fmt: skip
    rho = jnp.minimum(dn, sc.d_max) + sc.slack
    _, want, valid_w, _ = jg.candidate_faces(jnp, tree, xs, rho, slack=sc.slack, capacity=cap)
    n, k = len(s.slave), cap["face_candidates"]
    want, valid_w = np.asarray(want).reshape(n, k), np.asarray(valid_w).reshape(n, k)
    for kernel in (False, True):
        monkeypatch.setattr(jg, "INTERPRET", kernel)
        slave, face, valid, dist, counts = jg.candidate_distances(
            jnp, tree, xs, rho, m.nodes_x, m.faces, slack=sc.slack, capacity=cap
        )
        face, valid = np.asarray(face).reshape(n, k), np.asarray(valid).reshape(n, k)
        dist = np.asarray(dist).reshape(n, k)
        assert np.array_equal(valid, valid_w) and valid.sum() > n
        assert np.array_equal(np.where(valid, face, -1), np.where(valid_w, want, -1))
        assert np.isinf(dist[~valid]).all()
        i, j = np.nonzero(valid)
        _, d2 = _closest_on_faces(
            s.master.element, s.slave[i], s.master.points[s.master.faces[face[i, j]]]
        )
        np.testing.assert_allclose(dist[i, j], np.sqrt(d2), rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("which", ["rough", "crumpled"])
def test_quad4_exact_equals_numpy(which):
    """Bilinear faces: the JAX detection projects only the pairs whose distance bounds may
    hold the answer, gathered, and adds the lattice start only where some face is not
    proven convex (the crumpled sheet's warped quads; none on the rough surfaces): the same
    contacts as NumPy, and the reference's."""
    if which == "rough":
        s = scenes.rough_surfaces(2**10, element="quad4", seed=2)
        master, slave, d_max = s.master, s.slave, None
    else:
        s = scenes.crumpled_sheet(2**9, element="quad4")
        master = s.master
        slave = master.points[master.nodes] + 0.3 * master.node_normals[master.nodes]
        d_max = s.params["d_max"]
    p = acj.plan(master, slave, d_max=d_max)
    c = acj.detect(p, jnp.asarray(slave), jnp.asarray(master.points))
    assert not bool(c.overflow)
    r = ac.detect(slave, master, d_max=d_max, backend="numpy")
    _compare(c, r)
    assert_matches_reference(jax.tree.map(np.asarray, c), slave, master)
