"""The JAX back end's search="warp": Warp kernels inside XLA through Warp's FFI."""

import arraycontact_jax as acj
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import test_jax
from test_jax import _compare

import arraycontact as ac
from arraycontact import scenes


@pytest.fixture(autouse=True)
def x64():
    with jax.enable_x64(True):
        yield


def test_no_recompilation_with_the_warp_search():
    test_jax.test_no_recompilation_over_20_steps_of_a_moving_scene(search="warp")


def test_vmap_with_the_warp_search():
    test_jax.test_vmap_over_scenes_equals_one_by_one(search="warp")


def test_warp_search_equals_the_jax_search_with_the_same_gradients():
    """search="warp" (the Warp kernels through Warp's JAX FFI) finds the same contacts as the
    JAX stages, and the smooth outputs built on them have the same gradients."""
    s = scenes.rough_surfaces(2**9, seed=11)
    pj, pw = (acj.plan(s.master, s.slave, search=k) for k in ("jax", "warp"))
    x, m = jnp.asarray(s.slave), jnp.asarray(s.master.points)
    cj, cw = acj.detect(pj, x, m), acj.detect(pw, x, m)
    _compare(cw, jax.tree.map(np.asarray, cj))
    assert not bool(cw.overflow) and np.asarray(cj.active).any()
    gj = jax.grad(_energy(pj), argnums=(0, 1))(x, m)
    gw = jax.grad(_energy(pw), argnums=(0, 1))(x, m)
    for a, b in zip(gj, gw):
        assert np.abs(np.asarray(a)).max() > 0 and np.allclose(a, b, atol=1e-12)
    with pytest.raises(ValueError, match="exact"):
        acj.plan(s.master, s.slave, mode="node", search="warp")


def test_warp_search_on_curved_faces():
    """On quad8 faces: NumPy's contacts (the JAX search's equal them in test_jax), and a finite
    gradient (the smooth outputs are the JAX search's code, checked by finite differences in
    test_jax_gradients)."""

    s = scenes.curved_patch(3, element="quad8", n_slaves=200)
    p = acj.plan(s.master, s.slave, search="warp")
    x, m = jnp.asarray(s.slave), jnp.asarray(s.master.points)
    c = acj.detect(p, x, m)
    assert not bool(c.overflow) and np.asarray(c.active).any()
    _compare(c, ac.detect(s.slave, s.master, d_max=p.d_max, backend="numpy"))
    g = jax.grad(_energy(p), argnums=(0, 1))(x, m)
    assert all(np.isfinite(np.asarray(a)).all() and np.abs(np.asarray(a)).max() > 0 for a in g)


def _energy(p):
    def e(x, m):
        c = acj.detect(p, x, m)
        return jnp.sum(jnp.where(c.active, jnp.minimum(c.gap, 0.1) ** 2, 0.0))

    return e


def test_warp_search_on_a_master_grown_past_the_plan():
    """The Warp search plans no size that motion can outgrow: faces grown 1.5x give the
    contacts of a fresh detection, with no overflow to report."""

    s = scenes.rough_surfaces(2**8, seed=0)
    p = acj.plan(s.master, s.slave, search="warp")
    x = jnp.asarray(s.slave)
    grown = s.master.points * [1.5, 1.5, 1]
    c = acj.detect(p, x, jnp.asarray(grown))
    assert not bool(c.overflow)
    _compare(c, ac.detect(s.slave, s.master.with_points(grown), d_max=p.d_max, backend="numpy"))


@pytest.mark.skipif(
    sum(d.platform == "gpu" for d in jax.devices()) < 2, reason="needs two GPUs (run on the device)"
)
def test_warp_search_on_two_gpus_keeps_one_graph_per_device():
    """On several GPUs each call stages its inputs into the part's plan, whose CUDA graph is
    then one per device whatever buffers XLA hands the call. jax_callable's mode WARP captured
    one per device and call buffers: calls dispatched back to back, each on new buffers, ran
    5-6x slower than waited-for ones on two H200s, and hung past its limit of 32 graphs
    (benchmarks/RESULTS.md). Answers equal one device's on every call."""
    from jax.sharding import Mesh

    s = scenes.rough_surfaces(2**12, seed=3)
    mesh = Mesh(np.array(jax.devices()[:2]), ("space",))
    p = acj.plan(s.master, s.slave, search="warp", mesh=mesh)
    one = acj.plan(s.master, s.slave, search="warp")
    x, m = jnp.asarray(s.slave), jnp.asarray(s.master.points)
    moved = [(x + 1e-4 * k, m - 1e-4 * k) for k in range(8)]  # all alive: new buffers each
    answers = [acj.detect(p, a, b) for a, b in moved]  # dispatched back to back
    for (a, b), c in zip(moved, answers):
        _compare(c, jax.tree.map(np.asarray, acj.detect(one, a, b)))
    assert all(len(q.graph_of) == 1 for q in p.local.search.plans)


@pytest.mark.skipif(
    sum(d.platform == "gpu" for d in jax.devices()) < 2, reason="needs two GPUs (run on the device)"
)
@pytest.mark.parametrize("search", ["warp", "jax"])
def test_self_contact_on_two_gpus_equals_one_device(search):
    """Self-contact on two GPUs. The Warp search: each call stages the part's points into its
    plan (the slaves are the part's own nodes, gathered by the kernels). Either search: the
    plan's halos come from the GPU's scan kernel over a tree with normal boxes (it once read
    their entries 9 rows apart: most rows wrong, with either search). Calls back to back,
    each equal to one device's and to NumPy's, and the gradients equal one device's."""
    from jax.sharding import Mesh

    s = scenes.spiral_strip(700, element="tri3")
    mesh = Mesh(np.array(jax.devices()[:2]), ("space",))
    p = acj.plan_self(s.master, search=search, mesh=mesh)
    one = acj.plan_self(s.master, search=search)
    _compare(
        acj.detect_self(p, jnp.asarray(s.master.points)),
        ac.detect_self(s.master, d_max=p.d_max, backend="numpy"),
    )
    m = jnp.asarray(s.master.points)
    moved = [m + 1e-4 * k for k in range(4)]
    answers = [acj.detect_self(p, b) for b in moved]
    for b, c in zip(moved, answers):
        _compare(c, jax.tree.map(np.asarray, acj.detect_self(one, b)))

    def grad(q):
        return jax.grad(lambda b: jnp.sum(acj.detect_self(q, b).gap ** 2))(m)

    assert np.allclose(grad(p), grad(one), rtol=1e-10, atol=1e-12)
