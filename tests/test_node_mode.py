"""mode="node" (seed 000, section 2.2) against a direct, separate implementation of its rules."""

import numpy as np
import pytest

import arraycontact as ac
from arraycontact import scenes
from arraycontact.reference import _closest_on_faces

S = ac.Status


def _projection(e, r, xe):
    """Normal projection of r on one face by plain Newton, or None if it lands outside."""
    xi = e.centre.copy()
    for _ in range(50):
        x, dx = ac._elements.interpolate(e, xe, xi)
        jtj = dx.T @ dx
        xi = xi + np.linalg.solve(jtj, dx.T @ (r - x))
    x, _ = ac._elements.interpolate(e, xe, xi)
    inside = (xi @ e.constraints_a.T - e.constraints_b >= 0).all()
    return (np.linalg.norm(r - x), xi) if inside else None


def _boundary_links(surface):
    """For each boundary node m: (m2, face) before it and (m1, face) after it, walking the
    edges used by one face in that face's orientation."""
    k = surface.element.n_corners
    count = {}
    for row in surface.faces:
        for i in range(k):
            key = frozenset((row[i], row[(i + 1) % k]))
            count[key] = count.get(key, 0) + 1
    nxt, prv = {}, {}
    for f, row in enumerate(surface.faces):
        for i in range(k):
            a, b = row[i], row[(i + 1) % k]
            if count[frozenset((a, b))] == 1:
                nxt[a], prv[b] = (b, f), (a, f)
    return nxt, prv


def node_mode_direct(slave, surface, d_max):
    e = surface.element
    out = []
    nodes = surface.nodes
    nxt, prv = _boundary_links(surface)
    for r in slave:
        d = np.linalg.norm(surface.points[nodes] - r, axis=1)
        if d.min() > d_max:
            out.append((S.OUT_OF_RANGE, -1))
            continue
        m = nodes[np.argmin(d)]
        attached = np.nonzero((surface.faces == m).any(1))[0]
        proj = [
            (p[0], f)
            for f in attached
            if (p := _projection(e, r, surface.points[surface.faces[f]])) is not None
        ]
        tie = 1e-10 * surface.longest_edge  # the documented tie rule: smallest id wins
        if proj:
            dmin = min(p[0] for p in proj)
            out.append((S.OK, min(f for dist, f in proj if dist <= dmin + tie)))
            continue
        _, d2 = _closest_on_faces(
            e, np.repeat(r[None], len(attached), 0), surface.points[surface.faces[attached]]
        )
        closest = attached[np.sqrt(d2) <= np.sqrt(d2.min()) + tie].min()
        if m not in nxt:
            out.append((S.BLIND_SPOT, closest))
            continue
        (m2, f2), (m1, f1) = prv[m], nxt[m]
        n2, n1 = surface.face_normals[f2], surface.face_normals[f1]
        rm, rm1, rm2 = surface.points[[m, m1, m2]]
        convex = np.cross(rm - rm2, rm1 - rm) @ (n1 + n2) >= 0  # eq. (12)
        a = np.cross(n2, rm - rm2) @ (r - rm) >= 0  # eq. (13)
        b = np.cross(n1, rm1 - rm) @ (r - rm) >= 0
        inside = (a and b) if convex else (a or b)
        out.append((S.BLIND_SPOT, closest) if inside else (S.PASSING_BY, -1))
    return out


def l_shape():
    """Three unit quads in an L: a concave corner at (1, 1)."""
    pts = np.array([[x, y, 0.0] for y in range(3) for x in range(3)])
    quads = np.array([[0, 1, 4, 3], [1, 2, 5, 4], [3, 4, 7, 6]])
    return ac.Surface(pts, quads, "quad4")


def roof():
    """A convex ridge along y: two tilted quad strips meeting at x = 0 (external blind spot)."""
    pts = []
    for y in range(4):
        pts += [[-1.0, y, 0.0], [0.0, y, 0.6], [1.0, y, 0.0]]
    pts = np.array(pts)
    quads = [[3 * j, 3 * j + 1, 3 * j + 4, 3 * j + 3] for j in range(3)]
    quads += [[3 * j + 1, 3 * j + 2, 3 * j + 5, 3 * j + 4] for j in range(3)]
    return ac.Surface(pts, np.array(quads), "quad4")


