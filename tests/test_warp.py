"""The Warp back end against the NumPy back end and the reference (Warp's CPU device in CI; the
same tests capture and replay CUDA graphs where a GPU is present)."""

from typing import Any

import arraycontact_warp as acw
import numpy as np
import pytest
import warp as wp
from arraycontact_warp import _grid as warp_grid
from arraycontact_warp._closest_node import closest_node as _closest_node
from conftest import assert_matches_reference, set_node_search
from radix import grid_points, radix_groups

import arraycontact as ac
from arraycontact import scenes
from arraycontact._backends import quiet_warp
from arraycontact._detect import TIE_RTOL

quiet_warp()
DEVICE = "cuda" if wp.is_cuda_available() else "cpu"

SCENES = {
    "rough_tri3": lambda: scenes.rough_surfaces(2**10, seed=0),
    "rough_quad4": lambda: scenes.rough_surfaces(2**9, seed=1, element="quad4"),
    "layers_tri6": lambda: scenes.rough_layers(2**7, quadratic=True, seed=1),
    "patch_quad8": lambda: scenes.curved_patch(4, element="quad8", n_slaves=300),
    "patch_quad9": lambda: scenes.curved_patch(4, element="quad9", n_slaves=300),
    "sphere_quad4": lambda: scenes.sphere_on_plane(2**9),
    "graded_tri3": lambda: scenes.graded_surfaces(2**10, ratio=1000.0),
    "patch_tri3": lambda: scenes.fine_patch(12, ratio=1000.0),
}


def _same_as_numpy(o, r, L, rows=None):
    """Warp outputs `o` equal NumPy's contacts `r` on `rows` (default: the active ones)."""
    act = o["active"].astype(bool)
    assert np.array_equal(act, r.active)
    a = r.active if rows is None else rows
    for k in ("face", "feature"):
        assert np.array_equal(o[k][a], getattr(r, k)[a]), k
    for k in ("master_node", "status"):
        assert np.array_equal(o[k], getattr(r, k)), k
    for k in ("gap", "distance"):
        assert np.abs(o[k][a] - getattr(r, k)[a]).max() <= 2e-5 * L, k
    # Points agree to the float32 KKT tolerance (1e-4 in natural coordinates) times the size.
    assert np.abs(o["point"][a] - r.point[a]).max() <= 2e-4 * L
    # Normals: the pseudo-normal of the feature (computed per vertex slave in Warp) on the
    # surface, else the direction to the slave, whose float32 rounding grows as 1 / distance.
    d = r.distance[a]
    tol = 1e-3 + np.where(d <= 1e-5 * L, 0.0, 2e-6 * L / np.maximum(d, 1e-30))
    assert (np.abs(o["normal"][a] - r.normal[a]).max(1) <= tol).all()
    assert np.isnan(o["gap"][~a]).all() and (o["face"][~a] == -1).all()
    assert (o["face"][a] >= 0).all()


@pytest.mark.parametrize("name", sorted(SCENES))
def test_warp_equals_numpy_float32_and_the_reference(name, node_search):
    s = SCENES[name]()
    p = acw.plan(s.master, s.slave, device=DEVICE)
    o = acw.detect(p, s.slave, s.master.points)
    r = ac.detect(s.slave, s.master, dtype=np.float32, backend="numpy")
    _same_as_numpy(o, r, s.master.longest_edge)
    if name in ("rough_tri3", "layers_tri6"):  # the others: equal to NumPy, tested there
        c = ac.detect(s.slave, s.master, backend="warp")
        assert_matches_reference(c, s.slave, s.master, dtype=np.float32)


@pytest.mark.parametrize("name", ["rough_tri3", "patch_quad8", "graded_tri3"])
def test_warp_float64_equals_numpy_float64_and_the_reference(name, node_search):
    """The float64 twin of the kernels (the same source, `_real`) matches NumPy in float64."""
    s = SCENES[name]()
    p = acw.plan(s.master, s.slave, device=DEVICE, dtype="float64")
    o = acw.detect(p, s.slave, s.master.points)
    assert o["gap"].dtype == np.float64 and o["xi"].dtype == np.float64
    r = ac.detect(s.slave, s.master, dtype=np.float64, backend="numpy")
    assert np.array_equal(o["active"].astype(bool), r.active)
    for k in ("face", "feature", "master_node", "status"):
        assert np.array_equal(o[k], getattr(r, k)), k
    a, L = r.active, s.master.longest_edge
    assert np.abs(o["gap"][a] - r.gap[a]).max() <= 1e-12 * L
    # Points well within 1e-9 of the size: both projections meet the float64 KKT tolerance
    # (1e-12 in natural coordinates).
    assert np.abs(o["point"][a] - r.point[a]).max() <= 1e-9 * L
    c = ac.detect(s.slave, s.master, backend="warp", dtype="float64")
    assert_matches_reference(c, s.slave, s.master, dtype=np.float64)


def test_slave_order_does_not_change_the_result():
    """The Morton order of the slaves (at plan time by default, or each detect) only reorders
    the work: every output equals the unsorted run's, on slaves given in a random order, also
    once they moved away from the points the plan ordered."""
    s = scenes.rough_surfaces(2**10, seed=9)
    x = s.slave[np.random.default_rng(1).permutation(len(s.slave))]
    moved = x + np.random.default_rng(2).normal(scale=0.3, size=x.shape)
    for y in (x, moved):
        outs = [
            acw.detect(acw.plan(s.master, x, device=DEVICE, sort_slaves=v), y, s.master.points)
            for v in ("plan", "detect", False)
        ]
        for o in outs[1:]:
            for k in outs[0]:
                assert np.array_equal(outs[0][k], o[k], equal_nan=True), k
    with pytest.raises(ValueError, match="sort_slaves"):
        acw.plan(s.master, x, sort_slaves="never")


def test_the_box_of_the_morton_cells_does_not_change_the_result():
    """`box` (a sharded plan's parts take the scene's): a wider box (coarser cells, more
    slack) or one smaller than the points (those outside take its border cells) only changes
    the trees and the slaves' order: every output equals the default plan's, in one frame."""
    s = scenes.graded_surfaces(2**10, ratio=30.0, seed=4)
    frame = s.slave.min(0) - 1.0
    lo = np.minimum(s.slave.min(0), s.master.points.min(0))
    hi = np.maximum(s.slave.max(0), s.master.points.max(0))
    base = acw.detect(
        acw.plan(s.master, s.slave, device=DEVICE, frame=frame), s.slave, s.master.points
    )
    for box in ((lo - 5.0, hi + [0.0, 0.0, 300.0]), (lo + 0.3 * (hi - lo), hi - 0.3 * (hi - lo))):
        p = acw.plan(s.master, s.slave, device=DEVICE, frame=frame, box=box)
        assert p.constants.quantum == pytest.approx(float((box[1] - box[0]).max()) / 1024)
        o = acw.detect(p, s.slave, s.master.points)
        for k in base:
            assert np.array_equal(base[k], o[k], equal_nan=True), k
    with pytest.raises(ValueError, match="box must be"):
        acw.plan(s.master, s.slave, box=(hi, lo))
    with pytest.raises(ValueError, match="box must be"):
        acw.plan(s.master, s.slave, box=(lo, hi, hi))


@pytest.mark.parametrize("n_fan", [5, 12])
def test_tie_rule_at_a_vertex_of_many_faces(n_fan, node_search):
    """Slaves above the centre of a fan of triangles (ids shuffled) are equidistant from every
    face: the smallest id wins. 12 faces overflow the first scan's band of 8, so the second
    scan decides; 5 fit in it."""
    ang = np.linspace(0, 2 * np.pi, n_fan, endpoint=False)
    pts = np.r_[[[0.0, 0.0, 0.0]], np.c_[np.cos(ang), np.sin(ang), 0 * ang]]
    faces = np.array([[0, 1 + i, 1 + (i + 1) % n_fan] for i in range(n_fan)])
    faces = faces[np.random.default_rng(n_fan).permutation(n_fan)]
    master = ac.Surface(pts, faces, "tri3")
    rng = np.random.default_rng(3)
    slaves = np.c_[rng.normal(scale=1e-9, size=(50, 2)), rng.uniform(-0.5, 0.5, 50)]
    p = acw.plan(master, slaves, device=DEVICE, d_max=2.0)
    o = acw.detect(p, slaves, master.points)
    r = ac.reference.closest_points(slaves, master)
    assert (r.face == 0).all()  # every face within the tie tolerance: the smallest id
    assert np.array_equal(o["face"], r.face)


def test_tie_rule_when_the_chosen_face_leaves_the_band():
    """Three parallel faces under a slave, met in id order (one cell), at distances x + 0.9 tie,
    x and x - 0.2 tie: the third pushes the first out of the tie band while the second stays,
    so the first scan cannot apply the tie rule alone; the answer is the second (id 1), as
    NumPy's global selection says."""
    tri = np.array([[-0.5, -0.5, 0], [0.5, -0.5, 0], [-0.5, 0.5, 0.0]]) + [0.2, 0.2, 0]

    x, tie = 0.5, TIE_RTOL[np.dtype(np.float32)] * np.sqrt(2)  # float32 tie, longest edge
    pts = np.concatenate([tri + [0, 0, -z] for z in (x + 0.9 * tie, x, x - 0.2 * tie)])
    master = ac.Surface(pts, np.arange(9).reshape(3, 3), "tri3")
    slave = np.zeros((1, 3))
    o = acw.detect(acw.plan(master, slave, device=DEVICE, d_max=2.0), slave, master.points)
    r = ac.detect(slave, master, dtype=np.float32, d_max=2.0, backend="numpy")
    assert r.face[0] == 1 and o["face"][0] == 1


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_a_projection_kept_by_the_face_scan_is_the_chosen_faces(dtype):
    """Off a GPU the finish kernel takes a quad's projection from the face scan where the scan
    stored the chosen face's (Kept; on a GPU this checks the scans without it). Near-ties make
    the scan go back to an earlier face of the tie band, whose projection it did not store: a
    flat quad4 grid whose nodes lie within 2 ties of the plane, slaves above its vertices
    with offsets of the tie band's scale. Faces and
    points equal NumPy's (taking the stored projection whatever face it was for moves points
    by a face width; features are not compared: on a GPU a slave within the projections'
    tolerance of an edge may fall on either side of it, as before the store)."""
    rng = np.random.default_rng(0)
    n = 12
    g = np.linspace(0, 1, n + 1)
    tie = TIE_RTOL[np.dtype(dtype)] * np.sqrt(2) / n
    X, Y = np.meshgrid(g, g, indexing="ij")
    pts = np.c_[X.ravel(), Y.ravel(), rng.uniform(-2 * tie, 2 * tie, X.size)]
    idx = np.arange(X.size).reshape(X.shape)
    faces = np.stack([idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]], -1)
    master = ac.Surface(pts, faces.reshape(-1, 4)[rng.permutation(n * n)], "quad4")
    h = 0.3 / n
    v = rng.integers(1, n, size=(4000, 2)) / n + rng.normal(size=(4000, 2)) * np.sqrt(2 * h * tie)
    slaves = np.c_[v, np.full(4000, h)]
    p = acw.plan(master, slaves, device=DEVICE, d_max=2 / n, dtype=dtype)
    o = acw.detect(p, slaves, master.points)
    r = ac.detect(slaves, master, dtype=dtype, d_max=2 / n, backend="numpy")
    assert np.array_equal(o["face"], r.face)
    # (the projections converge to about 1e-4 of a face in float32, 1e-8 in float64)
    assert np.abs(o["point"] - r.point).max() < (1e-3 if dtype == np.float32 else 1e-7) / n


