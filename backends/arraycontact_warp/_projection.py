"""Stage 4 in Warp: candidate faces by their boxes within min(closest-node distance, d_max)
through the face tree, and the closest point on each (tri3 in closed form,
other elements by the active-set method from start I and, on curved faces, also from the
centre, the mid-edge nodes and a lattice start, then the exact edges: as the NumPy back end).
Each slave scans its candidates once, keeping the smallest distance and applying the tie rule
(smallest face id within `tie` of it) as it goes, and a second time only when unsure, so no
pair buffer exists and nothing can overflow."""

from __future__ import annotations

from typing import Any

import warp as wp

from ._closest_node import counts
from ._geometry import (
    EDGE,
    FACE,
    VERTEX,
    FaceNodes,
    Triangles,
    _active_set,
    _at,
    _segment,
    _start_one,
    beyond_an_edge,
    closest_point_edge,
    closest_point_triangle,
    coefficients,
    corners,
    curved_convex,
    edge_xi,
    face_nodes,
    face_point,
    face_tangents,
    is_bilinear,
    straight,
    surely_convex,
    unit_cross,
)
from ._grid import (
    Grid,
    Own,
    Plain,
    W,
    box_gap_sq,
    children,
    descend,
    enters,
    entry,
    item_hi,
    item_id,
    item_lo,
    item_world,
    may_face_item,
    next_pending,
    surely_facing,
)
from ._real import real, vec2, vec3

# Forward only, no loop unrolling (a scan's loops unrolled copy the projection many times).
wp.set_module_options({"enable_backward": False, "max_unroll": 1})


@wp.struct
class Master:
    points: wp.array(dtype=vec3)  # local frame
    faces: wp.array2d(dtype=int)
    face_world: wp.array(dtype=int)
    node_world: wp.array(dtype=int)
    nf_offsets: wp.array(dtype=int)  # node -> faces (CSR): the vertex pseudo-normals
    nf_ids: wp.array(dtype=int)
    face_edges: wp.array2d(dtype=int)
    edge_faces: wp.array2d(dtype=int)
    # node mode on an open master: the boundary neighbours of each node and the faces owning
    # those boundary edges (-1 off the boundary), as arraycontact._select.boundary_topology
    prev_node: wp.array(dtype=int)
    next_node: wp.array(dtype=int)
    prev_face: wp.array(dtype=int)
    next_face: wp.array(dtype=int)


@wp.func
def _nearer(e: int, t: real, d: real, b_e: int, b_t: real, b_d: real):
    if d < b_d:
        return e, t, d
    return b_e, b_t, b_d


@wp.func
def exact_edges(
    el: Any, r: vec3, xe: FaceNodes, xi: vec2, feature: int, local: int, conv: int, best: real
):
    """The exact closest point over the face's edges (closest_point_edge) replaces Newton's
    answer xi (at squared distance `best`) when at most as far: no start can miss a minimum
    on an edge, and on a degenerate quad4 Newton can stop at a stationary corner. The first
    edge wins a tie. quad4's four edges are written out on the node fields (a loop picks each
    edge's nodes at run time, which a GPU thread pays in selects)."""
    e_e = int(-1)
    e_t = real(0.0)
    e_d = real(3.0e38)
    if is_bilinear(el):
        t, d = _segment(r, xe.x0, xe.x1)
        e_e, e_t, e_d = _nearer(0, t, d, e_e, e_t, e_d)
        t, d = _segment(r, xe.x1, xe.x2)
        e_e, e_t, e_d = _nearer(1, t, d, e_e, e_t, e_d)
        t, d = _segment(r, xe.x2, xe.x3)
        e_e, e_t, e_d = _nearer(2, t, d, e_e, e_t, e_d)
        t, d = _segment(r, xe.x3, xe.x0)
        e_e, e_t, e_d = _nearer(3, t, d, e_e, e_t, e_d)
    else:
        for e in range(corners(el)):
            t, d = closest_point_edge(el, r, xe, e)
            e_e, e_t, e_d = _nearer(e, t, d, e_e, e_t, e_d)
    if e_e < 0 or not (e_d <= best):
        return xi, feature, local, conv
    e_f = EDGE
    e_l = e_e
    if e_t <= 0.0:
        e_f = VERTEX
    elif e_t >= 1.0:
        e_f = VERTEX
        e_l = (e_e + 1) % corners(el)
    return edge_xi(el, e_e, e_t), e_f, e_l, 1


