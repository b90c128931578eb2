"""Detection over several devices (arraycontact_jax.plan(..., mesh=)): run by test_sharding.py
in a child process with XLA_FLAGS=--xla_force_host_platform_device_count=4 (four CPU devices).

The expected answers are the one-device plan's, checked against the brute-force reference in
test_jax and test_self_contact."""

import arraycontact_jax as acj
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

import arraycontact as ac
from arraycontact import scenes

INTS = ("active", "face", "feature", "master_node", "status", "slave_ids")
FLOATS = ("gap", "distance", "xi", "point", "normal")


@pytest.fixture(autouse=True)
def x64():
    assert len(jax.devices()) == 4, "run with --xla_force_host_platform_device_count=4"
    with jax.enable_x64(True):
        yield


def _mesh(n):
    return Mesh(np.array(jax.devices()[:n]), ("space",))


def _loss(c):
    # Every differentiable output of the active rows, so that each one's gradient is checked.
    a = c.active
    g = jnp.where(a, c.gap, 0)
    x = jnp.where(a[:, None], c.point, 0) + jnp.where(a[:, None], c.normal, 0)
    return jnp.sum(g**2) + jnp.sum(jnp.sin(x)) + jnp.sum(jnp.where(a[:, None], c.xi, 0) ** 2)


def _same(c, r):
    """Sharded contacts `c` equal one device's `r`: integers exactly, floats to rounding (the
    node normals sum the same faces, in an order XLA may change)."""
    for k in INTS:
        assert np.array_equal(np.asarray(getattr(c, k)), np.asarray(getattr(r, k))), k
    for k in FLOATS:
        a, b = np.asarray(getattr(c, k)), np.asarray(getattr(r, k))
        assert np.array_equal(np.isnan(a), np.isnan(b)), k
        assert np.allclose(np.nan_to_num(a), np.nan_to_num(b), rtol=1e-12, atol=1e-12), k


SCENES = {
    "rough": lambda: scenes.rough_surfaces(2**10, seed=5),
    "graded": lambda: scenes.graded_surfaces(2**10, ratio=30.0, seed=6),
    "spiral": lambda: scenes.spiral_strip(700, element="tri3"),
}


# Device counts, a compilation each (the same sharded program for any count; about 7 s each on
# the 2-core CI machine): every count from 1 to 4 once over the three scenes, each with its
# gradients (the Warp-search tests below take 3 and 4 on the graded scene, 3 on the spiral).
COUNTS = {"rough": (1, 3), "graded": (4,), "spiral": (2,)}


@pytest.mark.parametrize("name", sorted(SCENES))
def test_one_to_four_devices_give_one_devices_contacts_and_gradients(name):
    s = SCENES[name]()
    spiral = name == "spiral"

    def run(p, slave, pts):
        if spiral:
            return acj.detect_self(p, pts)
        return acj.detect(p, slave, pts)

    def value_and_grads(p):
        def f(slave, pts):
            c = run(p, slave, pts)
            return _loss(c), c

        (_, c), g = jax.jit(jax.value_and_grad(f, argnums=(0, 1), has_aux=True))(
            jnp.asarray(s.slave), jnp.asarray(s.master.points)
        )
        return c, g

    if spiral:
        one = acj.plan_self(s.master, dtype=np.float64)
    else:
        one = acj.plan(s.master, s.slave, dtype=np.float64)
    r, g_r = value_and_grads(one)
    assert int(np.asarray(r.active).sum()) > 0.5 * len(r.active)
    for n in COUNTS[name]:
        if spiral:
            p = acj.plan_self(s.master, dtype=np.float64, mesh=_mesh(n))
        else:
            p = acj.plan(s.master, s.slave, dtype=np.float64, mesh=_mesh(n))
        c, g = value_and_grads(p)
        assert not bool(c.overflow), n
        _same(c, r)
        for a, b in zip(g, g_r):
            scale = float(np.abs(np.asarray(b)).max())
            assert np.allclose(np.asarray(a), np.asarray(b), rtol=1e-10, atol=1e-10 * scale), n
        if n > 1:  # every device got a share of the slaves
            assert min(dict(p.counts)["slaves"]) > 0