@pytest.mark.parametrize("name", ["rough_tri3", "patch_quad8"])
def test_slaves_on_master_corners_get_the_node_pseudo_normal(name):
    """On a vertex the normal is the node's angle-weighted pseudo-normal, which Warp computes
    per slave from the faces around the node: equal to the Surface's."""
    m = SCENES[name]().master
    corners = np.unique(m.faces[:, : m.element.n_corners])
    x = m.points[corners]
    o = acw.detect(acw.plan(m, x, device=DEVICE), x, m.points)
    assert (o["feature"] == 2).all() and (o["distance"] <= 1e-5 * m.longest_edge).all()
    assert np.abs(o["normal"] - m.node_normals[corners]).max() <= 1e-5


def test_closest_node_tie_rule(node_search):
    """A slave equidistant from two nodes (above the middle of an edge) goes to the smaller id,
    as in NumPy."""
    n = 6
    gx, gy = np.meshgrid(np.arange(n, dtype=float), np.arange(n, dtype=float), indexing="ij")
    pts = np.c_[gx.ravel(), gy.ravel(), np.zeros(n * n)]
    ids = np.arange(n * n).reshape(n, n)
    quads = np.c_[
        ids[:-1, :-1].ravel(), ids[1:, :-1].ravel(), ids[1:, 1:].ravel(), ids[:-1, 1:].ravel()
    ]
    faces = np.r_[quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]]
    # node ids shuffled, so that the smaller id is not always met first
    perm = np.random.default_rng(2).permutation(n * n)
    master = ac.Surface(pts[np.argsort(perm)], perm[faces], "tri3")
    rng = np.random.default_rng(5)
    # the first edge of each first-half triangle: along a grid line (the diagonals' midpoints
    # would be equidistant from four nodes)
    a, b = master.faces[: len(quads), 0], master.faces[: len(quads), 1]
    mid = 0.5 * (master.points[a] + master.points[b])
    slaves = mid + np.c_[np.zeros((len(mid), 2)), rng.uniform(0.1, 0.6, len(mid))]
    da = np.linalg.norm(slaves - master.points[a], axis=1)
    assert np.array_equal(da, np.linalg.norm(slaves - master.points[b], axis=1))  # exact ties
    o = acw.detect(acw.plan(master, slaves, device=DEVICE), slaves, master.points)
    r = ac.detect(slaves, master, dtype=np.float32, backend="numpy")
    assert np.array_equal(o["master_node"], r.master_node)
    assert np.array_equal(o["master_node"], np.minimum(a, b))


@pytest.mark.parametrize("name", ["rough_quad4", "graded_tri3", "self_quad4"])
def test_the_node_walk_gives_the_node_trees_bits(name, monkeypatch):
    """A plan whose face scan finds the closest node (the CPU's way) and one with a node tree
    (a GPU's) return the same bits in every output, in a first call and in a second (which
    starts from the first's answers)."""
    s = scenes.crumpled_sheet(2**10) if name == "self_quad4" else SCENES[name]()
    outs = []
    for walk in (False, True):
        set_node_search(monkeypatch, walk)
        if name == "self_quad4":
            p = acw.plan_self(s.master, device=DEVICE)
            args = (s.master.points,)
        else:
            p = acw.plan(s.master, s.slave, device=DEVICE)
            args = (s.slave, s.master.points)
        assert p.nodes_too == walk
        call = acw.detect_self if p.self_contact else acw.detect
        first = {k: v.copy() for k, v in call(p, *args).items()}
        outs.append((first, {k: v.copy() for k, v in call(p, *args).items()}))
    assert (outs[0][0]["master_node"] >= 0).mean() > 0.3
    for tree, walk in zip(*outs):
        for k in tree:
            assert np.array_equal(tree[k], walk[k], equal_nan=tree[k].dtype.kind == "f"), k


def _hinted_case(case):
    """(plan, detect(), hints) for a closest-node scan started from hints that would mislead
    it without their checks: another world's nearest node, the
    slave's own node (self-contact, where it never counts), or the farther-id node of a near
    tie in a master whose longest edge is 1000x the tie's (the tie band wider than the scan's
    rounding slack)."""
    if case == "worlds":
        a = scenes.rough_surfaces(2**9, seed=3)
        b = scenes.rough_surfaces(2**9, seed=4)
        pts = np.concatenate([a.master.points, b.master.points])
        master = ac.Surface(pts, np.r_[a.master.faces, b.master.faces + len(a.master.points)])
        slaves = np.r_[a.slave, b.slave]
        sw = np.r_[np.zeros(len(a.slave), int), np.ones(len(b.slave), int)]
        mw = np.r_[np.zeros(len(a.master.points), int), np.ones(len(b.master.points), int)]
        p = acw.plan(master, slaves, slave_world=sw, master_world=mw, device=DEVICE)
        d = np.linalg.norm(slaves[:, None] - pts[None], axis=2)
        d[mw[None] == sw[:, None]] = np.inf  # the other world's nodes only
        return p, lambda: acw.detect(p, slaves, pts), d.argmin(1)
    if case == "self":
        s = scenes.folded_sheet(2**9).master
        p = acw.plan_self(s, d_max=0.65, device=DEVICE)
        return p, lambda: acw.detect_self(p, s.points), s.nodes
    n = 6  # "tie": a grid of unit spacing, node ids shuffled, and a far triangle 1000 long
    gx, gy = np.meshgrid(np.arange(n, dtype=float), np.arange(n, dtype=float), indexing="ij")
    far = [[0.0, 0.0, -500.0], [1000.0, 0.0, -500.0], [0.0, 1000.0, -500.0]]
    unused = [[2.5, 2.5, 0.4]]  # a point of no face, among the slaves (id n * n + 3)
    perm = np.random.default_rng(2).permutation(n * n)
    pts = np.r_[np.c_[gx.ravel(), gy.ravel(), np.zeros(n * n)][np.argsort(perm)], far, unused]
    ids = perm.reshape(n, n)
    faces = np.c_[ids[:-1, :-1].ravel(), ids[1:, :-1].ravel(), ids[1:, 1:].ravel()]
    master = ac.Surface(pts, np.r_[faces, [[n * n, n * n + 1, n * n + 2]]], "tri3")
    tie = TIE_RTOL[np.dtype(np.float32)] * master.longest_edge
    lo, hi = np.minimum(faces[:, 0], faces[:, 1]), np.maximum(faces[:, 0], faces[:, 1])
    u = pts[hi] - pts[lo]  # unit edges along the grid
    # Above each edge's middle, moved towards its larger id so that the smaller id is farther
    # by half the tie band: the closest node is `hi`, the tie rule's `lo`.
    slaves = 0.5 * (pts[lo] + pts[hi]) + [0.0, 0.0, 0.4] + 0.5 * tie * np.hypot(0.5, 0.4) * u
    p = acw.plan(master, slaves, d_max=5.0, device=DEVICE)
    return p, lambda: acw.detect(p, slaves, pts), hi


@pytest.mark.parametrize("case", ["worlds", "self", "tie"])
def test_the_closest_node_scan_from_a_misleading_hint(case, node_search):
    """The closest-node scan starts from the last call's answer (the plan's `master_node`
    output, its node's distance bounding the scan) only where that node counts for the
    slave: hints at nodes that are closer but do not count, or that would cut the tie band,
    change nothing."""
    p, detect, hints = _hinted_case(case)
    assert p.nodes_too == node_search
    first = {k: v.copy() for k, v in detect().items()}
    assert (first["master_node"] >= 0).mean() > 0.4  # (the folded sheet: its facing sides)
    p.out["master_node"].assign(wp.array(hints.astype(np.int32), dtype=int, device=p.device))
    again = detect()
    for k in ("master_node", "face", "active"):
        assert np.array_equal(again[k], first[k]), k
    if case == "tie":  # every slave's answer is the smaller id, within the band
        f = p.master.faces[:-1]
        assert np.array_equal(first["master_node"], np.minimum(f[:, 0], f[:, 1]))
    # Any ids (an unused point's and out of range too) and the answers themselves: the same.
    rng = np.random.default_rng(0)
    unused = np.full(len(hints), len(p.master.points) - 1)
    answers = p.out["master_node"].numpy()
    for h in (unused, rng.integers(-3, len(p.master.points) + 3, len(hints)), answers):
        p.out["master_node"].assign(wp.array(h.astype(np.int32), dtype=int, device=p.device))
        assert np.array_equal(detect()["master_node"], first["master_node"])


@pytest.mark.parametrize("name", ["rough_tri3", "patch_quad8", "sphere_quad4"])
def test_warp_node_mode_equals_numpy(name):
    """mode="node" (closest node, its attached faces, blind spots, passing-by nodes) in the
    Warp kernels equals NumPy's, passing-by rows included."""
    s = SCENES[name]()
    p = acw.plan(s.master, s.slave, device=DEVICE, mode="node")
    o = acw.detect(p, s.slave, s.master.points)
    r = ac.detect(
        s.slave,
        s.master,
        dtype=np.float32,
        mode="node",
        d_max=p.constants.d_max,
        backend="numpy",
    )
    assert np.array_equal(o["status"], r.status)
    seen = set(r.status.tolist())
    assert int(ac.Status.OK) in seen
    if name == "rough_tri3":  # an open master: blind spots and passing-by nodes at its rim
        S = ac.Status
        assert {int(S.OUT_OF_RANGE), int(S.BLIND_SPOT), int(S.PASSING_BY)} <= seen
    keep = r.active | (r.status == int(ac.Status.PASSING_BY))
    _same_as_numpy(o, r, s.master.longest_edge, rows=keep)