@wp.func
def lattice_start(el: Any, r: vec3, xe: FaceNodes, pe: FaceNodes):
    """The closest of a 5 x 5 lattice of interior points (15 on triangles), as in NumPy."""
    best = el.centre
    best_d = real(3.0e38)
    for i in range(5):
        for j in range(5):
            xi = vec2(-real(0.8) + real(0.4) * real(i), -real(0.8) + real(0.4) * real(j))
            if el.n_corners == 3:
                xi = vec2(real(0.1) + real(0.175) * real(i), real(0.1) + real(0.175) * real(j))
            if el.n_corners != 3 or i + j <= 4:
                d = wp.length_sq(r - _at(el, xe, pe, xi))
                if d < best_d:
                    best_d = d
                    best = xi
    return best


@wp.func
def project(
    el: Triangles, m: Master, grid: Grid, k: int, s: vec3, f: int, iterations: int, tol: real
):
    """tri3: Voronoi regions on the corners the face grid holds in key order (item k), read
    contiguously; a per-face node block would live in slow local memory."""
    return _on_triangle(s, grid.corners[k, 0], grid.corners[k, 1], grid.corners[k, 2])


@wp.func
def _on_triangle(s: vec3, x0: vec3, x1: vec3, x2: vec3):
    """project's answer on the triangle (x0, x1, x2), in a frame at x0."""
    r = s - x0
    b = x1 - x0
    c = x2 - x0
    xi, feature, local = closest_point_triangle(r, vec3(0.0), b, c)
    return xi, feature, local, 1, r - (xi[0] * b + xi[1] * c)


@wp.func
def project_face(el: Triangles, m: Master, grid: Grid, s: vec3, f: int, iterations: int, tol: real):
    """`project` by face id alone (node mode: the face's grid item is not known)."""
    return _on_triangle(
        s, m.points[m.faces[f, 0]], m.points[m.faces[f, 1]], m.points[m.faces[f, 2]]
    )


@wp.func
def project_face(  # noqa: F811 (a Warp overload)
    el: Any, m: Master, grid: Grid, s: vec3, f: int, iterations: int, tol: real
):
    return project(el, m, grid, -1, s, f, iterations, tol)


# A Warp overload of the tri3 `project` above, chosen by the element struct's type.
@wp.func
def project(  # noqa: F811 (a Warp overload)
    el: Any,
    m: Master,
    grid: Grid,
    k: int,
    s: vec3,
    f: int,
    iterations: int,
    tol: real,
):
    """Closest point of s on face f in a frame at the face's first node: xi, feature, local,
    converged, s - point. (grid and k: the tri3 overload's data.)"""
    x0 = m.points[m.faces[f, 0]]
    return _project_nodes(el, s - x0, face_nodes(m.points, m.faces, f, x0), iterations, tol)