@pytest.mark.parametrize(
    "make, mode, n",
    [
        (lambda: scenes.rough_surfaces(2**10, seed=5), "node", 3),
        (lambda: scenes.rough_layers(2**8, quadratic=True, seed=1), "exact", 2),
    ],
    ids=["node_mode", "tri6"],
)
def test_node_mode_and_curved_faces(make, mode, n):
    s = make()
    r = acj.detect(
        acj.plan(s.master, s.slave, dtype=np.float64, mode=mode), s.slave, s.master.points
    )
    p = acj.plan(s.master, s.slave, dtype=np.float64, mode=mode, mesh=_mesh(n))
    c = acj.detect(p, s.slave, s.master.points)
    assert not bool(c.overflow)
    _same(c, r)


def test_warp_search_on_each_device():
    """search="warp": each device runs its part's Warp plan (on the CPU, the four JAX devices
    are one Warp device: the part's index picks the plan). The one-device Warp search's
    contacts on 3 (with the gradients, an uneven split) and 4 devices; motion beyond the
    margin is overflow and update_plan keeps the Warp search."""
    s = SCENES["graded"]()
    one = acj.plan(s.master, s.slave, dtype=np.float64, search="warp")

    def value_and_grads(p):
        def f(slave, pts):
            c = acj.detect(p, slave, pts)
            return _loss(c), c

        (_, c), g = jax.jit(jax.value_and_grad(f, argnums=(0, 1), has_aux=True))(
            jnp.asarray(s.slave), jnp.asarray(s.master.points)
        )
        return c, g

    r, g_r = value_and_grads(one)
    assert int(np.asarray(r.active).sum()) > 0.5 * len(r.active)
    for n in (3, 4):
        p = acj.plan(s.master, s.slave, dtype=np.float64, search="warp", mesh=_mesh(n))
        assert len(p.local.search.plans) == n
        if n == 3:  # the gradients on the uneven split
            c, g = value_and_grads(p)
            for a, b in zip(g, g_r):
                scale = float(np.abs(np.asarray(b)).max())
                assert np.allclose(np.asarray(a), np.asarray(b), rtol=1e-10, atol=1e-10 * scale)
        else:
            c = acj.detect(p, s.slave, s.master.points)
        assert not bool(c.overflow), n
        _same(c, r)
    shift = s.slave + np.array([1.5 * p.partition.margin, 0, 0])
    c = acj.detect(p, shift, s.master.points)
    assert bool(c.overflow)
    q = acj.update_plan(p, c, shift, s.master.points)
    assert q.local.search is not None and q.mesh is p.mesh
    c = acj.detect(q, shift, s.master.points)
    assert not bool(c.overflow)
    _same(c, acj.detect(acj.plan(s.master, shift, dtype=np.float64), shift, s.master.points))


def test_warp_self_contact_on_each_device():
    """search="warp" in self-contact: each part's Warp plan answers for every node of its
    surface, and the part's own slaves are taken from those rows; the one-device answer and
    gradients on 3 devices."""
    s = SCENES["spiral"]()

    def value_and_grad(p):
        def f(pts):
            c = acj.detect_self(p, pts)
            return _loss(c), c

        (_, c), g = jax.jit(jax.value_and_grad(f, has_aux=True))(jnp.asarray(s.master.points))
        return c, np.asarray(g)

    r, g_r = value_and_grad(acj.plan_self(s.master, dtype=np.float64, search="warp"))
    assert int(np.asarray(r.active).sum()) > 0
    for n in (3,):
        p = acj.plan_self(s.master, dtype=np.float64, search="warp", mesh=_mesh(n))
        c, g = value_and_grad(p)
        assert not bool(c.overflow), n
        _same(c, r)
        assert np.allclose(g, g_r, rtol=1e-10, atol=1e-10 * np.abs(g_r).max()), n