def test_warp_far_from_the_origin(node_search):
    s = scenes.rough_surfaces(2**10, seed=2)
    shift = np.array([1e6, -2e6, 3e6]) * s.master.longest_edge
    master = s.master.with_points(s.master.points + shift)
    c = ac.detect(s.slave + shift, master, backend="warp")
    assert_matches_reference(c, s.slave + shift, master, dtype=np.float32)


def test_worlds_equal_running_each_world_alone(node_search):
    a = scenes.rough_surfaces(2**9, seed=3)
    b = scenes.rough_surfaces(2**9, seed=4, element="tri3")
    # Two worlds on top of each other: without world ids they would see each other's master.
    pts = np.concatenate([a.master.points, b.master.points])
    faces = np.concatenate([a.master.faces, b.master.faces + len(a.master.points)])
    master = ac.Surface(pts, faces, "tri3")
    slaves = np.concatenate([a.slave, b.slave])
    sw = np.r_[np.zeros(len(a.slave), int), np.ones(len(b.slave), int)]
    mw = np.r_[np.zeros(len(a.master.points), int), np.ones(len(b.master.points), int)]
    d_max = max(a.master.longest_edge, b.master.longest_edge)
    p = acw.plan(master, slaves, slave_world=sw, master_world=mw, d_max=d_max, device=DEVICE)
    o = acw.detect(p, slaves, master.points)
    for s, off, rows in ((a, 0, sw == 0), (b, len(a.master.faces), sw == 1)):
        q = acw.plan(s.master, s.slave, d_max=d_max, device=DEVICE)
        alone = acw.detect(q, s.slave, s.master.points)
        got_face = o["face"][rows]
        assert np.array_equal(got_face, np.where(alone["face"] >= 0, alone["face"] + off, -1))
        assert np.allclose(o["gap"][rows], alone["gap"], equal_nan=True, atol=1e-6)
    # A master without world ids is shared by every world.
    p = acw.plan(
        a.master,
        np.concatenate([a.slave, a.slave]),
        slave_world=np.r_[np.zeros(len(a.slave), int), np.full(len(a.slave), 5)],
        device=DEVICE,
    )
    o = acw.detect(p, np.concatenate([a.slave, a.slave]), a.master.points)
    n = len(a.slave)
    assert np.array_equal(o["face"][:n], o["face"][n:]) and (o["face"] >= 0).any()


def test_bad_worlds_and_inputs():
    s = scenes.rough_surfaces(2**8, seed=0)
    with pytest.raises(ValueError, match="slave_world"):
        acw.plan(s.master, s.slave, slave_world=np.zeros(3, int))
    with pytest.raises(ValueError, match="negative"):
        acw.plan(s.master, s.slave, slave_world=-np.ones(len(s.slave), int))
    mw = np.zeros(len(s.master.points), int)
    mw[s.master.faces[0, 0]] = 1
    with pytest.raises(ValueError, match="different worlds"):
        acw.plan(s.master, s.slave, master_world=mw)
    p = acw.plan(s.master, s.slave, device=DEVICE)
    with pytest.raises(ValueError, match="slave_points"):
        acw.detect(p, s.slave[:-1], s.master.points)
    with pytest.raises(ValueError, match="not finite"):
        acw.detect(p, np.full_like(s.slave, np.nan), s.master.points)
    with pytest.raises(ValueError, match="float32 or float64"):
        acw.plan(s.master, s.slave, dtype=np.float16)
    # The plan checks its slaves on the device; the message names the host row.
    bad = s.slave.copy()
    bad[7, 1] = np.inf
    with pytest.raises(ValueError, match=r"slave_points row 7 is not finite"):
        acw.plan(s.master, bad, device=DEVICE)
    with pytest.raises(ValueError, match=r"slave_points must have shape \[n, 3\]"):
        acw.plan(s.master, s.slave[:, :2], device=DEVICE)
    with pytest.raises(ValueError, match="slave_points must be a real numeric array"):
        acw.plan(s.master, s.slave.astype(str), device=DEVICE)
    with pytest.raises(ValueError, match="empty"):
        acw.plan(s.master, np.zeros((0, 3)), device=DEVICE)
    p64 = acw.plan(s.master, s.slave, device=DEVICE, dtype="float64")
    with pytest.raises(ValueError, match="vec3d"):
        acw.detect(p64, wp.array(s.slave.astype(np.float32), dtype=wp.vec3, device=DEVICE))


def test_a_master_deformed_far_from_the_plan_stays_exact():
    # The trees keep no planned size: faces grown 1.5x (a refit on the CPU, a build on CUDA
    # outside a graph) give NumPy's contacts.
    s = scenes.rough_surfaces(2**9, seed=5)
    p = acw.plan(s.master, s.slave, device=DEVICE, growth=1.0)
    acw.detect(p, s.slave, s.master.points)
    stretched = s.master.points * [1.5, 1.5, 1.0]
    o = acw.detect(p, s.slave, stretched)
    r = ac.detect(
        s.slave,
        s.master.with_points(stretched),
        d_max=p.constants.d_max,
        dtype=np.float32,
        backend="numpy",
    )
    _same_as_numpy(o, r, s.master.longest_edge)


@pytest.mark.parametrize("first", [False, True], ids=["later call", "first call"])
def test_device_arrays_in_place_and_graph_capture(first):
    """wp.array inputs are used in place (outputs are the plan's buffers); on CUDA the whole
    detection is captured once and replayed on new coordinates written into the same arrays.
    first: the plan's very first detect is the one captured, in the caller's graph (the
    commands the plan recorded for the master's and the slaves' stages replayed inside the
    capture); its contacts are NumPy's too. Elsewhere the same call launches."""
    s = scenes.rough_surfaces(2**10, seed=6)
    p = acw.plan(s.master, s.slave, device=DEVICE)
    xs = wp.array(s.slave.astype(np.float32), dtype=wp.vec3, device=DEVICE)
    xm = wp.array(s.master.points.astype(np.float32), dtype=wp.vec3, device=DEVICE)
    if not first:
        o = acw.detect(p, xs, xm)
        assert o["gap"] is p.out["gap"]
    elif DEVICE == "cuda" and not wp.is_conditional_graph_supported():
        pytest.skip("this CUDA driver has no conditional graph nodes (12.4+)")
    moved = s.slave + [0.1, -0.05, -0.3]
    if DEVICE == "cuda":
        with wp.ScopedCapture(device=DEVICE) as cap:
            acw.detect(p, xs, xm)
        xs.assign(moved.astype(np.float32))
        wp.capture_launch(cap.graph)
    else:
        xs.assign(moved.astype(np.float32))
        acw.detect(p, xs, xm)
    r = ac.detect(moved, s.master, dtype=np.float32, backend="numpy")
    got = {k: v.numpy() for k, v in p.out.items()}
    if first:
        _same_as_numpy(got, r, s.master.longest_edge)
        return
    assert np.array_equal(got["face"], r.face)
    a = r.active
    assert np.abs(got["gap"][a] - r.gap[a]).max() <= 1e-4 * s.master.longest_edge


def test_a_master_that_does_not_move_keeps_its_grid():
    s = scenes.rough_surfaces(2**9, seed=8)
    p = acw.plan(s.master, s.slave, device=DEVICE)
    with pytest.raises(ValueError, match="previous detect"):
        acw.detect(p, s.slave)
    first = acw.detect(p, s.slave, s.master.points)
    moved = s.slave + [0.05, 0.0, -0.2]
    again = acw.detect(p, moved)  # master stages skipped
    r = ac.detect(moved, s.master, dtype=np.float32, backend="numpy")
    assert np.array_equal(again["face"], r.face) and not np.array_equal(
        again["face"], first["face"]
    )