@wp.func
def _project_nodes(el: Any, r: vec3, xe: FaceNodes, iterations: int, tol: real):
    """`project` of the point r on the face of nodes xe (both in a frame at its first node)."""
    xi = vec2(0.0)
    feature = int(0)
    local = int(-1)
    conv = int(1)
    # Start I, then on curved faces the centre, each mid-edge node and the lattice start, on
    # a bilinear face the lattice start, unless one start surely suffices (on a curved face:
    # if it converges); the closest result wins, the first on a tie. One call site keeps the
    # generated code small.
    n_starts = 1
    pe = coefficients(el, xe)
    proven = False  # a curved face proven convex: start I alone, if its active set converges
    if not straight(el):
        proven = curved_convex(el, r, pe)
        if not proven:
            n_starts = el.n_corners + 3
    elif is_bilinear(el):
        if beyond_an_edge(r, xe):
            n_starts = 0  # the closest point is on the edges
        elif not surely_convex(el, r, xe):
            n_starts = 2
    best = real(3.0e38)
    k = int(0)
    while k < n_starts:
        start = el.centre
        if k == 0:
            start = _start_one(el, r, xe, pe)
        elif k == el.n_corners + 2 or straight(el):
            start = lattice_start(el, r, xe, pe)
        elif k > 1:
            start = el.nodes[el.n_corners + k - 2]
        xi2, f2, l2, c2 = _active_set(el, r, xe, pe, start, iterations, tol)
        d2 = wp.length_sq(r - _at(el, xe, pe, xi2))
        if d2 < best:
            best = d2
            xi = xi2
            feature = f2
            local = l2
            conv = c2
        if k == 0 and proven and c2 == 0:
            # (unconverged even where the distance is convex: its stall on an edge did so,
            # 1.15 from face 668's closest point for the crumpled tri6 sheet's node 3479)
            proven = False
            n_starts = el.n_corners + 3
        k += 1
    # The edges' exact closest points guard against a start that missed an edge minimum; on
    # a curved face proven convex the one start's converged active set is the minimum (its
    # edge steps exact already): a quarter of a curved detection's time on the CPU.
    if not proven:
        xi, feature, local, conv = exact_edges(el, r, xe, xi, feature, local, conv, best)
    return xi, feature, local, conv, r - face_point(el, xe, xi)


@wp.struct
class Kept:
    """Each slave's chosen face as its face scan projected it, so that the finish kernel need
    not project it again (a bilinear or curved face's projection, Newton from one or more
    starts, is most of the finish kernel's time: quad4 at 2^16 on the CPU 22.9 -> 10.9 ms
    thread time). item: the face-grid item whose projection xi and tag (feature, local,
    converged, packed by `keep`) hold, -1 when none. A scan that returns to an earlier face
    of the tie band (scan_faces) leaves another face's item here: that face is projected
    again."""

    item: wp.array(dtype=int)
    xi: wp.array(dtype=vec2)
    tag: wp.array(dtype=int)


@wp.struct
class Unkept:
    """No store (`kept_type`): triangles, whose closest point costs less than its store, and
    GPUs, where the stored values live on through the scan and cost it registers (H100, 2^17:
    self-contact's quad4 scans 6-8 % slower, the two-body quad4 detection 2 % faster)."""

    item: wp.array(dtype=int)  # (unused: a Warp struct needs a field)


def kept_type(el, cuda: bool):
    """The `kp` struct of a detection's scans: Kept for bilinear and curved faces off a GPU."""
    return Kept if el is not Triangles and not cuda else Unkept


@wp.func
def keep(kp: Kept, i: int, k: int, xi: vec2, feature: int, local: int, conv: int):
    kp.item[i] = k
    kp.xi[i] = xi
    kp.tag[i] = feature + 4 * (local + 1) + 64 * conv  # feature < 4, -1 <= local < 15
    return 0


@wp.func
def keep(kp: Unkept, i: int, k: int, xi: vec2, feature: int, local: int, conv: int):  # noqa: F811
    return 0


@wp.func
def projected(
    el: Any, m: Master, grid: Grid, kp: Unkept, i: int, k: int, s: vec3, f: int,
    iterations: int, tol: real,
):  # fmt: skip
    """`project` of slave i on face f (item k), from `keep`'s store where it holds item k."""
    return project(el, m, grid, k, s, f, iterations, tol)