def flat_square(element="quad4"):
    x, y = np.meshgrid(np.arange(3.0), np.arange(3.0), indexing="ij")
    return scenes.grid_surface(x, y, 0 * x, element)


CASES = {
    "convex_square": flat_square,
    "convex_square_tri": lambda: flat_square("tri3"),
    "concave_l": l_shape,
    "roof": roof,
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_node_mode_matches_the_paper_rules(backend, case):
    _check_paper_rules(case, backend=backend)


@pytest.mark.parametrize("case", sorted(CASES))
def test_warp_node_mode_matches_the_paper_rules(case):
    """The Warp kernels' node mode, in float64 (the direct rules' tie tolerance)."""
    _check_paper_rules(case, backend="warp", dtype="float64")


_DIRECT = {}


def _check_paper_rules(case, **options):
    surface = CASES[case]()
    rng = np.random.default_rng(0)
    lo, hi = surface.points.min(0) - 1.0, surface.points.max(0) + 1.0
    slave = rng.uniform(lo, hi, (300, 3))
    d_max = 1.0
    if case not in _DIRECT:  # the direct rules (plain Python, seconds) once for the back ends
        _DIRECT[case] = node_mode_direct(slave, surface, d_max)
    want = _DIRECT[case]
    c = ac.detect(slave, surface, mode="node", d_max=d_max, **options)
    status = np.array([w[0] for w in want])
    assert np.array_equal(c.status, status)
    active = np.isin(status, [S.OK, S.BLIND_SPOT])
    assert np.array_equal(c.active, active)
    face = np.array([w[1] for w in want])
    assert np.array_equal(c.face[active], face[active])
    # The rules this scene is built for fired.
    seen = set(status.tolist())
    assert {S.OK, S.OUT_OF_RANGE, S.PASSING_BY} <= seen
    if case == "roof":
        assert S.BLIND_SPOT in seen


def test_concave_corner_uses_or():
    from arraycontact._select import boundary_frames, proximal

    s = l_shape()
    prev_node, next_node, prev_n, next_n, on, concave = boundary_frames(s)
    # Boundary runs counter-clockwise: 5 -> 4 -> 7 around the re-entrant corner (1, 1).
    assert (prev_node[4], next_node[4]) == (5, 7) and concave[4]
    assert on[[0, 1, 2, 3, 5, 6, 7]].all() and not on[8]
    assert not concave[[0, 2, 6]].any()  # the outer corners are convex (eq. 12)
    # A point on the inner side of edge 5 -> 4 only (y < 1) but beyond edge 4 -> 7 (x > 1):
    # one half-space holds, so it is inside at the concave corner (OR) ...
    p = np.array([[1.5, 0.5, 0.1]])
    args = (s.points, prev_node, next_node, prev_n, next_n)
    assert proximal(np, p, np.array([4]), *args, concave)[0]
    # ... and would be outside at a convex one (AND).
    assert not proximal(np, p, np.array([4]), *args, np.zeros_like(concave))[0]
    # Beyond the convex outer corner (2, 0): passing by.
    c = ac.detect(np.array([[2.3, -0.3, 0.1]]), s, mode="node", d_max=1.0, backend="numpy")
    assert c.master_node[0] == 2 and c.status[0] == S.PASSING_BY and not c.active[0]


@pytest.mark.parametrize("backend", ["numpy", "warp"])
def test_closed_master_has_no_passing_by(backend):
    from test_surface import cube

    rng = np.random.default_rng(1)
    slave = rng.uniform(-0.5, 1.5, (200, 3))
    c = ac.detect(slave, cube(), mode="node", d_max=1.0, backend=backend, dtype="float64")
    assert not (c.status == S.PASSING_BY).any()
    want = node_mode_direct(slave, cube(), 1.0)
    assert np.array_equal(c.status, [w[0] for w in want])