@pytest.mark.parametrize("way", ["graph", "new buffers"])
def test_grid_refit_and_rebuild(way, node_search):
    """Where the device chooses (a CUDA graph with conditional nodes, the caller's; on a GPU
    outside a graph, through the plan's graph of the rebuild alone: a call on buffers new to
    the plan; the CPU), the master's trees keep their order while every face centre and node
    stays within the plan's margin of where it was sorted, and are sorted again otherwise:
    contacts equal NumPy's on either path, and the path taken is the one the nodes and the
    faces' centres call for."""
    s = scenes.rough_surfaces(2**9, seed=9)
    L = s.master.longest_edge
    p = acw.plan(s.master, s.slave, device=DEVICE)
    q = acw.plan(s.master, s.slave, device=DEVICE, refit=False)
    xs = wp.array(s.slave.astype(np.float32), dtype=wp.vec3, device=DEVICE)
    xm = wp.array(s.master.points.astype(np.float32), dtype=wp.vec3, device=DEVICE)
    acw.detect(p, xs, xm)  # the first call: a refit, the check read on the host
    run = lambda: acw.detect(p, xs, xm)  # noqa: E731
    if DEVICE == "cuda" and not wp.is_conditional_graph_supported():
        pytest.skip("this CUDA driver has no conditional graph nodes (12.4+)")
    if way == "graph" and DEVICE == "cuda":
        with wp.ScopedCapture(device=DEVICE) as cap:
            acw.detect(p, xs, xm)
        run = lambda: wp.capture_launch(cap.graph)  # noqa: E731
    kept = []  # (new buffers: every one kept alive, so that no address comes back)

    def fresh():
        kept.append([wp.clone(xs), wp.clone(xm)])
        acw.detect(p, *kept[-1])

    if way == "new buffers":
        run = fresh
    c0, _ = s.master.face_bounds
    x0 = s.master.points[s.master.nodes]
    margin = float(p.node_grid.margin)
    assert margin > 0 and float(p.face_grid.margin) == margin
    rng = np.random.default_rng(3)
    shift = np.array([0.013, -0.007, 0.02]) * L
    small = s.master.points + shift + rng.normal(0, 0.002 * L, s.master.points.shape)
    # One node 1.6 margins from where it was sorted, its faces' centres (tri3) 0.53: the node
    # tree alone is stale (on a GPU's graph, refitted beside the face tree, sorted after its
    # scan).
    lone = s.master.points.copy()
    lone[s.master.nodes[len(s.master.nodes) // 2]] += [0.0, 0.0, 1.6 * margin]
    for step, moved in enumerate([small, lone, s.master.points + [1.7 * L, 0.4 * L, -0.05 * L]]):
        master = ac.Surface(moved, s.master.faces, element=s.master.element.name)
        slave = s.slave + (moved - s.master.points).mean(0)
        c, r = master.face_bounds
        x = moved[s.master.nodes]
        faces_stale = bool((np.linalg.norm(c - c0, axis=1) > margin).any())
        nodes_stale = bool((np.linalg.norm(x - x0, axis=1) > margin).any())
        assert (faces_stale, nodes_stale) == (step == 2, step > 0)  # as the motions say
        stale = faces_stale or (nodes_stale and not p.nodes_too)  # (nodes_too: no node tree)
        xs.assign(slave.astype(np.float32))
        xm.assign(moved.astype(np.float32))
        run()
        assert int(p.rebuild.numpy()[0]) == int(stale)
        if way == "new buffers" and DEVICE == "cuda":
            assert p.build_graph is not None and not p.graph_of  # no call's graph
        got = {k: v.numpy() for k, v in p.out.items()}
        r = ac.detect(slave, master, d_max=p.constants.d_max, dtype=np.float32, backend="numpy")
        _same_as_numpy(got, r, L)
        built = {k: v.numpy() for k, v in acw.detect(q, xs, xm).items()}
        for k in got:  # a grid built in every call: the same bits
            assert np.array_equal(got[k], built[k], equal_nan=got[k].dtype.kind == "f"), k
        assert int(q.rebuild.numpy()[0]) == 0
        if stale:
            c0, x0 = c, x


def test_first_detect_on_a_master_far_from_the_plans_points():
    """A GPU plan sorts the master's trees on the plan's points; a first detect refits them
    and reads their staleness on the host after its scans. On a master turned, bent and
    jittered far from those points (every tree stale) the first call's contacts and the next
    one's (on trees sorted again) equal NumPy's."""
    s = scenes.rough_surfaces(2**9, seed=10)
    L = s.master.longest_edge
    p = acw.plan(s.master, s.slave, device=DEVICE, dtype="float64")  # (no float32 near-ties)
    c, sn = np.cos(0.7), np.sin(0.7)
    turn = np.array([[c, -sn, 0.0], [sn, c, 0.0], [0.0, 0.0, 1.0]])

    def move(x):
        y = x @ turn.T
        return y + np.c_[0 * y[:, :2], 2 * L * np.sin(y[:, 0] / (8 * L))]

    rng = np.random.default_rng(4)
    moved = move(s.master.points) + rng.normal(0, 0.05 * L, s.master.points.shape)
    master = ac.Surface(moved, s.master.faces, element=s.master.element.name)
    slave = move(s.slave)
    r = ac.detect(slave, master, d_max=p.constants.d_max, backend="numpy")
    assert r.active.sum() > len(slave) // 4
    xs = wp.array(slave, dtype=wp.vec3d, device=DEVICE)
    xm = wp.array(moved, dtype=wp.vec3d, device=DEVICE)
    for call in range(2):
        got = {k: v.numpy() for k, v in acw.detect(p, xs, xm).items()}
        _same_as_numpy(got, r, L)
        if DEVICE == "cuda":  # stale in the first call, sorted again after its scans
            assert int(p.rebuild.numpy()[0]) == int(call == 0)


def test_double_buffered_inputs_replay_a_graph_each():
    """Inputs that alternate between two sets of buffers (a simulator's previous and next
    state): each call's contacts are NumPy's, and on CUDA each set of buffers replays a graph
    of its own once seen twice."""
    s = scenes.rough_surfaces(2**9, seed=12)
    p = acw.plan(s.master, s.slave, device=DEVICE)
    bufs = [
        [
            wp.array(x.astype(np.float32), dtype=wp.vec3, device=DEVICE)
            for x in (s.slave, s.master.points)
        ]
        for _ in range(2)
    ]
    rng = np.random.default_rng(4)
    for step in range(6):
        xs, xm = bufs[step % 2]
        moved = s.slave + rng.normal(0, 0.05, 3) + [0, 0, -0.1 * step]
        xs.assign(moved.astype(np.float32))
        got = {k: v.numpy() for k, v in acw.detect(p, xs, xm).items()}
        r = ac.detect(moved, s.master, d_max=p.constants.d_max, dtype=np.float32, backend="numpy")
        _same_as_numpy(got, r, s.master.longest_edge)
    if DEVICE == "cuda":
        assert len(p.graph_of) == 2


def test_graph_bookkeeping_keeps_the_latest_buffers():
    """What a CUDA detect does with its input buffers (host logic, run here on any device):
    buffers seen again are captured, then replayed; double buffers keep a graph each; buffers
    rotating over more sets than GRAPHS are captured at most once each and then only replay
    or launch (never a capture every call)."""
    from arraycontact_warp import _detect as wd

    s = scenes.rough_surfaces(2**6, seed=1)

    def run(keys):
        p = acw.plan(s.master, s.slave, device=DEVICE)
        out = []
        for k in keys:
            a = wd._graph_action(p, k)
            if a == "capture":
                wd._keep_graph(p, k, f"graph of {k}")
            assert a != "replay" or p.graph_of[k] == f"graph of {k}"
            out.append(a)
        return out, p

    got, _ = run(["a"] * 4)
    assert got == ["launch", "capture", "replay", "replay"]
    got, p = run(["a", "b"] * 3)
    assert got == ["launch", "launch", "capture", "capture", "replay", "replay"]
    assert sorted(p.graph_of) == ["a", "b"]
    n = wd.GRAPHS + 2
    got, p = run([f"r{i}" for i in range(n)] * 5)
    assert got.count("capture") == n  # each once, in the second round
    assert "capture" not in got[2 * n :]
    assert got[-n:].count("replay") == wd.GRAPHS and len(p.graph_of) == wd.GRAPHS


def _tree_state(g):
    """A tree's records as bytes: the levels up to the root, the item slots, corners and
    normal boxes, and the refit's arrival counts."""
    end = int(g.offsets.numpy()[int(g.root.numpy()[0])]) + warp_grid.W
    out = [g.boxes.numpy()[:end], g.items.numpy(), g.corners.numpy()]
    if g.normals:
        out += [g.nboxes.numpy()[:end], g.nitems.numpy()]
    return [a.view(np.uint8).copy() for a in out], g.arrived.numpy().copy()  # (CPU: views)


@pytest.mark.parametrize("name", ["graded_tri3", "rough_quad4", "self_quad4"])
def test_refit_in_one_launch_equals_a_launch_a_level(name, monkeypatch):
    """A refit's boxes (`_refit_up`: every level in one launch, the last thread to reach a
    group making its parent) are the bytes of `fill`'s (one reduction launch a level), on
    master coordinates moved twice; its arrival counts are back at zero after each launch.
    (Two-body plans with a node tree, as a GPU's.)"""
    set_node_search(monkeypatch, False)
    if name == "self_quad4":
        s = scenes.crumpled_sheet(2**10)
        p = acw.plan_self(s.master, device=DEVICE)
        acw.detect_self(p, s.master.points)
    else:
        s = SCENES[name]()
        p = acw.plan(s.master, s.slave, device=DEVICE)
        acw.detect(p, s.slave, s.master.points)
    m, L = p.m, s.master.longest_edge
    tri3 = s.master.element.name == "tri3"
    node_n = (p.normals, p.normals) if p.self_contact else None
    face_n = (p.face_nlo, p.face_nhi) if p.self_contact else None
    rng = np.random.default_rng(4)
    for _ in range(2):
        moved = s.master.points + rng.normal(0, 0.3 * L, s.master.points.shape)
        m.points.assign((moved - p.origin).astype(np.float32))
        p.rebuild.zero_()
        args = (m.points, m.node_world, DEVICE, p.rebuild, node_n)
        warp_grid.refit(p.node_grid, p.node_layout, *args)
        args = (m.points, m.faces, p.constants.lebesgue, m.face_world, DEVICE, tri3)
        warp_grid.refit_faces(p.face_grid, p.face_layout, *args, p.rebuild, face_n)
        assert int(p.rebuild.numpy()[0]) == 1  # moved 0.3 edges: past the margin
        one = [_tree_state(p.node_grid), _tree_state(p.face_grid)]
        warp_grid.fill(p.node_grid, p.node_layout, DEVICE)
        warp_grid.fill(p.face_grid, p.face_layout, DEVICE)
        level = [_tree_state(p.node_grid), _tree_state(p.face_grid)]
        for (a, arrived), (b, _) in zip(one, level):
            assert not arrived.any()
            for x, y in zip(a, b):
                assert np.array_equal(x, y)


def test_exported_geometry_in_a_user_kernel():
    """The README's example: a simulator's own kernel calls the exported @wp.func."""

    # fmt: off
    # (Warp 1.19 read this nested kernel's body past its end when the signature took one line
    # a parameter, as the formatter writes it: the test's next lines became kernel code.)
    @wp.kernel
    def nearest_on_triangles(q: wp.array(dtype=wp.vec3), tri: wp.array(dtype=wp.vec3),
                             xi_out: wp.array(dtype=wp.vec2), feature_out: wp.array(dtype=int)):
        i = wp.tid()
        xi, feature, local = acw.closest_point_triangle(q[i], tri[0], tri[1], tri[2])
        xi_out[i] = xi
        feature_out[i] = feature
    # fmt: on

    rng = np.random.default_rng(0)
    q = rng.uniform(-1, 2, (200, 3)).astype(np.float32)
    tri = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32)
    xi = wp.zeros(200, dtype=wp.vec2, device=DEVICE)
    feat = wp.zeros(200, dtype=int, device=DEVICE)
    wp.launch(
        nearest_on_triangles,
        200,
        inputs=[
            wp.array(q, dtype=wp.vec3, device=DEVICE),
            wp.array(tri, dtype=wp.vec3, device=DEVICE),
        ],
        outputs=[xi, feat],
        device=DEVICE,
    )
    master = ac.Surface(tri, [[0, 1, 2]], "tri3")
    ref = ac.reference.closest_points(q.astype(float), master)
    assert np.allclose(xi.numpy(), ref.xi, atol=1e-6)
    assert np.array_equal(feat.numpy(), ref.feature)


def _edges_kernel(g, real, vec3, struct):
    """A user kernel calling the exported edge solver of geometry module g on element data of
    type `struct` (g.Element, or g.Quads for quad4)."""

    # (A compact signature: see test_exported_geometry_in_a_user_kernel.)
    # fmt: off
    @wp.kernel(module="unique")
    def edges(el: struct, pts: wp.array(dtype=vec3), q: wp.array(dtype=vec3),
              t_out: wp.array2d(dtype=real), d_out: wp.array2d(dtype=real)):
        i = wp.tid()
        xe = g.FaceNodes()
        for k in range(pts.shape[0]):
            xe = g.set_node(xe, k, pts[k])
        for e in range(el.n_corners):
            t, d = g.closest_point_edge(el, q[i], xe, e)
            t_out[i, e] = t
            d_out[i, e] = d
    # fmt: on

    return edges


@pytest.mark.parametrize(
    "element,dtype",
    [
        ("quad4", "float32"),
        ("quad4 as Quads", "float64"),
        ("tri6", "float32"),
        ("quad8", "float32"),
        ("quad9", "float32"),
        ("quad8", "float64"),
    ],
)
def test_exported_closest_point_edge(element, dtype):
    """The exact edge solver as a @wp.func: the same minimum as dense sampling of each edge
    (quad4 in an Element and in a Quads struct)."""
    from arraycontact._elements import get_element, shape_functions

    g = acw.geometry(dtype)
    real, vec3 = (wp.float32, wp.vec3) if dtype == "float32" else (wp.float64, wp.vec3d)
    quads = element == "quad4 as Quads"
    element = element.split()[0]
    struct = g.Quads if quads else g.Element
    data = g.quad_data(DEVICE) if quads else g.element_data(element, DEVICE)

    e = get_element(element)
    rng = np.random.default_rng(4)
    pts = np.c_[e.nodes, np.zeros(e.nodes_per_face)] + 0.3 * rng.normal(size=(e.nodes_per_face, 3))
    q = rng.normal(size=(300, 3))
    t = wp.zeros((300, e.n_corners), dtype=real, device=DEVICE)
    d = wp.zeros((300, e.n_corners), dtype=real, device=DEVICE)

    def arr(a):
        return wp.array(a.astype(dtype), dtype=vec3, device=DEVICE)

    wp.launch(
        _edges_kernel(g, real, vec3, struct),
        300,
        inputs=[data, arr(pts), arr(q)],
        outputs=[t, d],
        device=DEVICE,
    )
    ts = np.linspace(0, 1, 4001)
    for k in range(e.n_corners):
        a, b = e.edge_nodes[k, :2]
        x = shape_functions(e, e.nodes[a] + ts[:, None] * (e.nodes[b] - e.nodes[a])) @ pts
        dense = ((q[:, None] - x[None]) ** 2).sum(-1).min(1)
        # Against a float64 sampling 2.5e-4 apart along the edge (its own error ~1e-7 here).
        assert np.abs(d.numpy()[:, k] - dense).max() <= 1e-4 * (1 + dense.max())
        assert (d.numpy()[:, k] <= dense + (1e-5 if dtype == "float32" else 1e-12)).all()
        xt = shape_functions(e, e.nodes[a] + t.numpy()[:, k, None] * (e.nodes[b] - e.nodes[a]))
        tol = 1e-5 if dtype == "float32" else 1e-12
        assert np.allclose(((xt @ pts - q) ** 2).sum(-1), d.numpy()[:, k], rtol=tol, atol=tol)


def _warped_quads(seed, n):
    """n random warped quad4 faces about the square [-1, 1]^2 and a point each: (xs [n, 4, 3],
    r [n, 3]); and, on a 41 x 41 grid of the square (xi major), x - r, x_xi and x_eta in
    closed form [n, 41 * 41, 3]."""
    from arraycontact._elements import get_element, shape_functions

    e = get_element("quad4")
    rng = np.random.default_rng(seed)
    warp = rng.uniform(0.0, 0.6, n)[:, None, None]
    xs = np.c_[e.nodes, np.zeros(4)][None] + warp * rng.normal(size=(n, 4, 3))
    r = rng.normal(size=(n, 3)) * rng.uniform(0.1, 2.0, n)[:, None]
    t = np.linspace(-1, 1, 41)
    xi = np.stack(np.meshgrid(t, t, indexing="ij"), -1).reshape(-1, 2)
    z = e.nodes
    x = np.einsum("gc,pck->pgk", shape_functions(e, xi), xs) - r[:, None]
    # x_xi = sum_c z_c0 (1 + z_c1 eta) / 4 x_c, x_eta likewise.
    d_xi = np.einsum("gc,pck->pgk", z[None, :, 0] * (1 + z[None, :, 1] * xi[:, 1:]) / 4, xs)
    d_eta = np.einsum("gc,pck->pgk", z[None, :, 1] * (1 + z[None, :, 0] * xi[:, :1]) / 4, xs)
    return xs, r, x, d_xi, d_eta


def _launch_flags(kernel, n, inputs):
    out = wp.zeros(n, dtype=int, device=DEVICE)
    wp.launch(kernel, n, inputs=inputs, outputs=[out], device=DEVICE)
    return out.numpy().astype(bool)


def test_quads_constants_equal_the_element_table():
    """Quads' domain and nodes (constants in the kernels) equal quad4's table
    (arraycontact._elements), as Element's arrays give them."""
    from arraycontact._elements import get_element

    g = acw.geometry("float64")

    # fmt: off
    @wp.func
    def put(el: Any, j: int, k: int, out: wp.array2d(dtype=wp.float64)):
        a = g.cons_a(el, j)
        x = g.node_xi(el, j)
        nxt = g.edge_xi(el, j, wp.float64(1.0))
        out[k, 0] = a[0]
        out[k, 1] = a[1]
        out[k, 2] = g.cons_b(el, j)
        out[k, 3] = wp.float64(g.cons_edge(el, j))
        out[k, 4] = x[0]
        out[k, 5] = x[1]
        out[k, 6] = wp.float64(g.n_cons(el))
        out[k, 7] = wp.float64(g.corners(el))
        out[k, 8] = nxt[0]
        out[k, 9] = nxt[1]
        return 0

    @wp.kernel(module="unique")
    def read(el: g.Quads, gen: g.Element, out: wp.array2d(dtype=wp.float64)):
        j = wp.tid()
        put(el, j, j, out)
        put(gen, j, 4 + j, out)  # the same functions on the generic struct: its arrays
    # fmt: on

    e = get_element("quad4")
    out = wp.zeros((8, 10), dtype=wp.float64, device=DEVICE)
    wp.launch(read, 4, inputs=[g.quad_data(DEVICE), g.element_data("quad4", DEVICE)],
              outputs=[out], device=DEVICE)  # fmt: skip
    got = out.numpy()
    want = np.column_stack(
        [e.constraints_a, e.constraints_b, e.constraint_edge, e.nodes, np.full(4, 4),
         np.full(4, e.n_corners), np.roll(e.nodes, -1, axis=0)]
    )  # fmt: skip
    np.testing.assert_array_equal(got[:4], want)  # Quads
    np.testing.assert_array_equal(got[4:], want)  # Element


def test_curved_edges_mid_nodes_follow_the_corners():
    """A curved edge's closest point reads its corners and its mid-edge node as x at t = 0,
    1 and 1/2 (`closest_point_edge`): edge e (corner e to e + 1) has its middle node at
    n_corners + e, halfway along it, on every curved element."""
    from arraycontact._elements import get_element

    for name in ("tri6", "quad8", "quad9"):
        e = get_element(name)
        c = e.n_corners
        for k in range(c):
            mid = 0.5 * (e.nodes[k] + e.nodes[(k + 1) % c])
            np.testing.assert_array_equal(e.nodes[c + k], mid, err_msg=f"{name} edge {k}")


def test_surely_convex_bilinear_faces():
    """`surely_convex` (one Newton start suffices on a bilinear face) only where the Hessian
    of |x(xi) - r|^2 is positive definite over the whole square (checked on a 41 x 41 grid
    from its closed form), and everywhere it clearly is: it holds for near-flat quads and
    points near them, fails for strongly warped ones."""
    from arraycontact._elements import get_element
    from arraycontact._geometry import surely_convex

    g = acw.geometry("float64")

    # fmt: off
    @wp.kernel(module="unique")
    def convex(el: g.Element, xs: wp.array2d(dtype=wp.vec3d), r: wp.array(dtype=wp.vec3d),
               out: wp.array(dtype=int)):
        i = wp.tid()
        xe = g.FaceNodes()
        for k in range(4):
            xe = g.set_node(xe, k, xs[i, k])
        out[i] = int(g.surely_convex(el, r[i], xe))
    # fmt: on

    e = get_element("quad4")
    n = 2000
    xs, r, x, d_xi, d_eta = _warped_quads(11, n)
    vec = {k: wp.array(v, dtype=wp.vec3d, device=DEVICE) for k, v in (("xs", xs), ("r", r))}
    ok = _launch_flags(convex, n, [g.element_data("quad4", DEVICE), vec["xs"], vec["r"]])
    assert 0.2 < ok.mean() < 0.9
    # NumPy's twin (arraycontact._geometry) decides alike, so the back ends agree.
    np.testing.assert_array_equal(ok, surely_convex(e, r, xs))
    a3 = 0.25 * np.einsum("c,pck->pk", e.nodes[:, 0] * e.nodes[:, 1], xs)
    c = np.einsum("pgk,pk->pg", x, a3)
    h = np.stack(
        [
            np.stack([(d_xi * d_xi).sum(-1), (d_xi * d_eta).sum(-1) + c], -1),
            np.stack([(d_xi * d_eta).sum(-1) + c, (d_eta * d_eta).sum(-1)], -1),
        ],
        -2,
    )
    eig = np.linalg.eigvalsh(h)
    least = eig[..., 0].min(1)
    assert (least[ok] > 0).all()
    assert (least[~ok] <= 0).any()  # the certificate is needed: some are not convex
    # and nearly complete: wherever the Hessian is clearly positive definite it proves it
    # (the cheap bound alone leaves out 46% of these).
    assert ok[least > 0.05 * eig[..., 1].max(1)].all()


@pytest.mark.parametrize("name", ["tri6", "quad8", "quad9"])
def test_curved_convex_faces(name):
    """`curved_convex` (one Newton start, where it converges, suffices on a curved face) only
    where the Hessian of |x(xi) - r|^2, J^T J + (x - r) . x_ab from the shape functions'
    derivatives, is positive definite all over the face (a grid of 41 x 41 points, the
    triangle's half): it holds for gently curved faces and points near them (on tri6 nearly
    wherever the Hessian is clearly positive definite), fails for strongly curved ones, and
    NumPy's twin decides alike."""
    from arraycontact._elements import get_element, interpolate, shape_second_derivatives
    from arraycontact._geometry import curved_convex

    g = acw.geometry("float64")
    e = get_element(name)
    nn = e.nodes_per_face

    # fmt: off
    @wp.kernel(module="unique")
    def convex(el: g.Element, xs: wp.array2d(dtype=wp.vec3d), r: wp.array(dtype=wp.vec3d),
               out: wp.array(dtype=int)):
        i = wp.tid()
        xe = g.FaceNodes()
        for k in range(el.nn):
            xe = g.set_node(xe, k, xs[i, k] - xs[i, 0])
        out[i] = int(g.curved_convex(el, r[i] - xs[i, 0], g.monomials_of(el, xe)))
    # fmt: on

    # Faces of size 2 (the natural domain doubled), every node moved by up to 0.25 of it.
    n = 1500
    rng = np.random.default_rng(3)
    bend = rng.uniform(0.0, 0.25, n)
    xs = np.c_[2 * e.nodes, np.zeros(nn)][None] + bend[:, None, None] * rng.normal(size=(n, nn, 3))
    r = xs.mean(1) + rng.normal(size=(n, 3)) * rng.uniform(0.05, 1.5, n)[:, None]
    vec = {k: wp.array(v, dtype=wp.vec3d, device=DEVICE) for k, v in (("xs", xs), ("r", r))}
    ok = _launch_flags(convex, n, [g.element_data(name, DEVICE), vec["xs"], vec["r"]])
    assert 0.08 < ok.mean() < 0.9
    np.testing.assert_array_equal(ok, curved_convex(e, r, xs))
    # Gently curved faces and points within 1 of their centre: (nearly) all proven.
    gentle = (bend < 0.02) & (np.linalg.norm(r - xs.mean(1), axis=1) < 1.0)
    assert gentle.sum() > 40 and ok[gentle].mean() > 0.95

    t = np.linspace(0, 1, 41) if e.kind == "tri" else np.linspace(-1, 1, 41)
    xi = np.stack(np.meshgrid(t, t, indexing="ij"), -1).reshape(-1, 2)
    if e.kind == "tri":
        xi = xi[xi.sum(1) <= 1 + 1e-12]
    x, dx = interpolate(e, xs[:, None], xi[None], np)  # [n, g, 3], [n, g, 3, 2]
    d2 = np.einsum("gns,pnk->pgks", shape_second_derivatives(e, xi), xs)  # (11, 12, 22)
    c = np.einsum("pgks,pgk->pgs", d2, x - r[:, None])
    h = np.einsum("pgka,pgkb->pgab", dx, dx)
    h[..., 0, 0] += c[..., 0]
    h[..., 0, 1] += c[..., 1]
    h[..., 1, 0] += c[..., 1]
    h[..., 1, 1] += c[..., 2]
    eig = np.linalg.eigvalsh(h)
    least = eig[..., 0].min(1)
    assert (least[ok] > 0).all()
    assert (least[~ok] <= 0).any()  # the certificate is needed: some are not convex
    if name == "tri6":  # (its second test, on the Hessian's own Bernstein coefficients, is tight)
        assert ok[least > 0.05 * eig[..., 1].max(1)].mean() > 0.9


def test_warp_face_boxes_equal_numpys():
    """The kernels' face boxes (`_prepare.face_bounds`: on curved faces the Bernstein control
    points' box cut by the Lebesgue box and the ball's cube) equal arraycontact._surface's
    face_boxes, which tests/test_surface.py checks hold the faces, on every element."""
    import importlib

    from arraycontact._elements import get_element
    from arraycontact._surface import face_boxes

    prep = importlib.import_module(acw._real.precision("float64").__package__ + "._prepare")

    # fmt: off
    @wp.kernel(module="unique")
    def boxes(points: wp.array(dtype=wp.vec3d), faces: wp.array2d(dtype=int),
              lebesgue: wp.float64, lo: wp.array(dtype=wp.vec3d), hi: wp.array(dtype=wp.vec3d)):
        f = wp.tid()
        c, r, a, b = prep.face_bounds(points, faces, f, lebesgue)
        lo[f] = a
        hi[f] = b
    # fmt: on

    rng = np.random.default_rng(2)
    for name in ("tri3", "quad4", "tri6", "quad8", "quad9"):
        e = get_element(name)
        nn = e.nodes_per_face
        xe = np.c_[e.nodes, np.zeros(nn)][None] + 0.3 * rng.normal(size=(300, nn, 3))
        faces = np.arange(300 * nn).reshape(300, nn)
        lo, hi = (wp.zeros(300, dtype=wp.vec3d, device=DEVICE) for _ in range(2))
        pts = wp.array(xe.reshape(-1, 3), dtype=wp.vec3d, device=DEVICE)
        f = wp.array(faces.astype(np.int32), dtype=int, device=DEVICE)
        wp.launch(boxes, 300, inputs=[pts, f, wp.float64(e.lebesgue), lo, hi], device=DEVICE)
        want = face_boxes(e, xe)
        np.testing.assert_allclose(lo.numpy(), want[0], rtol=0, atol=1e-12, err_msg=name)
        np.testing.assert_allclose(hi.numpy(), want[1], rtol=0, atol=1e-12, err_msg=name)


def test_beyond_an_edge_bilinear_faces():
    """`beyond_an_edge` (the Warp projection then takes the closest point on the edges
    alone) only where |x(xi) - r|^2 has no stationary point in the square: one of its
    gradient's components, (x - r) . x_xi or (x - r) . x_eta, keeps one sign over a 41 x 41
    grid of it; and wherever that component is clearly negative all along an edge xi = 1 or
    eta = 1 (positive along xi = -1, eta = -1) on the grid, it says so (each edge's case is
    met)."""

    g = acw.geometry("float64")

    # fmt: off
    @wp.kernel(module="unique")
    def beyond(xs: wp.array2d(dtype=wp.vec3d), r: wp.array(dtype=wp.vec3d),
               out: wp.array(dtype=int)):
        i = wp.tid()
        xe = g.FaceNodes()
        for k in range(4):
            xe = g.set_node(xe, k, xs[i, k] - xs[i, 0])
        out[i] = int(g.beyond_an_edge(r[i] - xs[i, 0], xe))
    # fmt: on

    n = 4000
    xs, r, x, d_xi, d_eta = _warped_quads(12, n)
    vec = [wp.array(v, dtype=wp.vec3d, device=DEVICE) for v in (xs, r)]
    ok = _launch_flags(beyond, n, vec)
    assert 0.2 < ok.mean() < 0.9
    g1 = (x * d_xi).sum(-1).reshape(n, 41, 41)  # [p, xi, eta]
    g2 = (x * d_eta).sum(-1).reshape(n, 41, 41)
    one_sign = (
        (g1 < 0).all((1, 2)) | (g1 > 0).all((1, 2)) | (g2 < 0).all((1, 2)) | (g2 > 0).all((1, 2))
    )
    assert one_sign[ok].all()
    scale = np.abs(g1).max((1, 2)) + np.abs(g2).max((1, 2))
    clear = {
        "xi = 1": g1[:, -1, :].max(1) < -0.05 * scale,
        "xi = -1": g1[:, 0, :].min(1) > 0.05 * scale,
        "eta = 1": g2[:, :, -1].max(1) < -0.05 * scale,
        "eta = -1": g2[:, :, 0].min(1) > 0.05 * scale,
    }
    for edge, c in clear.items():
        alone = c & ~np.any([v for k, v in clear.items() if k != edge], 0)
        assert alone.sum() > 20, edge
        assert ok[alone].all(), edge


def test_jax_arrays_in_and_out():
    import jax.numpy as jnp  # a core dependency: never skipped

    s = scenes.rough_surfaces(2**9, seed=7)
    p = acw.plan(s.master, s.slave, device=DEVICE)
    xs, xm = (jnp.asarray((v - p.origin).astype(np.float32)) for v in (s.slave, s.master.points))
    p.origin = np.zeros(3)  # the arrays above are in the plan's frame already
    o = acw.detect(p, xs, xm)
    assert type(o["gap"]).__module__.startswith("jax")
    r = ac.detect(s.slave, s.master, dtype=np.float32, backend="numpy")
    assert np.array_equal(np.asarray(o["face"]), r.face)


def _topology_surfaces():
    """Open and closed, linear and quadratic, a non-manifold edge, a pinched vertex and points
    no face uses."""
    u = np.linspace(0.0, 1.0, 7)
    x, y = np.meshgrid(u, u[:5], indexing="ij")
    z = 0.1 * np.sin(3 * x) * np.cos(2 * y)
    out = {
        el: scenes.grid_surface(x, y, z, el) for el in ("tri3", "quad4", "tri6", "quad8", "quad9")
    }
    out["closed quad4"] = scenes.block_surface(lambda a, b, c: (a, 2 * b, c), (4, 3, 5))
    out["closed tri6"] = scenes.block_surface(lambda a, b, c: (a, b, c), (5, 3, 3), "tri6")
    pts = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [5, 5, 5.0]])
    # Edge 0-1 has three faces; node 0 is shared by two otherwise separate fans (a pinch);
    # point 5 is used by no face.
    pinch = np.array([[-1, 0.5, 0.2], [-1, -0.5, 0.2]])
    out["non-manifold, pinched"] = ac.Surface(
        np.vstack([pts, pinch]), [[0, 1, 2], [1, 0, 3], [0, 1, 4], [0, 6, 7]], "tri3"
    )
    # Large enough for the CPU's launches in parts (their atomics fill the counting sorts'
    # segments in a varying order), faces and nodes numbered at random.
    rough = scenes.rough_surfaces(2**12, element="quad4").master
    rng = np.random.default_rng(7)
    new_id = rng.permutation(len(rough.points))
    pts = np.empty_like(rough.points)
    pts[new_id] = rough.points
    out["rough quad4, shuffled"] = ac.Surface(
        pts, new_id[rough.faces][rng.permutation(rough.n_faces)]
    )
    return out