def test_all_contact_in_one_corner_still_balances():
    """The slaves over most of the master are beyond d_max; those over one corner are close.
    Each device's work in the JAX search (a lane per slave, a tree entry per local face: the
    plan's own counts) is within 20 % of the mean, though the faces the slaves reach are all
    in the corner."""
    s = scenes.rough_surfaces(2**12, seed=7, gap=0.5)
    slave = s.slave.copy()
    lo, hi = s.master.node_box
    corner = (slave[:, 0] < lo[0] + 0.2 * (hi - lo)[0]) & (slave[:, 1] < lo[1] + 0.2 * (hi - lo)[1])
    slave[~corner, 2] += 20 * s.master.longest_edge
    p = acj.plan(s.master, slave, dtype=np.float64, mesh=_mesh(4))
    k = dict(p.counts)
    work = np.add(k["slaves"], k["local_faces"])
    assert sum(k["candidates"]) > 0
    assert work.max() <= 1.2 * work.mean(), k
    # The part holding the reached faces holds fewer slaves.
    corner_part = int(np.argmax(k["local_faces"]))
    assert k["slaves"][corner_part] < 0.9 * np.mean(k["slaves"]), k
    c = acj.detect(p, slave, s.master.points)
    r = acj.detect(acj.plan(s.master, slave, dtype=np.float64), slave, s.master.points)
    _same(c, r)


def test_motion_beyond_the_margin_is_overflow_and_update_plan_partitions_again():
    s = scenes.rough_surfaces(2**10, seed=8)
    mesh = _mesh(3)
    p = acj.plan(s.master, s.slave, dtype=np.float64, mesh=mesh)
    margin = p.partition.margin
    one = acj.plan(s.master, s.slave, dtype=np.float64)
    rng = np.random.default_rng(0)
    # Within the margin (slaves and master together): no overflow, one device's answer.
    d = rng.normal(size=s.slave.shape)
    d *= 0.4 * margin / np.linalg.norm(d, axis=1).max()
    m = s.master.points.copy()
    m[:, :2] += 0.4 * margin * np.array([0.6, 0.8])
    c = acj.detect(p, s.slave + d, m)
    assert not bool(c.overflow)
    assert float(c.counts.count["halo_motion"]) <= margin
    _same(c, acj.detect(one, s.slave + d, m))
    # Beyond it: reported, and update_plan's new partition gives one device's answer.
    shift = s.slave + np.array([1.5 * margin, 0, 0])
    c = acj.detect(p, shift, s.master.points)
    assert bool(c.overflow)
    assert float(c.counts.count["halo_motion"]) > margin
    q = acj.update_plan(p, c, shift, s.master.points)
    assert q is not p and q.mesh is mesh
    c = acj.detect(q, shift, s.master.points)
    assert not bool(c.overflow)
    r = acj.detect(acj.plan(s.master, shift, dtype=np.float64), shift, s.master.points)
    _same(c, r)


def test_sharded_or_replicated_inputs_give_sharded_outputs():
    s = scenes.rough_surfaces(2**10, seed=9)
    mesh = _mesh(4)
    p = acj.plan(s.master, s.slave, dtype=np.float64, mesh=mesh)
    rows = NamedSharding(mesh, P("space"))
    n_m = len(s.master.points)
    assert len(s.slave) % 4 == 0 and n_m % 4 == 0
    sharded = acj.detect(p, jax.device_put(s.slave, rows), jax.device_put(s.master.points, rows))
    replicated = acj.detect(
        p,
        jax.device_put(s.slave, NamedSharding(mesh, P())),
        jax.device_put(s.master.points, NamedSharding(mesh, P())),
    )
    _same(sharded, replicated)
    assert len(sharded.gap.sharding.device_set) == 4


def test_uneven_rows_give_a_replicated_answer_by_one_all_gather():
    """Rows not a multiple of the devices cannot be sharded in JAX's equal blocks: the answer
    is replicated, every part's rows packed into one all_gather (XLA had replicated the
    sharded result by an all_gather a field), and equals one device's."""
    s = scenes.rough_surfaces(2**10, seed=9)
    slave = s.slave[:1001]
    r = acj.detect(acj.plan(s.master, slave, dtype=np.float64), slave, s.master.points)
    p = acj.plan(s.master, slave, dtype=np.float64, mesh=_mesh(2))
    c = acj.detect(p, slave, s.master.points)
    _same(c, r)
    assert c.gap.sharding.is_fully_replicated and len(c.gap.sharding.device_set) == 2
    hlo = jax.jit(acj.detect).lower(p, slave, s.master.points).compile().as_text()
    assert hlo.count(" all-gather(") == 1