@wp.func
def projected(  # noqa: F811 (a Warp overload)
    el: Any, m: Master, grid: Grid, kp: Kept, i: int, k: int, s: vec3, f: int,
    iterations: int, tol: real,
):  # fmt: skip
    if kp.item[i] != k:
        return project(el, m, grid, k, s, f, iterations, tol)
    tag = kp.tag[i]
    xi = kp.xi[i]
    x0 = m.points[m.faces[f, 0]]
    xe = face_nodes(m.points, m.faces, f, x0)
    return xi, tag % 4, (tag // 4) % 16 - 1, tag // 64, (s - x0) - face_point(el, xe, xi)


_candidates = wp.types.vector(length=W, dtype=int)

#: arraycontact._grid.FACING_TOL: self-contact counts faces with n_i . n_f < -FACING_TOL.
FACING_TOL = 1.0e-6


@wp.func
def holds(m: Master, f: int, node: int):
    """Whether face f has node `node`."""
    found = int(0)
    for c in range(m.faces.shape[1]):
        if m.faces[f, c] == node:
            found = 1
    return found == 1


@wp.func
def holds_own(o: Plain, m: Master, f: int):
    return False


@wp.func
def holds_own(o: Own, m: Master, f: int):  # noqa: F811 (a Warp overload)
    return holds(m, f, o.node)


#: A face's slab: its unit normal n (of the corners: the diagonals' on quads) and the range
#: lo..hi of n . x over its corners, which holds a straight-edged face (its points are convex
#: combinations of its corners), and on curved faces over its Bernstein control points too
#: (their hull holds the face). A degenerate face: n = 0, the whole range.
Slab = wp.types.vector(length=5, dtype=real)


@wp.func
def slab_gap(o: Plain, slab: wp.array(dtype=Slab), f: int, s: vec3):
    """A lower bound of s's distance to face f beyond its box's: none in a two-body scan (the
    rough scenes' faces lie flat, where their boxes are tight)."""
    return real(0.0)


@wp.func
def slab_gap(o: Own, slab: wp.array(dtype=Slab), f: int, s: vec3):  # noqa: F811
    """Self-contact: s's distance to face f's slab (`Slab`), a lower bound of its distance to
    the face: a box is loose across a tilted face (the crumpled sheet's), whose projection
    this skips."""
    b = slab[f]
    x = b[0] * s[0] + b[1] * s[1] + b[2] * s[2]
    return wp.max(real(0.0), wp.max(x - b[4], b[3] - x))


@wp.func
def project_facing(
    o: Plain, el: Any, m: Master, grid: Grid, k: int, s: vec3, f: int, iterations: int, tol: real
):
    """`project` of s on face f (tree item k), and whether the face counts with its closest
    point there: always, or (Own, self-contact) when its unit normal there faces the slave's
    (n_i . n_f < -FACING_TOL)."""
    xi, feature, local, conv, diff = project(el, m, grid, k, s, f, iterations, tol)
    return xi, feature, local, conv, diff, True


@wp.func
def project_facing(  # noqa: F811 (a Warp overload)
    o: Own,
    el: Triangles,
    m: Master,
    grid: Grid,
    k: int,
    s: vec3,
    f: int,
    iterations: int,
    tol: real,
):
    xi, feature, local, conv, diff = project(el, m, grid, k, s, f, iterations, tol)
    c0 = grid.corners[k, 0]
    n = unit_cross(grid.corners[k, 1] - c0, grid.corners[k, 2] - c0)
    return xi, feature, local, conv, diff, wp.dot(o.normal, n) < -real(FACING_TOL)


@wp.func
def project_facing(  # noqa: F811 (a Warp overload)
    o: Own, el: Any, m: Master, grid: Grid, k: int, s: vec3, f: int, iterations: int, tol: real
):
    # The face's nodes loaded once for both: loaded again for the normal, the self-contact
    # face kernel ran 6-9 % slower on an H100 (2^17, the five self-contact scenes).
    x0 = m.points[m.faces[f, 0]]
    xe = face_nodes(m.points, m.faces, f, x0)
    xi, feature, local, conv, diff = _project_nodes(el, s - x0, xe, iterations, tol)
    t0, t1 = face_tangents(el, xe, xi)
    facing = wp.dot(o.normal, unit_cross(t0, t1)) < -real(FACING_TOL)
    return xi, feature, local, conv, diff, facing


@wp.func
def first_reach(
    kind: Plain,
    el: Any,
    m: Master,
    node: int,
    dn: real,
    d_max: real,
    nlo: wp.array(dtype=vec3),
    nhi: wp.array(dtype=vec3),
):
    """How far the face scan need reach once `node`, a node that counts for the slave, is at
    distance dn: its faces are no farther (else d_max)."""
    return wp.min(dn, d_max)


@wp.func
def first_reach(  # noqa: F811 (a Warp overload)
    kind: Own,
    el: Any,
    m: Master,
    node: int,
    dn: real,
    d_max: real,
    nlo: wp.array(dtype=vec3),
    nhi: wp.array(dtype=vec3),
):
    # Self-contact: the closest (obtuse) node bounds the answer only through a face of its
    # own that counts (arraycontact._detect.self_reach, which projects on them): the node is
    # a point of that face. A face of straight edges (tri3, quad4) whose corner normals all
    # face the slave's counts wherever its closest point is (its normal x_xi x x_eta is an
    # affine mix of the corner ones), so no projection is needed. On a thin body most nodes
    # have such a face across the gap: their scan starts near the gap, not at d_max.
    best = d_max
    if node >= 0 and m.faces.shape[1] == el.n_corners:
        for j in range(m.nf_offsets[node], m.nf_offsets[node + 1]):
            f = m.nf_ids[j]
            if not holds(m, f, kind.node):
                if surely_facing(kind.normal, nlo[f], nhi[f]):
                    best = wp.min(best, dn)
    return best


@wp.struct
class NoNodes:
    """A face scan alone (a node tree and kernel of their own find the closest node)."""

    unused: int


@wp.struct
class Nodes:
    """A face scan that finds the closest node too (see scan_faces). A type, not a flag: the
    node code present but switched off at run time made the two-body face scan 1.15-1.25x
    slower on an H100 (2^20: uniform 0.92 -> 1.15 ms, graded_1000 1.75 -> 2.21)."""

    unused: int


@wp.func
def finds_nodes(nt: NoNodes):
    return False


@wp.func
def finds_nodes(nt: Nodes):  # noqa: F811 (a Warp overload)
    return True


@wp.func
def _walk(nt: NoNodes, reach: real, n_wide: real):
    """How far the walk goes: the face reach, or the node reach where it is farther."""
    return reach


@wp.func
def _walk(nt: Nodes, reach: real, n_wide: real):  # noqa: F811 (a Warp overload)
    return wp.max(reach, n_wide)


@wp.func
def _face_node(el: Triangles, m: Master, grid: Grid, k: int, f: int, c: int):
    """Node c of face f (tree item k): a triangle's from the tree's own copy of its corners
    (no gather through the connectivity)."""
    return grid.corners[k, c]


@wp.func
def _face_node(el: Any, m: Master, grid: Grid, k: int, f: int, c: int):  # noqa: F811
    return m.points[m.faces[f, c]]


@wp.func
def scan_faces(
    el: Any,
    m: Master,
    grid: Grid,
    s: vec3,
    world: int,
    shared: int,
    rho: real,
    tie: real,
    limit: real,
    slack: real,
    iterations: int,
    tol: real,
    o: Any,
    kp: Any,
    i: int,
    d_max: real,
    nt: Any,
    track: int,
    n_reach: real,
    n_limit: real,
    normals: wp.array(dtype=vec3),
    nlo: wp.array(dtype=vec3),
    nhi: wp.array(dtype=vec3),
    slab: wp.array(dtype=Slab),
):
    """Over the faces whose box is within rho of s: the smallest distance, and the face of the
    tie rule (smallest id within `tie` of it) with its tree item. Its projection goes to kp
    (slave i, `keep`) when it is made, not kept through the scan: registers all threads pay.
    shared = 1: every item is of this world.

    The face tree depth first (_grid: a visit tests an entry's W children, goes on with the
    nearest, keeps the others in `stack`), within the reach; at a leaf, its faces within
    reach are collected, the nearest box's projected first, the others tested again against
    the reach of the running minimum (which rejects most before their projection). The reach
    shrinks to the running minimum (plus rounding slack) after each projection: no farther
    face can hold the answer.

    limit < 0, the first scan: the tie rule applied as the faces come, from the face at the
    running minimum, the smallest distance of any other face seen and the chosen face. When a
    new minimum pushes the chosen face out of the band, the band's other members were all seen
    before: the face at the old minimum, if in the band, and, when the second smallest
    distance is in it too, faces this scan did not keep: then `unsure` = 1 (three faces within
    about twice `tie`: rare) and the caller runs the second scan. limit >= 0, the second
    scan: the smallest face id at distance <= limit, skipping larger ids than the best so far.
    rho < 0 (Nodes): no face is projected (a second scan for the closest node alone).

    nt: NoNodes, or Nodes with track = 1 (no node tree: NODES_IN_FACE_SCAN): the same walk
    also finds the closest master node within d_max that counts for the slave (`counts`:
    self-contact's another node, obtuse), as _closest_node's scan does over the node tree,
    from the nodes of the faces it meets. A node within reach r of s has every face of its
    own within r, and (self-contact) one that may face the slave: a pseudo-normal obtuse to
    the slave's is an angle-weighted mean of its faces' normals there, so one of those is
    obtuse too, and its face's normal box lets the walk in. So walking the faces within the
    node reach (n_reach: d_max, or less from a bound, shrinking to the closest node's
    distance plus the tie band) meets it. Each closer node found may bound the face reach
    (`first_reach`). n_limit < 0: the node at the smallest distance and the smallest
    distance of another node (the caller's tie test); n_limit >= 0: the smallest node id
    within n_limit. The faces between the face reach and the node reach are walked but not
    projected. normals: the nodes' pseudo-normals, nlo / nhi the faces' normal boxes
    (self-contact's; unread otherwise).

    o: Plain, or Own (self-contact): faces that hold the slave's node, or whose normal at
    the closest point does not face the slave's (arraycontact.detect_self), count as absent."""
    reach = rho
    dmin = real(3.0e38)
    f_min = int(-1)  # the face at dmin and its tree item
    k_min = int(-1)
    second = real(3.0e38)  # the smallest distance of the other faces
    best = int(-1)
    b_d = real(3.0e38)
    b_k = int(-1)
    unsure = int(0)
    n_dmin = real(3.0e38)  # Nodes: the closest node's distance, the next node's, its id
    n_second = real(3.0e38)
    n_best = int(-1)
    # (a node's distance against the boxes' gaps: _closest_node's widening for rounding)
    n_wide = real(-1.0)
    if track == 1:
        n_wide = n_reach * real(1.0001)
    walk = _walk(nt, reach, n_wide)
    found = _candidates(0)
    stack = wp.uint64(0)  # level k's W bits: its children still to visit
    root = grid.root[0]
    lv = root
    j = int(0)
    visit = int(1)
    while visit == 1:
        visit = 0
        n = int(0)
        first = int(0)  # the collected face with the nearest box: projected first
        box = entry(grid, lv, j)
        if enters(s, world, shared, box, walk):
            if lv == 1:
                first_d2 = real(3.0e38)
                for t in range(W):
                    k = box.first + t  # (an empty slot is out of every reach)
                    d2 = box_gap_sq(s, item_lo(grid, k), item_hi(grid, k))
                    near = d2 <= walk * walk
                    if near and shared == 0:  # (Warp evaluates both sides of `or`)
                        near = item_world(grid, k) == world
                    if near:
                        near = may_face_item(o, grid, k)
                    if finds_nodes(nt) and near and d2 <= n_wide * n_wide:
                        f = item_id(grid, k)
                        for c in range(m.faces.shape[1]):
                            e2 = wp.length_sq(_face_node(el, m, grid, k, f, c) - s)
                            if e2 <= n_wide * n_wide:
                                e = wp.sqrt(e2)
                                node = m.faces[f, c]
                                if e <= d_max and counts(o, normals, node):
                                    if n_limit < real(0.0):
                                        if e < n_dmin:
                                            n_second = n_dmin
                                            n_dmin = e
                                            n_best = node
                                            # (a face of that node may bound the answer)
                                            r = first_reach(o, el, m, node, e, d_max, nlo, nhi)
                                            reach = wp.min(reach, r + slack)
                                        elif node != n_best:  # (met again through another face)
                                            n_second = wp.min(n_second, e)
                                    elif e <= n_limit and (n_best < 0 or node < n_best):
                                        n_best = node
                                        n_dmin = wp.min(n_dmin, e)
                                    n_wide = wp.min(n_reach, wp.max(n_dmin + tie, n_limit))
                                    n_wide = n_wide * real(1.0001)
                                    walk = _walk(nt, reach, n_wide)
                    if near:
                        near = d2 <= reach * reach
                        if finds_nodes(nt):  # (a second scan for the node alone: rho < 0)
                            near = near and reach >= real(0.0)
                    if near:
                        if d2 < first_d2:
                            first = n
                            first_d2 = d2
                        found[n] = k
                        n += 1
            else:
                mask, near_c = children(grid, s, world, shared, lv, box.first, walk, 0, o)
                if mask != 0:
                    stack, lv, j = descend(stack, lv, box.first, mask, near_c)
                    visit = 1
        for t in range(n):
            tt = t
            if t == 0:
                tt = first
            elif t == first:
                tt = 0
            kt = found[tt]
            f = item_id(grid, kt)
            cut = wp.min(reach, wp.max(dmin, limit) + slack)
            near = box_gap_sq(s, item_lo(grid, kt), item_hi(grid, kt)) <= cut * cut
            # The second scan skips ids above the best so far.
            if near:
                near = not holds_own(o, m, f)
            if near:  # (slack: the slab's rounding, 10 eps of the extent at most)
                near = slab_gap(o, slab, f, s) <= cut + slack
            if near and (limit < real(0.0) or best < 0 or f < best):
                xi, feature, local, conv, diff, ok = project_facing(
                    o, el, m, grid, kt, s, f, iterations, tol
                )
                d = wp.length(diff)
                if not ok:
                    d = real(3.0e38)
                top = limit
                if limit < real(0.0):
                    if d < dmin:
                        top = d + tie
                        if best >= 0 and b_d > top:
                            best = int(-1)
                            if dmin <= top:
                                best = f_min
                                b_d = dmin
                                b_k = k_min
                                if second <= top:
                                    unsure = 1
                        second = wp.min(second, dmin)
                        dmin = d
                        f_min = f
                        k_min = kt
                    else:
                        second = wp.min(second, d)
                    top = dmin + tie
                else:
                    dmin = wp.min(dmin, d)
                if d <= top and (best < 0 or f < best):
                    best = f
                    b_d = d
                    b_k = kt
                    keep(kp, i, kt, xi, feature, local, conv)
                reach = wp.min(reach, wp.max(dmin, limit) + slack)
                walk = _walk(nt, reach, n_wide)
        if visit == 0:
            stack, lv, j, visit = next_pending(grid, root, stack, lv, j)
    return dmin, best, b_k, unsure, n_dmin, n_second, n_best


@wp.func
def scan_attached(
    el: Any,
    m: Master,
    grid: Grid,
    s: vec3,
    node: int,
    only_face: int,
    limit: real,
    iterations: int,
    tol: real,
    own: int,
):
    """Node mode (seed 000 section 2.2): the projections of s on the faces attached to its
    closest node (self-contact, own >= 0: but those holding node `own`). Returns the
    smallest distance among the projections that land on a face's
    interior and among all, and the smallest face id at distance <= limit (only interior
    landings when only_face = 1) with its projection."""
    d_face = real(3.0e38)
    d_any = real(3.0e38)
    best = int(-1)
    b_xi = vec2(0.0)
    b_feature = int(-1)
    b_local = int(-1)
    b_conv = int(0)
    b_diff = vec3(0.0)
    for j in range(m.nf_offsets[node], m.nf_offsets[node + 1]):
        f = m.nf_ids[j]
        if own >= 0:
            if holds(m, f, own):
                continue
        xi, feature, local, conv, diff = project_face(el, m, grid, s, f, iterations, tol)
        d = wp.length(diff)
        d_any = wp.min(d_any, d)
        if feature == FACE:
            d_face = wp.min(d_face, d)
        if d <= limit and (only_face == 0 or feature == FACE) and (best < 0 or f < best):
            best = f
            b_xi = xi
            b_feature = feature
            b_local = local
            b_conv = conv
            b_diff = diff
    return d_face, d_any, best, b_xi, b_feature, b_local, b_conv, b_diff


__all__ = [
    "Kept",
    "NoNodes",
    "Nodes",
    "Unkept",
    "kept_type",
    "Master",
    "holds",
    "project",
    "projected",
    "scan_attached",
    "scan_faces",
]