@pytest.mark.parametrize("name", list(_topology_surfaces()))
def test_a_deformed_surface_shares_the_device_tables_of_its_connectivity(name):
    """Surface.with_points (a deformed configuration) shares the device tables of the
    connectivity alone with the surface it comes from, down a chain of such surfaces; its
    geometry (the scalars, the boxes, the balls) is its own: equal to its NumPy properties.
    A Surface made anew from the same arrays shares nothing."""
    from arraycontact_warp._surface import face_balls, topology

    m = _topology_surfaces()[name]
    t = topology(m, DEVICE)
    rng = np.random.default_rng(5)
    a = m
    for step in range(2):
        scale = np.array([1.3, 0.8, 1.1]) if step == 0 else np.array([0.9, 1.2, 1.0])
        a = a.with_points(a.points * scale + rng.normal(0, 0.02, a.points.shape))
        ta = topology(a, DEVICE)
        for key in ("faces", "face_edges", "edge_faces", "nf_offsets", "nf_ids", "nodes"):
            assert getattr(ta, key) is getattr(t, key), key
        assert (ta.n_nodes, ta.n_edges, ta.closed) == (t.n_nodes, t.n_edges, t.closed)
        np.testing.assert_array_equal(ta.points.numpy(), a.points)
        assert ta.longest_edge == pytest.approx(a.longest_edge, rel=1e-15)
        c, r = a.face_bounds
        assert ta.r_max == pytest.approx(r.max(), rel=1e-15)
        assert ta.r_small == pytest.approx(np.quantile(r, 0.1), rel=1e-6)
        for got, want in zip(ta.node_box, a.node_box):
            np.testing.assert_array_equal(got, want)
        scale = 1e-15 * np.abs(a.points).max()
        np.testing.assert_allclose(ta.ball_box[0], (c - r[:, None]).min(0), rtol=1e-15, atol=scale)
        np.testing.assert_allclose(ta.ball_box[1], (c + r[:, None]).max(0), rtol=1e-15, atol=scale)
        np.testing.assert_array_equal(face_balls(ta, DEVICE)[0].numpy(), c)
    anew = topology(ac.Surface(a.points, a.faces, a.element.name), DEVICE)
    assert anew.face_edges is not t.face_edges