def test_uneven_master_points_alone_give_one_devices_contacts_and_gradients():
    """The master's points alone no multiple of the devices (an unused point added): each
    part takes its nodes from the replicated points, the slaves are exchanged as ever, and
    the answer stays sharded; contacts and gradients equal one device's."""
    s = scenes.rough_surfaces(2**9, seed=4)
    pts = np.vstack([s.master.points, [[50.0, 50.0, 50.0]]])
    master = ac.Surface(pts, s.master.faces, s.master.element.name)

    def value_and_grads(p):
        def f(x, y):
            c = acj.detect(p, x, y)
            return _loss(c), c

        return jax.jit(jax.value_and_grad(f, argnums=(0, 1), has_aux=True))(
            jnp.asarray(s.slave), jnp.asarray(pts)
        )

    (_, r), g_r = value_and_grads(acj.plan(master, s.slave, dtype=np.float64))
    p = acj.plan(master, s.slave, dtype=np.float64, mesh=_mesh(2))
    assert len(s.slave) % 2 == 0 and len(pts) % 2 == 1
    (_, c), g = value_and_grads(p)
    _same(c, r)
    assert not c.gap.sharding.is_fully_replicated
    for a, b in zip(g, g_r):
        scale = float(np.abs(np.asarray(b)).max())
        assert scale > 0 and np.allclose(np.asarray(a), np.asarray(b), atol=1e-10 * scale)


def test_bad_input_is_named():
    s = scenes.rough_surfaces(2**8, seed=1)
    with pytest.raises(ValueError, match="axis"):
        acj.plan(s.master, s.slave, mesh=Mesh(np.array(jax.devices()[:2]), ("x",)))
    p = acj.plan(s.master, s.slave, dtype=np.float64, mesh=_mesh(2))
    with pytest.raises(ValueError, match="rows"):
        acj.detect(p, s.slave[:-1], s.master.points)
    with pytest.raises(ValueError, match="detect_self"):
        acj.detect_self(p, s.master.points)
    with pytest.raises(ValueError, match="margin"):
        acj.plan(s.master, s.slave, mesh=_mesh(2), margin=-1.0)


def test_partition_of_the_sharded_plan_is_arraycontacts():
    """The plan's cuts are ac.partition's on the same weights: the Warp helper's parts."""
    s = scenes.rough_surfaces(2**10, seed=10)
    p = acj.plan(s.master, s.slave, dtype=np.float64, mesh=_mesh(4))
    part = p.partition
    q = ac.partition(s.master, s.slave, 4, d_max=p.d_max, margin=part.margin)
    assert part.n_parts == q.n_parts == 4 and len(part.cuts) == 3
    assert np.array_equal(np.bincount(part.slave_part, minlength=4), dict(p.counts)["slaves"])
    # Each halo holds every face within min(dn + margin, d_max) + margin of each of its
    # slaves, dn the slave's closest master node within d_max (brute force over the faces'
    # sample points: a face some point of which is that close).
    xe = s.master.points[s.master.faces]
    w = np.array([[1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1], [2, 1, 1], [1, 2, 1], [1, 1, 2]])
    samples = np.einsum("sk,fkd->fsd", w / w.sum(1, keepdims=True), xe)
    nodes = s.master.points[s.master.nodes]
    m = part.margin
    for e in range(4):
        mine = s.slave[part.slave_part == e]
        near = set()
        for x in mine[::7]:
            dn = np.linalg.norm(nodes - x, axis=1).min()
            reach = min(dn + m, p.d_max) + m if dn <= p.d_max else p.d_max + m
            d = np.linalg.norm(samples - x, axis=-1).min(1)
            near.update(np.flatnonzero(d <= reach).tolist())
        assert near <= set(part.halo[e].tolist()), e
