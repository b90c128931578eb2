"""Detection over several devices: the RCB partition (arraycontact.partition), Warp plans per
part, and the JAX sharded plan on four CPU devices (sharding_checks.py, in a child process:
XLA fixes the number of host devices when it starts)."""

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import arraycontact as ac
from arraycontact import scenes


def _within(master, x, reach):
    """Faces some point of which lies within `reach` of a point x (brute force over each
    face's nodes and interior samples: a subset of the faces truly within reach)."""
    xe = master.points[master.faces]
    w = np.array([[1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1], [2, 1, 1], [1, 2, 1], [1, 1, 2]])
    samples = np.einsum("sk,fkd->fsd", w / w.sum(1, keepdims=True), xe[:, :3])
    return np.linalg.norm(samples - x, axis=-1).min(1) <= reach


@pytest.mark.parametrize("n_parts", [1, 2, 3, 5])
def test_partition_owns_each_slave_once_and_its_halo_holds_every_face_in_reach(n_parts):
    s = scenes.rough_surfaces(2**10, seed=11)
    part = ac.partition(s.master, s.slave, n_parts)
    assert part.slave_part.shape == (len(s.slave),)
    assert set(np.unique(part.slave_part)) == set(range(n_parts))
    assert len(part.cuts) == n_parts - 1
    # The cells tile space: each slave lies in its part's cell.
    lo, hi = part.regions[part.slave_part, 0], part.regions[part.slave_part, 1]
    assert ((s.slave >= lo) & (s.slave <= hi)).all()
    # Unit weights: the parts' weights within one item of an even share.
    share = part.work.sum() * np.array([1 / n_parts] * n_parts)
    assert np.abs(part.work - share).max() <= 1 + 1e-9
    reach = part.d_max + part.margin
    for e in range(n_parts):
        halo = set(part.halo[e].tolist())
        for x in s.slave[part.slave_part == e][::5]:
            assert set(np.flatnonzero(_within(s.master, x, reach)).tolist()) <= halo


def test_uneven_weights_move_the_cut():
    s = scenes.rough_surfaces(2**10, seed=12)
    w = np.where(s.slave[:, 0] < np.median(s.slave[:, 0]), 9.0, 1.0)
    part = ac.partition(s.master, s.slave, 2, weights=w, face_weights=np.zeros(s.master.n_faces))
    heavy = np.bincount(part.slave_part, weights=w, minlength=2)
    assert abs(heavy[0] - heavy[1]) <= 9 + 1e-9
    counts = np.bincount(part.slave_part, minlength=2)
    assert counts.min() < 0.75 * counts.max()  # the light side holds more slaves


def test_a_part_is_the_master_around_its_slaves():
    """Part.master is a Surface of the halo and the ring of faces around it: its node normals
    are the whole master's at every node of a halo face."""
    s = scenes.rough_surfaces(2**10, seed=13)
    part = ac.partition(s.master, s.slave, 3)
    for e in range(3):
        q = part.part(e)
        assert np.array_equal(q.master.points, s.master.points[q.nodes])
        assert np.array_equal(q.nodes[q.master.faces], s.master.faces[q.faces])
        halo_nodes = np.unique(s.master.faces[part.halo[e]])
        local = np.searchsorted(q.nodes, halo_nodes)
        assert np.allclose(q.master.node_normals[local], s.master.node_normals[halo_nodes])


def test_partition_rejects_bad_input():
    s = scenes.rough_surfaces(2**8, seed=1)
    with pytest.raises(ValueError, match="n_parts"):
        ac.partition(s.master, s.slave, 0)
    with pytest.raises(ValueError, match="weights"):
        ac.partition(s.master, s.slave, 2, weights=np.ones(3))
    with pytest.raises(ValueError, match="margin"):
        ac.partition(s.master, s.slave, 2, margin=-1)
    with pytest.raises(ValueError, match="slave_points"):
        ac.partition(s.master, s.slave, 2, self_contact=True)