@pytest.mark.parametrize("name", list(_topology_surfaces()))
def test_device_topology_equals_the_surfaces(name):
    """The plan's topology, made by Warp kernels, against the Surface's NumPy tables (a
    separate implementation): every table row for row, the scalars to rounding."""
    from arraycontact_warp._surface import (
        face_balls,
        fill_surface,
        iota,
        morton_order,
        node_face_table,
        topology,
    )

    from arraycontact._grid import morton_keys
    from arraycontact._grid import morton_order as host_morton
    from arraycontact._select import boundary_topology

    m = _topology_surfaces()[name]
    # A first topology of a copy loads the kernels: the CPU launches this one in parts.
    topology(ac.Surface(m.points, m.faces, m.element.name), DEVICE)
    t = topology(m, DEVICE)
    assert topology(m, DEVICE) is t  # made once per Surface and device
    np.testing.assert_array_equal(t.face_edges.numpy(), m.face_edges)
    np.testing.assert_array_equal(t.edge_faces.numpy()[: len(m.edges)], m.edge_faces)
    offsets, ids = m.node_faces
    np.testing.assert_array_equal(t.nf_offsets.numpy(), offsets)
    np.testing.assert_array_equal(t.nf_ids.numpy(), ids)
    want = boundary_topology(m)[:4]
    got = (t.prev_node, t.next_node, t.prev_face, t.next_face)
    for g, w in zip(got, want):
        np.testing.assert_array_equal(g.numpy(), w)
    assert t.n_nodes == len(m.nodes)
    np.testing.assert_array_equal(t.nodes.numpy()[: t.n_nodes], m.nodes)
    assert t.closed == m.closed
    assert t.longest_edge == pytest.approx(m.longest_edge, rel=1e-15)
    radii = m.face_bounds[1]
    assert t.r_max == pytest.approx(radii.max(), rel=1e-15)
    assert t.r_small == pytest.approx(np.quantile(radii, 0.1), rel=1e-6)
    np.testing.assert_array_equal(t.node_box[0], m.node_box[0])
    np.testing.assert_array_equal(t.node_box[1], m.node_box[1])
    centres, radii_64 = face_balls(t, DEVICE)
    np.testing.assert_array_equal(centres.numpy(), m.face_bounds[0])
    c, r = m.face_bounds  # the radii to rounding (a GPU may fuse their squares' sums)
    scale = 1e-15 * np.abs(m.points).max()
    np.testing.assert_allclose(t.ball_box[0], (c - r[:, None]).min(0), rtol=1e-15, atol=scale)
    np.testing.assert_allclose(t.ball_box[1], (c + r[:, None]).max(0), rtol=1e-15, atol=scale)
    np.testing.assert_allclose(radii_64.numpy(), radii, rtol=1e-15)
    np.testing.assert_array_equal(t.edges.numpy()[: t.n_edges], m.edges)
    # The exact tables copied into a new Surface's cache equal its NumPy properties.
    fresh = ac.Surface(m.points, m.faces, m.element.name)
    fill_surface(fresh, DEVICE)
    assert {"_edge_table", "node_faces", "nodes", "closed", "node_box"} <= set(vars(fresh))
    for key in ("edges", "face_edges", "edge_faces", "edge_counts", "boundary_edges", "nodes"):
        np.testing.assert_array_equal(getattr(fresh, key), getattr(m, key), err_msg=key)
    for a, b in zip(fresh.node_faces + fresh.node_box, m.node_faces + m.node_box):
        np.testing.assert_array_equal(a, b)
    assert fresh.closed == m.closed
    # Morton orders on the device equal arraycontact._grid.morton_order's, and their sorted
    # keys morton_keys' (the JAX plan groups its trees from them).
    lo, extent = m.node_box[0] - 0.3, 1.7 * float((m.node_box[1] - m.node_box[0]).max())
    got, keys = morton_order(t.points, t.nodes, t.n_nodes, lo, extent, DEVICE, keys_too=True)
    np.testing.assert_array_equal(got, host_morton(m.points[m.nodes], lo, extent))
    np.testing.assert_array_equal(keys, morton_keys(m.points[m.nodes[got]], lo, extent))
    ids = iota(m.n_faces, m.n_faces, DEVICE)
    got, keys = morton_order(centres, ids, m.n_faces, lo, extent, DEVICE, keys_too=True)
    np.testing.assert_array_equal(got, host_morton(m.face_bounds[0], lo, extent))
    np.testing.assert_array_equal(keys, morton_keys(m.face_bounds[0][got], lo, extent))
    from arraycontact_jax._gradients import MAX_VALENCE, padded_node_faces

    np.testing.assert_array_equal(
        node_face_table(t, len(m.points), MAX_VALENCE, DEVICE).numpy(), padded_node_faces(m)
    )
    if name.startswith("closed"):
        assert t.closed
    if name.startswith("non-manifold"):
        assert not t.closed and (m.edge_counts == 3).any()
        # The pinch: several boundary edges start and end at node 0 (the last one wins).
        assert (m.boundary_edges[:, 0] == 0).sum() == 2 and (m.boundary_edges[:, 1] == 0).sum() == 3


