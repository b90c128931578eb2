"""The NumPy and JAX back ends' trees (arraycontact._grid): groups by Morton prefixes, boxes,
and the JAX scan's closest node, against independent computations."""

import numpy as np
import pytest
from radix import W, grid_points, radix_groups

from arraycontact import _grid


@pytest.mark.parametrize(
    "kind, falls", [("fine_patch", False), ("clusters", True), ("caterpillar", True),
                   ("repeated", False)]
)  # fmt: skip
def test_host_tree_groups_are_the_radix_trees_largest_nodes(kind, falls):
    """`grouping`: on a level whose groups hold 2 entries or more on average, the largest
    nodes of the keys' radix tree holding at most W entries (a top-down split, independent of
    the neighbour rule); elsewhere W consecutive entries (`falls`: level 1 of the clusters and
    of the caterpillar, whose radix groups hold fewer than 2). Entries fill their group's
    slots from its first in order. The tree's boxes are their items' boxes, and the JAX
    scan's closest node is brute force's."""
    import jax
    import jax.numpy as jnp
    from arraycontact_jax._grid import closest_node

    rng = np.random.default_rng(3)
    x = grid_points(kind, rng)
    lo = x.min(0)
    keys = _grid.morton_keys(x, lo, float((x.max(0) - lo).max()))
    order = np.argsort(keys, kind="stable")
    keys = keys[order]
    groups = _grid.grouping(keys)
    ranges = [(p, p + 1) for p in range(len(x))]  # each entry's run of item positions
    nodes, fell = True, False
    for k, slots in enumerate(groups):
        m = len(ranges)
        assert len(slots) % W == 0 and np.array_equal(np.sort(slots[slots >= 0]), np.arange(m))
        got = []
        for g in slots.reshape(-1, W):
            c = int((g >= 0).sum())
            assert c >= 1 and np.array_equal(g[:c], g[0] + np.arange(c)) and (g[c:] < 0).all()
            got.append((ranges[g[0]][0], ranges[g[c - 1]][1]))
        if nodes:  # (after W consecutive entries, the entries are no nodes of the radix tree)
            radix = radix_groups(keys, ranges)
            by_rule = m / len(radix) >= 2
            fell = fell or not by_rule
            want = radix if by_rule else [
                (ranges[e][0], ranges[min(e + W, m) - 1][1]) for e in range(0, m, W)
            ]  # fmt: skip
            if by_rule and W < len(radix) and m <= W * W:
                want = _packed(radix, ranges) or radix
            assert got == want, k
            nodes = by_rule
        ranges = got
    assert len(ranges) == 1 and ranges[0] == (0, len(x)) and fell == falls
    assert len(groups[0]) <= 4 * len(x) + W  # slots: at most 4 an item

    xs = (x - lo)[order]
    tree = _grid.build(np, order, xs, xs, xs, groups=groups)
    for k in range(1, len(tree.lo)):  # a slot's box is the box of its group's slots
        filled = tree.lo[k][:, 0] <= tree.hi[k][:, 0]
        assert np.array_equal(filled, np.asarray(tree.down[k]) >= 0) if k < len(groups) else 1
        below = tree.lo[k - 1].reshape(-1, W, 3)[np.maximum(tree.down[k], 0)].min(1)
        np.testing.assert_array_equal(tree.lo[k][filled], below[filled])
    np.testing.assert_array_equal(tree.lo[-1][0], xs.min(0))
    np.testing.assert_array_equal(tree.hi[-1][0], xs.max(0))
    assert np.array_equal(np.sort(tree.ids[tree.ids >= 0]), np.arange(len(x)))

    q = x[rng.integers(0, len(x), 300)] + rng.normal(size=(300, 3)) * 1e-3 - lo
    d = np.linalg.norm(q[:, None] - (x - lo)[None], axis=-1)
    # Ties: the smallest id within `tie` of the smallest distance; a wide band makes many, and
    # sends slaves whose kept id fell out of the band while another might stay in it to the
    # second scan.
    with jax.enable_x64(True):
        jtree = _grid.build(jnp, jnp.asarray(order, jnp.int32), *(jnp.asarray(xs),) * 3,
                            groups=groups)  # fmt: skip
    for tie in (1e-9 * np.ptp(x), 1e-2 * np.ptp(x)):
        with jax.enable_x64(True):
            node, dist, _ = closest_node(
                jnp,
                jtree,
                None,
                jnp.asarray(q),
                d_max=np.inf,
                tie=tie,
                slack=tie + 1e-9 * np.ptp(x),
            )
        np.testing.assert_allclose(np.asarray(dist), d.min(1), rtol=1e-12, atol=1e-12)
        tied = d <= d.min(1, keepdims=True) + tie
        assert np.array_equal(np.asarray(node), tied.argmax(1))


