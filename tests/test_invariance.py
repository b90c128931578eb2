"""Property-based invariances: translation, rotation, scaling, permutation of nodes and faces."""

import functools

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from test_detect import random_scene

import arraycontact as ac
from arraycontact.reference import _closest_on_faces

MASTER, SLAVE = random_scene(7, "tri3", n=5)
MASTER_Q, SLAVE_Q = random_scene(8, "quad4", n=4)


@functools.cache
def _base(backend, element):
    """The untransformed scene's contacts (computed when first needed, not at collection:
    every pytest-xdist worker collects this file, one of them runs it)."""
    m, s = (MASTER, SLAVE) if element == "tri3" else (MASTER_Q, SLAVE_Q)
    return ac.detect(s, m, backend=backend)


def _rotation(seed):
    q, r = np.linalg.qr(np.random.default_rng(seed).normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def _same(c, base, master, slave, scale=1.0):
    L = master.longest_edge
    assert np.array_equal(c.active, base.active)
    a = c.active
    assert np.allclose(c.distance[a], scale * base.distance[a], rtol=1e-9, atol=1e-9 * L)
    assert np.allclose(c.gap[a], scale * base.gap[a], rtol=1e-9, atol=1e-9 * L)
    # Equidistant faces may be renumbered: the chosen face is at the minimal distance.
    _, d2 = _closest_on_faces(master.element, slave[a], master.points[master.faces[c.face[a]]])
    assert np.allclose(np.sqrt(d2), c.distance[a], atol=1e-9 * L)


transforms = st.tuples(
    st.integers(0, 2**31 - 1),
    st.floats(-3, 3),
    st.floats(-3, 3),
    st.sampled_from(["tri3", "quad4"]),
)


def _check(backend, seed, log_shift, log_scale, element):
    master, slave = (MASTER, SLAVE) if element == "tri3" else (MASTER_Q, SLAVE_Q)
    base = _base(backend, element)
    rng = np.random.default_rng(seed)
    rot = _rotation(seed)
    scale = 10.0**log_scale
    shift = rng.normal(size=3) * 10.0**log_shift * master.longest_edge
    # Rigid motion and scaling.
    m = ac.Surface(scale * master.points @ rot.T + shift, master.faces, element)
    s = scale * slave @ rot.T + shift
    c = ac.detect(s, m, backend=backend)
    _same(c, base, m, s, scale)
    assert np.allclose(c.normal[c.active], base.normal[base.active] @ rot.T, atol=1e-8)
    # Permutation of nodes, faces and slaves.
    pn = rng.permutation(len(master.points))
    inv = np.argsort(pn)
    pf = rng.permutation(master.n_faces)
    ps = rng.permutation(len(slave))
    m = ac.Surface(master.points[pn], inv[master.faces[pf]], element)
    c = ac.detect(slave[ps], m, backend=backend)
    back = np.empty_like(ps)
    back[ps] = np.arange(len(ps))
    c = ac.Contacts(
        **{
            k: (v[back] if isinstance(v, np.ndarray) and len(v) == len(ps) else v)
            for k, v in c.__dict__.items()
        }
    )
    _same(c, base, m, slave)


@settings(max_examples=12, deadline=None)
@given(transforms)
def test_invariances_numpy(t):
    _check("numpy", *t)


@settings(max_examples=3, deadline=None)
@given(transforms)
def test_invariances_jax(t):
    _check("jax", *t)