@pytest.mark.skipif(
    not wp.is_cpu_available(), reason="Warp's CPU device cannot compile here (no LLVM)"
)
@pytest.mark.parametrize("mode", ["exact", "node"])
def test_cpu_parts_in_threads_equal_one_launch(monkeypatch, mode):
    """On the CPU the per-slave kernels run in parts, one thread each: every output equals the
    one-launch answer bit for bit (3 uneven parts: two bodies, self-contact, swept), also in
    a later call, whose parts are cut where the calls before said (Plan.cuts) and whose two
    trees are refitted at once."""
    import arraycontact_warp._parts as wd

    s = scenes.graded_surfaces(2**10, ratio=20)
    spiral = scenes.spiral_strip(2**10)

    monkeypatch.setattr(wd, "MIN_PART", 64)  # (these scenes' 512-1024 slaves in parts)

    def outputs(parts):
        monkeypatch.setattr(wd, "CPU_PARTS", parts)
        p = acw.plan(s.master, s.slave, device="cpu", mode=mode)
        for _ in range(2):  # a build, a refit; the third call refits both trees at once
            acw.detect(p, s.slave, s.master.points)
        moved_slaves = s.slave + np.array([0.13, -0.07, 0.11]) * s.master.longest_edge
        a = {k: v.copy() for k, v in acw.detect(p, moved_slaves, s.master.points).items()}
        even = np.linspace(0, p.n_slaves, parts + 1).astype(int)
        moved.extend(not np.array_equal(c, even) for c in p.cuts.values())
        q = acw.plan_self(spiral.master, device="cpu", mode=mode)
        b = {k: v.copy() for k, v in acw.detect_self(q, spiral.master.points).items()}

        step = scenes.closing_step(scenes.rough_surfaces(2**9))
        r = acw.plan_swept(step.master, step.slave_x0, device="cpu")
        args = (step.slave_x0, step.slave_x1, step.master.points, step.master_x1)
        c = {k: v.copy() for k, v in acw.detect_swept(r, *args).items()}
        return a, b, c

    moved = []
    outputs(1)  # the kernels' overloads loaded, so the next calls run in threads
    whole = outputs(1)
    parts = outputs(3)
    assert any(moved)  # the second call's cuts were not the even ones
    assert len(wd._loaded) > 0 and wd._pool is not None  # the threads ran
    for one, three in zip(whole, parts):
        for k in one:
            np.testing.assert_array_equal(one[k], three[k], err_msg=k)


def test_balanced_cuts_move_halfway_to_equal_times():
    """Parts of 50 slaves that took 1 and 3 s: at even work density within each part, equal
    times need the cut at 66.7; the next launch cuts halfway there. Times of zero keep the
    cuts."""
    from arraycontact_warp._parts import _balanced

    assert list(_balanced(np.array([0, 50, 100]), np.array([1.0, 3.0]))) == [0, 58, 100]
    assert list(_balanced(np.array([0, 30, 100]), np.zeros(2))) == [0, 30, 100]


@wp.kernel
def _morton_keys(x: wp.array(dtype=wp.vec3), w: wp.array(dtype=int), q: float, bits: int,
                 out: wp.array(dtype=wp.int64)):  # fmt: skip
    i = wp.tid()
    out[i] = warp_grid.morton_key(x[i], w[i], q, bits)


@pytest.mark.parametrize("bits, n_worlds", [(21, 1), (19, 60), (12, 2**20)])
def test_morton_keys_interleave_every_bit(bits, n_worlds):
    """The trees' keys (bits spread by masks) against a bit-by-bit interleave in NumPy: bit b
    of axis a at 3 b + a, the world id above, cells clamped to the box."""
    rng = np.random.default_rng(bits)
    n, q = 4096, np.float32(0.37)
    x = rng.uniform(-10.0, 0.37 * 2**bits * 1.1, (n, 3)).astype(np.float32)
    w = rng.integers(0, n_worlds, n).astype(np.int32)
    out = wp.zeros(n, dtype=wp.int64, device=DEVICE)
    xs, ws = wp.array(x, dtype=wp.vec3, device=DEVICE), wp.array(w, dtype=int, device=DEVICE)
    wp.launch(_morton_keys, n, inputs=[xs, ws, float(q), bits], outputs=[out], device=DEVICE)
    cells = np.clip(np.floor(x / q).astype(np.int64), 0, 2**bits - 1)
    want = w.astype(np.int64) << (3 * bits)
    for b in range(bits):
        for a in range(3):
            want |= ((cells[:, a] >> b) & 1) << (3 * b + a)
    np.testing.assert_array_equal(out.numpy(), want)