def test_parts_trees_padded_to_common_levels_keep_their_answers():
    """A sharded plan's parts (arraycontact_jax._shard): each part's tree over its own items,
    grouped by `grouping`, padded to the deepest part's levels and the widest level sizes.
    A shallow part padded so (3 items under a part of 3000) keeps its boxes and the JAX
    scan's closest node is brute force's, in each part."""
    import jax
    import jax.numpy as jnp
    from arraycontact_jax._grid import closest_node
    from arraycontact_jax._shard import _common_levels, _part_tree

    rng = np.random.default_rng(5)
    x = rng.random((3003, 3))
    lo = x.min(0)
    keys = _grid.morton_keys(x, lo, 1.0)
    order = np.argsort(keys, kind="stable")
    rank = np.argsort(order)  # each item's position in the whole tree's order
    parts = [np.sort(order[:3]), np.sort(order[3:])]  # the first 3 items in Morton order
    trees = [_part_tree(rank[p], keys[order]) for p in parts]
    padded = _common_levels([t[1] for t in trees])
    assert len(trees[0][1]) < len(trees[1][1])  # (the case: a shallower part)
    assert [len(s) for s in padded[0]] == [len(s) for s in padded[1]]
    q = rng.random((200, 3))
    for p, (ids, _), groups in zip(parts, trees, padded):
        xs = x[p][ids] - lo
        assert np.all(np.diff(keys[p][ids]) >= 0)  # in Morton order
        tree = _grid.build(np, ids, xs, xs, xs, groups=groups)
        np.testing.assert_array_equal(tree.lo[-1][0], xs.min(0))
        np.testing.assert_array_equal(tree.hi[-1][0], xs.max(0))
        assert np.array_equal(np.sort(tree.ids[tree.ids >= 0]), np.arange(len(p)))
        with jax.enable_x64(True):
            jtree = _grid.build(jnp, jnp.asarray(ids, jnp.int32), *(jnp.asarray(xs),) * 3,
                                groups=groups)  # fmt: skip
            node, dist, _ = closest_node(
                jnp, jtree, None, jnp.asarray(q - lo), d_max=np.inf, tie=1e-12, slack=1e-12
            )
        d = np.linalg.norm(q[:, None] - x[p][None], axis=-1)
        np.testing.assert_allclose(np.asarray(dist), d.min(1), rtol=1e-12, atol=1e-12)
        assert np.array_equal(np.asarray(node), d.argmin(1))


def _packed(groups, ranges):
    """Neighbouring groups (item ranges) merged greedily while their entries (`ranges`, the
    level's entries' item ranges) fit W, if that leaves at most W groups (else None)."""
    starts = [r[0] for r in ranges]
    out = []
    for a, b in groups:
        c = starts.index(b) - starts.index(a) if b in starts else len(starts) - starts.index(a)
        if out and out[-1][2] + c <= W:
            out[-1] = (out[-1][0], b, out[-1][2] + c)
        else:
            out.append((a, b, c))
    return [(a, b) for a, b, _ in out] if len(out) <= W else None