def test_warp_plans_per_part_give_one_plans_contacts():
    """The Warp recipe of the README: one plan per part (a device each on a GPU machine; the
    CPU device here), the master's points of each part's nodes in, the part's face ids out."""
    import arraycontact_warp as acw

    s = scenes.rough_surfaces(2**10, seed=14)
    p1 = acw.plan(s.master, s.slave, device="cpu", dtype="float64")
    one = acw.detect(p1, s.slave, s.master.points)
    part = ac.partition(s.master, s.slave, 3)
    face = np.full(len(s.slave), -2)
    gap = np.full(len(s.slave), np.nan)
    for e in range(3):
        q = part.part(e)
        p = acw.plan(q.master, s.slave[q.slaves], d_max=part.d_max, device="cpu", dtype="float64")
        out = acw.detect(p, s.slave[q.slaves], s.master.points[q.nodes])
        f = np.asarray(out["face"])
        face[q.slaves] = np.where(f >= 0, q.faces[np.maximum(f, 0)], -1)
        gap[q.slaves] = out["gap"]
    assert np.array_equal(face, one["face"])
    a = one["active"].astype(bool)
    assert np.allclose(gap[a], one["gap"][a], atol=1e-12)


def run_sharding_checks(select: str, expected: int):
    """The checks of sharding_checks.py that `select` (pytest -k) names, in a child process
    with four host devices (XLA fixes the count when it starts; conftest's cheaper
    optimisation flags are in os.environ already). Two halves, one in
    test_sharding_devices.py, so that the suite's two workers take one each."""
    here = Path(__file__).parent
    flags = os.environ.get("XLA_FLAGS", "")
    env = dict(os.environ, XLA_FLAGS=f"--xla_force_host_platform_device_count=4 {flags}")
    r = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-n", "0", "-k", select]
        + [str(here / "sharding_checks.py")],
        cwd=here.parent,
        capture_output=True,
        text=True,
        env=env,
    )
    assert r.returncode == 0, r.stdout[-4000:] + r.stderr[-2000:]
    assert f"{expected} passed" in r.stdout


#: The half of sharding_checks.py this file runs (test_sharding_devices.py: the rest).
HALF = "one_to_four or warp_self_contact"


def test_jax_sharded_detection_on_four_cpu_devices():
    run_sharding_checks(HALF, 4)


def test_sharded_plans_halo_search_marks_what_brute_force_finds(monkeypatch):
    """The sharded plan's halo search (the faces each slave reaches, found in chunks of slaves
    with as many slots as the chunk's largest count: here forced into many chunks of several
    slot counts) marks, for a random grouping of the slaves, exactly the faces whose box lies
    within the reach of a slave of the group (brute force over every slave and face; a band
    of the search's slack left undecided)."""
    import arraycontact_jax as acj
    import jax
    from arraycontact_jax import _shard
    from jax.sharding import Mesh

    from arraycontact._surface import face_boxes

    seen = []
    reached = _shard._Reached

    class Recording(reached):
        def __init__(self, *args):
            seen.append(args)
            super().__init__(*args)

    monkeypatch.setattr(_shard, "_Reached", Recording)
    s = scenes.graded_surfaces(2**9, ratio=30.0, seed=4)
    acj.plan(
        s.master,
        s.slave,
        dtype=np.float32,
        mesh=Mesh(np.array(jax.devices()[:1]), ("x",)),
        axis="x",
    )
    sc, m, x, reach, st = seen[0]
    # Reaches of 0.1-4 % of the plan's (a few faces to a few hundred), one chunk per 64
    # slaves at most and at most 2048 slots a chunk.
    rng = np.random.default_rng(0)
    reach = np.asarray(reach) * rng.uniform(0.001, 0.04, len(s.slave))
    small = reached(sc, m, x, reach, st, chunk=64, slots=2048)
    ks = {k for _, k, _ in small.chunks}
    assert len(small.chunks) >= 8 and len(ks) >= 3, (len(small.chunks), ks)
    group = rng.integers(0, 3, len(s.slave))
    hit = small(group, 3)
    lo, hi = (
        np.asarray(v, float)
        for v in face_boxes(s.master.element, np.asarray(m.nodes_x)[np.asarray(m.faces)])
    )
    xs, rho = np.asarray(x, float), np.asarray(reach, float)
    d = np.linalg.norm(
        np.maximum(lo[None] - xs[:, None], 0) + np.maximum(xs[:, None] - hi[None], 0), axis=-1
    )
    tol = 1e-4 * s.master.longest_edge + 2 * float(sc.slack)
    for g in range(3):
        mine = group == g
        surely = (d[mine] <= rho[mine, None] - tol).any(0)
        maybe = (d[mine] <= rho[mine, None] + tol).any(0)
        assert hit[g][surely].all() and not hit[g][~maybe].any(), g
        assert 0 < surely.sum() < 0.5 * len(lo)