@wp.kernel
def _closest_nodes(grid: warp_grid.Grid, q: wp.array(dtype=wp.vec3),
                   normals: wp.array(dtype=wp.vec3), node: wp.array(dtype=int),
                   dist: wp.array(dtype=float)):  # fmt: skip
    i = wp.tid()
    n, d = _closest_node(q[i], 0, 1, grid, 1.0e30, 0.0, warp_grid.Plain(), normals, 3.0e38)
    node[i] = n
    dist[i] = d


@pytest.mark.parametrize(
    "kind, measured, aligned",
    [
        ("fine_patch", True, 1),
        ("clusters", True, 1),
        ("clusters", False, 0),
        ("caterpillar", True, 0),
        ("repeated", True, 1),
    ],
)
def test_tree_groups_are_the_radix_trees_largest_nodes(kind, measured, aligned):
    """The Warp tree's groups: on a level that groups by the rule, the largest nodes of the
    keys' radix tree holding at most W entries (a top-down split, independent of the build's
    neighbour rule); elsewhere W consecutive entries: level 0 of the caterpillar (groups of
    about 2 a plan does not make room for) and of the clusters in a tree not sized by a
    measure (groups of 3.5 on average, where room was made for 4). Every slot's box is its
    items' box, every item is in one slot, and the closest node through the tree equals brute
    force."""
    rng = np.random.default_rng(3)
    x = grid_points(kind, rng)
    n = len(x)
    lo = x.min(0)
    dev = DEVICE
    g, bits = warp_grid.new_grid(n, np.zeros(3), float((x.max(0) - lo).max()), dev, 0.0)
    xs = wp.array((x - lo).astype(np.float32), dtype=wp.vec3, device=dev)
    ids = wp.array(np.arange(n, dtype=np.int32), dtype=int, device=dev)
    world = wp.zeros(n, dtype=int, device=dev)
    means = warp_grid.measure_nodes(g, xs, ids, world, n, dev, bits) if measured else ()
    lay = warp_grid.allot(g, n, dev, means)
    warp_grid.build(g, lay, xs, ids, world, n, dev, wp.zeros(1, dtype=wp.int32, device=dev), bits)
    keys, order = g.keys.numpy()[:n], g.sorted_ids.numpy()[:n]
    counts, rule = g.counts.numpy(), g.aligned.numpy()
    slots, soff, off = g.slots.numpy(), g.slot_offsets.numpy(), g.offsets.numpy()
    items = np.frombuffer(g.items.numpy().tobytes(), np.float32).reshape(-1, 8)
    boxes = np.frombuffer(g.boxes.numpy().tobytes(), np.float32).reshape(-1, 8)
    up = g.up.numpy()
    assert rule[0] == aligned
    ids = items[: counts[1] * warp_grid.W, 3].view(np.int32)  # the slots of the groups
    assert np.array_equal(np.sort(ids[ids >= 0]), np.arange(n))
    assert (
        items[: counts[1] * warp_grid.W][ids < 0, 0] > items[: counts[1] * warp_grid.W][ids < 0, 4]
    ).all()
    ranges = [(p, p + 1) for p in range(n)]  # each entry's run of item positions
    nodes = True
    root = int(g.root.numpy()[0])
    for k in range(root + 1):
        m = counts[k]
        assert m == len(ranges) and (k < root or m == 1)
        s = slots[soff[k] : soff[k] + m]
        groups = {}
        for e in range(m):
            groups.setdefault(s[e] // warp_grid.W, []).append(e)
        got = sorted((ranges[es[0]][0], ranges[es[-1]][1]) for es in groups.values())
        if rule[k]:
            if nodes:  # (units made by W consecutive entries are no nodes of the radix tree)
                assert got == radix_groups(keys, ranges), k
        else:
            nodes = False
            want = [(ranges[e][0], ranges[min(e + warp_grid.W, m) - 1][1])
                    for e in range(0, m, warp_grid.W)]  # fmt: skip
            assert got == want, k
        for e in range(m):  # entries in slot order within a group, one slot each
            assert s[e] % warp_grid.W == e - min(groups[s[e] // warp_grid.W])
        if k >= 1:  # a group's other slots are empty
            free = np.setdiff1d(
                np.concatenate([np.arange(warp_grid.W) + warp_grid.W * g for g in groups]), s
            )
            assert (boxes[off[k] + free, 0] > boxes[off[k] + free, 4]).all()
        if k >= 1:
            for e, (a, b) in enumerate(ranges):
                rec = boxes[off[k] + s[e]]
                pts = (x - lo)[order[a:b]].astype(np.float32)
                np.testing.assert_array_equal(rec[:3], pts.min(0))
                np.testing.assert_array_equal(rec[4:7], pts.max(0))
                assert rec[3].view(np.int32) == warp_grid.W * e
                if k >= 2:
                    assert up[off[k - 1] // warp_grid.W + e] == s[e]
        else:
            rec = items[s]
            np.testing.assert_array_equal(rec[:, :3], (x - lo)[order].astype(np.float32))
        ranges = [(ranges[es[0]][0], ranges[es[-1]][1]) for _, es in sorted(groups.items())]
    q = (x[rng.integers(0, n, 300)] + rng.normal(size=(300, 3)) * 1e-3 - lo).astype(np.float32)
    node = wp.zeros(300, dtype=int, device=dev)
    dist = wp.zeros(300, dtype=float, device=dev)
    normals = wp.zeros(1, dtype=wp.vec3, device=dev)
    wp.launch(_closest_nodes, 300, inputs=[g, wp.array(q, dtype=wp.vec3, device=dev), normals],
              outputs=[node, dist], device=dev)  # fmt: skip
    d = np.linalg.norm(q[:, None, :] - (x - lo).astype(np.float32)[None], axis=2)
    np.testing.assert_allclose(dist.numpy(), d.min(1), rtol=1e-6, atol=1e-7)
    hit = d[np.arange(300), node.numpy()]
    np.testing.assert_allclose(hit, d.min(1), rtol=1e-6, atol=1e-7)


def test_plan_declares_the_overloads_its_detect_launches():
    """A Warp plan adds every scan-kernel overload its detections launch, so the first detect
    does not add one (each added overload rebuilds the whole module: three compilations of
    the scans on a first call). And each of the back end's Warp modules is built for one
    block size a device (Warp builds a module once for each block size its launches and loads
    ask: a cold cache compiled the topology's module four times on the CPU, the detection's
    twice on a GPU). And tri3's and quad4's kernels take their own element structs. In a
    fresh process, each case's types are new there."""
    code = """
import itertools, sys
import warp as wp
import arraycontact as ac, arraycontact_warp as acw
from arraycontact import scenes
from arraycontact_warp import _detect as d
kernels = [d._node_kernel, d._face_kernel, d._self_face_kernel, d._finish_kernel]
def sigs():
    return [set(k.overloads) for k in kernels]
cases = [("tri3", "exact", False), ("quad4", "exact", True), ("quad4", "node", False)]
# (a GPU machine's Warp may have no LLVM to compile for its CPU)
devices = ["cpu"] * wp.is_cpu_available() + ["cuda:0"] * wp.is_cuda_available()
fin = set()
for device, (element, mode, self_contact) in itertools.product(devices, cases):
    s = scenes.two_bodies(200, element=element)
    if self_contact:
        p = acw.plan_self(s.master, d_max=0.65, device=device, mode=mode)
    else:
        p = acw.plan(s.master, s.master.points[:50], d_max=0.65, device=device, mode=mode)
    before = sigs()
    x = s.master.points
    acw.detect_self(p, x) if self_contact else acw.detect(p, x[:50], x)
    assert sigs() == before, (device, element, mode, self_contact)
    assert sum(map(len, before)) > 0
    # quad4's kernels specialise on Quads (no curved-face code): an Element overload would
    # give the same answers, slower on a GPU
    struct = {"tri3": "Triangles", "quad4": "Quads"}[element]
    assert all(sig.startswith(struct) for sig in d._finish_kernel.overloads if sig not in fin)
    fin = set(d._finish_kernel.overloads)
    # (a second call loads the trees' modules before its threads launch their kernels)
    acw.detect_self(p, x) if self_contact else acw.detect(p, x[:50], x)
modules = {k.module for name, m in list(sys.modules.items()) if name.startswith("arraycontact_warp")
           for k in vars(m).values() if isinstance(k, wp.Kernel)}
blocks = {}
for m in modules:
    for context, block in m.execs:
        blocks.setdefault((m.name, context), set()).add(block)
assert blocks and all(len(b) == 1 for b in blocks.values()), blocks
print("ok")
"""
    import subprocess
    import sys

    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert r.returncode == 0 and r.stdout.strip().endswith("ok"), r.stderr[-3000:]


def test_a_float64_call_loads_only_the_modules_it_runs():
    """The package imports its float32 modules on the first use of their names, so that
    arraycontact.detect's float64 default runs the float64 twins alone, and a static
    detection does not import the swept module (in a fresh process: Warp declaring those
    functions took about 0.6 s of a first call); a swept call then imports it, and the
    names resolve to the float32 modules' as before."""
    code = """
import sys
import arraycontact as ac
from arraycontact import scenes
s = scenes.rough_surfaces(2**6)
c = ac.detect(s.slave, s.master, backend="warp")
assert (c.backend, c.dtype) == ("warp", "float64"), (c.backend, c.dtype)
assert int(c.active.sum()) > 0
assert "arraycontact_warp._float64._detect" in sys.modules
assert "arraycontact_warp._detect" not in sys.modules, "float32 imported"
assert "arraycontact_warp._geometry" not in sys.modules, "float32 imported"
assert "arraycontact_warp._float64._sweep" not in sys.modules, "swept module imported"
st = scenes.closing_rough_surfaces(2**6)
sw = ac.detect_swept(st.slave_x0, st.slave_x1, st.master, st.master_x1, backend="warp")
assert int(sw.hit.sum()) > 0
assert "arraycontact_warp._float64._sweep" in sys.modules
import arraycontact_warp as acw
assert acw.plan is sys.modules["arraycontact_warp._detect"].plan
assert acw.closest_point_face is sys.modules["arraycontact_warp._geometry"].closest_point_face
print("ok")
"""
    import subprocess
    import sys

    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert r.returncode == 0 and r.stdout.strip().endswith("ok"), r.stderr[-3000:]
    assert {"plan", "detect", "closest_point_face", "geometry"} <= set(dir(acw))
    with pytest.raises(AttributeError, match="no attribute 'no_such_name'"):
        acw.no_such_name  # noqa: B018