def test_host_tree_top_merges_groups_to_lose_a_level():
    """A level of at most W^2 entries whose radix groups number just past W: neighbouring
    groups merged so that the root comes next (`_top`), where whole radix groups allow it:
    the tree a level shallower than the radix rule alone makes it."""
    rng = np.random.default_rng(5)
    merged = 0
    for _ in range(40):
        # 9-12 tight clusters of 1-7 points far apart: their radix groups, one level.
        sizes = rng.integers(1, 8, rng.integers(9, 13))
        centres = rng.uniform(0, 1, (len(sizes), 3))
        x = np.concatenate([c + 1e-6 * rng.normal(size=(k, 3)) for c, k in zip(centres, sizes)])
        keys = np.sort(_grid.morton_keys(x, x.min(0), float(np.ptp(x, 0).max())))
        ranges = [(p, p + 1) for p in range(len(x))]
        radix = radix_groups(keys, ranges)
        want = _packed(radix, ranges) if len(radix) > W else radix
        groups = _grid.grouping(keys)
        got = [tuple(g[g >= 0]) for g in groups[0].reshape(-1, W)]
        assert [(g[0], g[-1] + 1) for g in got] == (want or radix)
        if len(radix) > W and want:
            merged += 1
            assert len(groups) == 2  # the root's level next
    assert merged >= 5


@pytest.mark.parametrize("normals", [False, True], ids=["plain", "normal_boxes"])
@pytest.mark.parametrize("kind", ["clusters", "repeated"])
def test_scan_kernel_against_brute_force(monkeypatch, kind, normals):
    """The scans as the Pallas kernel (GPUs; interpreted here): the closest node with a wide
    tie band (the second pass too) as brute force's, and without shrinking the reach (the
    sharded plan's halos) every item within the reach, each once. normal_boxes: a tree whose
    entries also hold normal boxes (self-contact's), scanned without the normal test as the
    sharded self-contact plan scans it (the kernel once read such entries 9 rows apart: on
    GPUs the plan's halos missed most faces)."""
    import arraycontact_jax._grid as jg
    import jax
    import jax.numpy as jnp

    monkeypatch.setattr(jg, "INTERPRET", True)
    rng = np.random.default_rng(4)
    x = grid_points(kind, rng)
    lo = x.min(0)
    keys = _grid.morton_keys(x, lo, float((x.max(0) - lo).max()))
    order = np.argsort(keys, kind="stable")
    groups = _grid.grouping(keys[order])
    xs = (x - lo)[order]
    q = x[rng.integers(0, len(x), 100)] + rng.normal(size=(100, 3)) * 1e-3 - lo
    d = np.linalg.norm(q[:, None] - (x - lo)[None], axis=-1)
    tie, reach = 1e-2 * np.ptp(x), 0.05 * np.ptp(x)
    within = d <= reach
    k = int(within.sum(1).max())
    with jax.enable_x64(True):
        nb = None
        if normals:  # any unit vectors: the scans here do not test them
            nv = rng.normal(size=xs.shape)
            nv = jnp.asarray(nv / np.linalg.norm(nv, axis=1, keepdims=True))
            nb = (nv, nv)
        jtree = _grid.build(jnp, jnp.asarray(order, jnp.int32), *(jnp.asarray(xs),) * 3,
                            normals=nb, groups=groups)  # fmt: skip
        assert bool(jtree.nlo) == normals
        node, dist, _ = jg.closest_node(
            jnp, jtree, None, jnp.asarray(q), d_max=np.inf, tie=tie, slack=tie + 1e-9 * np.ptp(x)
        )
        rho = jnp.full(len(q), reach)
        _, item, valid, counts = jg.candidate_faces(
            jnp, jtree, jnp.asarray(q), rho, slack=0.0, capacity={"face_candidates": k},
            shrink=False,
        )  # fmt: skip
    np.testing.assert_allclose(np.asarray(dist), d.min(1), rtol=1e-12, atol=1e-12)
    tied = d <= d.min(1, keepdims=True) + tie
    assert np.array_equal(np.asarray(node), tied.argmax(1))
    assert int(counts["face_candidates"]) == k
    item, valid = np.asarray(item).reshape(len(q), k), np.asarray(valid).reshape(len(q), k)
    for i in range(len(q)):
        got = np.sort(item[i][valid[i]])
        assert np.array_equal(got, np.flatnonzero(within[i])), i
