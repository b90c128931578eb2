"""The JAX back end's search="warp": Warp kernels inside XLA through Warp's FFI."""

import arraycontact_jax as acj
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import test_jax
from test_jax import _compare

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
    import arraycontact as ac

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
    import arraycontact as ac

    s = scenes.rough_surfaces(2**8, seed=0)
    p = acj.plan(s.master, s.slave, search="warp")
    x = jnp.asarray(s.slave)
    grown = s.master.points * [1.5, 1.5, 1]
    c = acj.detect(p, x, jnp.asarray(grown))
    assert not bool(c.overflow)
    _compare(c, ac.detect(s.slave, s.master.with_points(grown), d_max=p.d_max, backend="numpy"))


def test_warp_search_keeps_every_graph_it_captured():
    """On several GPUs the search's jax_callable captures a graph per device and call buffers;
    past a limit it destroyed the oldest inside the call, on the device's thread, which hung
    calls dispatched back to back on two H200s (benchmarks/RESULTS.md, run s42x2b). The plan's
    callable must keep them (no limit), on the CPU as anywhere."""
    s = scenes.rough_surfaces(2**7, seed=3)
    p = acj.plan(s.master, s.slave, search="warp")
    assert p.search.call.graph_cache_max is None
