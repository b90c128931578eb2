"""Warp detection for simulators: `plan` allocates every buffer once; `detect` only launches
kernels (no allocation, no host synchronisation), so a CUDA graph can capture and replay it.

Stages, one module each (the names of the other back ends): _prepare (master geometry from
the current coordinates), _grid (the size-adaptive tree: Morton keys with the world id, one
radix sort, a reduction launch per level), _closest_node, _projection (candidates and
projections), _select (gap, normal). Three kernels, each slave one thread: the closest node
(the node tree depth first from the bound of its nearest leaf); in exact mode the closest face
(the face tree depth first within the reach, each leaf's faces within reach projected, the tie
rule applied as they come, a second scan only when that was unsure); then the chosen face's
projection, or in node mode the projections on the faces attached to the closest node, and
every output. On the CPU an exact detection has two: its face scan walks on to the closest
node's distance and finds that node among its faces' nodes (NODES_IN_FACE_SCAN). The
scans take the slaves in Morton order, so that the threads of a GPU warp walk the same
entries. There is no pair buffer and no planned size that motion can outgrow.
Inside a CUDA graph the master's trees are refitted (the previous order kept, the boxes
recomputed: exact for any motion) while every item stays within the plan's margin of where it
was sorted, and sorted again when one does not (the tree would grow loose): a conditional
node decides on the device.

Many worlds: a world id per slave and per master node enters every key and every comparison;
results per world equal running each world alone. A master without world ids is shared by all
worlds. Computation is in float32 or float64 (the plan's dtype; `_real` says how one source
serves both) in a local frame at the plan's box corner.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np
import warp as wp

from arraycontact._detect import ITERATIONS, KKT_TOL, MODES, SIZE_RTOL, TIE_RTOL
from arraycontact._surface import Surface, bounds, face_bounds, validate_points
from arraycontact._sweep import FEATURE_TOL as SWEPT_FEATURE_TOL
from arraycontact._sweep import SPACE_RTOL as SWEPT_SPACE_RTOL
from arraycontact._sweep import T_TOL as SWEPT_T_TOL
from arraycontact._sweep import capture_pads
from arraycontact_warp import _surface  # one set of its (precision-free) kernels

from . import _grid, _parts, _prepare
from ._closest_node import closest_node, counts
from ._geometry import Element, Quads, Triangles, element_data, quad_data, triangle_data
from ._parts import _concrete, replayed
from ._parts import launch as _slave_launch
from ._projection import (
    Kept,
    Master,
    Nodes,
    NoNodes,
    Slab,
    Unkept,
    finds_nodes,
    first_reach,
    kept_type,
    projected,
    scan_attached,
    scan_faces,
)
from ._real import NP_REAL, precision, real, vec2, vec3
from ._select import classify, proximal, self_face_geometry, self_node_geometry

# Forward only, no loop unrolling (a scan's loops unrolled copy the projection many times into
# the kernel: minutes of CUDA compilation for no speed).
wp.set_module_options({"enable_backward": False, "max_unroll": 1})

GROWTH = 1.25

#: Exact mode (two-body and self-contact), by device (is_cuda): whether the face scan also
#: finds the closest node (from the nodes of the faces its walk meets, which then reaches the
#: closest node's distance where the face scan alone stops at the closest face's) instead of
#: a node tree and a kernel of its own. The same answers. Warp's CPU device, 2^16, steady
#: detections, thread times (.probe/suite_stages.py): uniform node 12.2 + face 31.7 -> 37.0
#: ms, steep 11.1 + 19.4 -> 22.6, graded_1000 16.0 + 55.5 -> 63.3; self-contact wall times
#: (.probe/self_stages.py) spiral 71.8 -> 57.1 ms, two bodies 53.0 -> 39.3; and the plan and
#: a first call build no node tree. An H100, 2^20 (benchmarks/gpu_stages.py): the one walk
#: 1.59 ms against 0.92 + 0.31 ms uniform, 3.10 against 1.75 + 0.51 graded_1000, 5.33 against
#: 3.60 + 0.34 quad4; self-contact at 2^17, spiral 2.36 against 1.83 + 0.19 (its extra state
#: and branches cost a latency-bound scan more than a second, simpler scan does).
NODES_IN_FACE_SCAN = {False: True, True: False}


#: A GPU's threads a block for every kernel of this module. Warp builds a module once for each
#: block size its launches ask (a cold kernel cache compiled this module twice, 48 s each on an
#: H100's host for float64 quad4, when the scans ran in blocks of 128 and the rest of 256).
#: 128 for the scans (H100, 2^20, against 256: uniform face scan 0.98 -> 0.92 ms and closest
#: node 0.34 -> 0.32, steep 0.44 -> 0.39 and 0.29 -> 0.26, graded_1000 1.85 -> 1.75 and 0.88
#: -> 0.82; quad4 alike; 64 and 32 no better): a block frees its SM's room when its slowest
#: warp ends.
BLOCK = 128


@wp.func
def _own(kind: _grid.Plain, own_nodes: wp.array(dtype=int), normals: wp.array(dtype=vec3), i: int):
    """What a scan of slave i needs of self-contact: nothing (Plain), or (Own) its node and
    normal."""
    return kind


@wp.func
def _own(  # noqa: F811 (a Warp overload)
    kind: _grid.Own, own_nodes: wp.array(dtype=int), normals: wp.array(dtype=vec3), i: int
):
    o = _grid.Own()
    o.node = own_nodes[i]
    o.normal = normals[o.node]
    return o


@wp.func
def _bound(
    m: Master,
    s: vec3,
    w: int,
    shared: int,
    o: Any,
    normals: wp.array(dtype=vec3),
    h: int,
    tie: real,
):
    """The distance from s to node h (the plan's last answer for this slave) plus the tie
    band, where that node still counts for the slave (a node of some face, of its world;
    self-contact: another node, obtuse): the closest node is no farther. Else 3e38. Any h is
    checked (a caller may have written into the returned outputs)."""
    bound = real(3.0e38)
    if h >= 0 and h < m.points.shape[0]:
        ok = m.nf_offsets[h + 1] > m.nf_offsets[h]  # a node of some face: in the tree
        if ok and shared == 0:
            ok = m.node_world[h] == w
        if ok:
            ok = counts(o, normals, h)
        if ok:
            bound = wp.sqrt(wp.length_sq(m.points[h] - s)) + tie
    return bound


# 64 registers a thread (H100, `gpu_stages.py`, the node kernel: 2^20 uniform / graded_1000 /
# steep / dmax_10 0.31 / 0.51 / 0.25 / 0.42 ms uncapped, 0.24 / 0.40 / 0.21 / 0.32 at 64,
# 0.27 / 0.45 at 96, 0.30 / 0.48 at 48; self-contact 2^17 spiral 0.185 -> 0.151 ms).
@wp.kernel(cuda_max_registers=64)
def _node_kernel(
    node_grid: _grid.Grid,
    m: Master,
    slaves: wp.array(dtype=vec3),
    order: wp.array(dtype=int),
    slave_world: wp.array(dtype=int),
    shared: int,
    origin: vec3,
    d_max: real,
    tie: real,
    kind: Any,
    own_nodes: wp.array(dtype=int),
    normals: wp.array(dtype=vec3),
    node_out: wp.array(dtype=int),
    dist: wp.array(dtype=real),
):
    """Stage 3 (node mode; exact mode unless NODES_IN_FACE_SCAN has the face scan find it):
    each slave's closest node and its distance (into `dist`). Self-contact (a
    node grid with normals): slave i is node own_nodes[i], of normal normals[that node].
    node_out[i] holds the plan's last answer for slave i when the scan starts: the scan
    starts from its `_bound` instead of d_max (CPU, 2^16, steady detections: the scan's
    thread time 12.2 -> 11.4 ms uniform, 20.5 -> 15.7 graded_1000, 19.4 -> 13.8 with d_max
    10x)."""
    i = order[wp.tid()]
    w = slave_world[i]
    if shared == 1:
        w = 0
    o = _own(kind, own_nodes, normals, i)
    s = slaves[i] - origin
    bound = _bound(m, s, w, shared, o, normals, node_out[i], tie)
    node, dn = closest_node(s, w, shared, node_grid, d_max, tie, o, normals, bound)
    node_out[i] = node
    dist[i] = dn


# Three kernels rather than one: the face scan alone spills fewer registers. 96 registers a
# thread (face kernel at 2^20 on an H100, benchmarks/gpu_stages.py, uniform: 64: 3.18 ms, 80:
# 1.99, 96: 1.49, 128: 1.47, no cap: 2.36 ms; since quad4's kernels of their own, uniform /
# quad4 / graded_1000: 80: 0.95 / 2.81 / 1.79 ms, 96: 0.82 / 2.82 / 1.56, 112: 0.91 / 2.99 /
# 1.72, 128: 0.85 / 2.85 / 1.61, 168: 0.96 / 3.05, no cap: 0.99 / 3.55).
@wp.kernel(cuda_max_registers=96)
def _face_kernel(
    el: Any,
    m: Master,
    face_grid: _grid.Grid,
    slaves: wp.array(dtype=vec3),
    order: wp.array(dtype=int),
    slave_world: wp.array(dtype=int),
    shared: int,
    origin: vec3,
    d_max: real,
    tie: real,
    slack: real,
    iterations: int,
    tol: real,
    kind: Any,
    own_nodes: wp.array(dtype=int),
    normals: wp.array(dtype=vec3),
    nodes: wp.array(dtype=int),
    nlo: wp.array(dtype=vec3),
    nhi: wp.array(dtype=vec3),
    slab: wp.array(dtype=Slab),
    kp: Any,
    nt: Any,
    dist: wp.array(dtype=real),
    face_out: wp.array(dtype=int),
    item: wp.array(dtype=int),
):
    """Stage 4, exact mode: the smallest distance (into `dist`), the face of the tie rule
    (into face_out) and its face-grid item. nt: Nodes (NODES_IN_FACE_SCAN): stage 3 in the
    same walk, the closest node (into `nodes`, which holds the plan's last answer when the
    scan starts: the walk starts from its `_bound`); NoNodes: `nodes` and `dist` hold the node
    kernel's closest node and distance. Self-contact: the closest admissible face, within
    d_max (the closest node bounds it only through a face of its own that surely counts,
    `first_reach`)."""
    i = order[wp.tid()]
    s = slaves[i] - origin
    w = slave_world[i]
    if shared == 1:
        w = 0
    o = _own(kind, own_nodes, normals, i)
    n_reach = real(-1.0)
    rho = real(0.0)
    nodes_too = int(0)
    if finds_nodes(nt):
        nodes_too = 1
        h = nodes[i]
        bound = _bound(m, s, w, shared, o, normals, h, tie)
        n_reach = wp.min(d_max, bound)
        if bound > d_max:
            h = int(-1)  # (a node that does not count, or beyond d_max, bounds nothing)
        rho = first_reach(o, el, m, h, n_reach, d_max, nlo, nhi) + slack
    else:
        rho = first_reach(o, el, m, nodes[i], dist[i], d_max, nlo, nhi) + slack
    # The first scan finds the smallest distance and applies the tie rule as it goes; a second
    # (the smallest face id within `tie` of the smallest distance) runs only when the first was
    # unsure; and the smallest node id within `tie` of the closest node's distance only when
    # another node is that near (closest_node's rule). One call site in a loop keeps the
    # generated code small.
    limit = real(-1.0)
    n_limit = real(-1.0)
    track = nodes_too
    dmin = real(3.0e38)
    f = int(-1)
    k = int(-1)
    node = int(-1)
    for scan in range(2):
        if scan == 0 or rho >= real(0.0) or track == 1:
            d, ff, kk, u, n_d, n_2, n_b = scan_faces(
                el, m, face_grid, s, w, shared, rho, tie, limit, slack, iterations, tol, o, kp,
                i, d_max, nt, track, n_reach, n_limit, normals, nlo, nhi, slab,
            )  # fmt: skip
            if scan == 0 or rho >= real(0.0):
                f = ff
                k = kk
            if scan == 0 or track == 1:
                node = n_b
            if scan == 0:
                dmin = d
                limit = dmin + tie
                rho = wp.min(rho, limit + slack)  # the second scan needs only this near
                if not (dmin <= d_max and u == 1):
                    rho = real(-1.0)  # (no face then)
                track = int(0)
                if nodes_too == 1 and n_d <= d_max and n_2 <= n_d + tie:
                    track = int(1)
                    n_limit = n_d + tie
                    n_reach = n_limit
    dist[i] = dmin
    face_out[i] = f
    item[i] = k
    if nodes_too == 1:
        nodes[i] = node


# Self-contact's face scan (the Own overload: the slave's node and normal, the facing tests)
# spills at 128 registers: without a cap it runs 1.46x faster (crumpled sheet, 2^17, H100:
# 96.4 -> 66.1 ms a launch; 160: 70.5 ms). The same function in a module of its own, uncapped.
_self_face_kernel = wp.kernel(
    module="unique", module_options={"enable_backward": False, "max_unroll": 1}
)(_face_kernel.func)


@wp.struct
class Exact:
    """The finish kernel of exact mode: the chosen face's projection. A type, not a flag, so
    that exact mode's kernel holds no code of node mode's search: with both, the finish kernel
    of a quad4 or quadratic master took 3.4x longer to compile (float64, quad4, self-contact,
    sm_90, compile_aot_module on this 2-core host: 16.2 -> 5.3 s)."""

    unused: int


@wp.struct
class NodeSearch:
    """The finish kernel of node mode: the search among the faces around the closest node."""

    unused: int


_EXACT, _NODE_SEARCH = Exact(), NodeSearch()


@wp.func
def _no_answer(f: int):
    """`_answer` of a slave without one (out of range): face f as the scan left it."""
    return f, vec2(0.0), int(-1), int(-1), int(0), vec3(0.0), int(0), int(1)


@wp.func
def _answer(
    md: Exact,
    el: Any,
    m: Master,
    grid: _grid.Grid,
    kp: Any,
    i: int,
    s: vec3,
    node: int,
    own: int,
    f: int,
    d: real,
    k: int,
    d_max: real,
    tie: real,
    iterations: int,
    tol: real,
    passing_by: int,
    h_node: wp.array(dtype=real),
):
    """Slave i's face, xi, feature, local, converged, s - point, active and status: exact
    mode's from the scan's face f at distance d (its face-grid item k)."""
    if d <= d_max:
        xi, feature, local, conv, diff = projected(el, m, grid, kp, i, k, s, f, iterations, tol)
        return f, xi, feature, local, conv, diff, int(1), int(0)
    return _no_answer(f)


@wp.func
def _answer(  # noqa: F811 (a Warp overload)
    md: NodeSearch,
    el: Any,
    m: Master,
    grid: _grid.Grid,
    kp: Any,
    i: int,
    s: vec3,
    node: int,
    own: int,
    f: int,
    d: real,
    k: int,
    d_max: real,
    tie: real,
    iterations: int,
    tol: real,
    passing_by: int,
    h_node: wp.array(dtype=real),
):
    """Node mode's answer from the closest node: the faces attached to it; the closest
    projection landing inside a face, else (a blind spot) the closest of all, each by the tie
    rule (a second pass picks the smallest face id within `tie`). A blind spot at a boundary
    node outside its proximal volume is passing by: reported, not active."""
    if node < 0:
        return _no_answer(int(-1))
    only_face = int(0)
    limit = real(-1.0)
    f = int(-1)
    xi = vec2(0.0)
    feature = int(-1)
    local = int(-1)
    conv = int(0)
    diff = vec3(0.0)
    for scan in range(2):
        d_face, d_any, f, xi, feature, local, conv, diff = scan_attached(
            el, m, grid, s, node, only_face, limit, iterations, tol, own
        )
        if scan == 0:
            limit = d_any + tie
            if d_face < real(3.0e38):
                only_face = 1
                limit = d_face + tie
    active = int(f >= 0)
    status = 1 - active
    if only_face == 0 and active == 1:
        status = 2  # blind spot
        if passing_by == 1 and (m.prev_face[node] >= 0 or m.next_face[node] >= 0):
            if not proximal(el, m, s, node):
                active = 0
                status = 3  # passing by
    if own >= 0 and active == 1:
        # Seed 000 section 3, item 5 (as arraycontact._detect.run_stages).
        h_i = h_node[own]
        h_j = h_node[node]
        coarser = h_i > h_j * real(1.0 + SIZE_RTOL)
        finer = h_i * real(1.0 + SIZE_RTOL) < h_j
        if coarser or (not finer and only_face == 0 and own > node):
            active = 0
            status = 5  # master side
    return f, xi, feature, local, conv, diff, active, status


# 64 registers (79 unbounded): 0.175 -> 0.148 ms at 2^20 on an H100 (40: 0.162, 48: 0.154,
# 56: 0.148, 80: 0.174). The closest-node kernel gains nothing from a cap (55 registers).
@wp.kernel(cuda_max_registers=64)
def _finish_kernel(
    el: Any,
    m: Master,
    face_grid: _grid.Grid,
    slaves: wp.array(dtype=vec3),
    origin: vec3,
    d_max: real,
    tie: real,
    iterations: int,
    tol: real,
    md: Any,
    passing_by: int,
    selfc: int,
    own_nodes: wp.array(dtype=int),
    h_node: wp.array(dtype=real),
    h_face: wp.array(dtype=real),
    dist: wp.array(dtype=real),
    item: wp.array(dtype=int),
    kp: Any,
    first: int,
    finer_out: wp.array(dtype=wp.int32),
    active_out: wp.array(dtype=wp.int32),
    face_out: wp.array(dtype=int),
    xi_out: wp.array(dtype=vec2),
    point_out: wp.array(dtype=vec3),
    gap_out: wp.array(dtype=real),
    dist_out: wp.array(dtype=real),
    normal_out: wp.array(dtype=vec3),
    feature_out: wp.array(dtype=int),
    node_out: wp.array(dtype=int),
    status_out: wp.array(dtype=int),
    local_out: wp.array(dtype=int),
):
    """The chosen face's projection (exact mode) or the node-mode search on the faces around
    the closest node (md: Exact or NodeSearch, `_answer`), then stage 5 and every output.
    Slaves in their own order, so that the outputs are written in whole cache lines.
    Self-contact (selfc = 1): the faces of the slave's node drop out of node mode, whose pair
    goes to the finer side (MASTER_SIDE), and `finer_out` is written. Thread t takes slave
    first + t."""
    i = first + wp.tid()
    s = slaves[i] - origin
    node = node_out[i]
    own = int(-1)
    if selfc == 1:
        own = own_nodes[i]
    f, xi, feature, local, conv, diff, active, status = _answer(
        md, el, m, face_grid, kp, i, s, node, own, face_out[i], dist[i], item[i], d_max, tie,
        iterations, tol, passing_by, h_node,
    )  # fmt: skip
    nan = real(wp.nan)
    if own >= 0:
        finer_out[i] = 0
        if active == 1:
            finer_out[i] = int(h_node[own] <= h_face[f] * real(1.0 + SIZE_RTOL))
    if active == 1 or status == 3:
        gap, distance, normal = classify(el, m, f, feature, local, xi, diff, tie)
        active_out[i] = active
        face_out[i] = f
        xi_out[i] = xi
        point_out[i] = s - diff + origin
        gap_out[i] = gap
        dist_out[i] = distance
        normal_out[i] = normal
        feature_out[i] = feature
        local_out[i] = local
        status_out[i] = status
        if active == 1 and conv == 0:
            status_out[i] = 4
    else:
        active_out[i] = 0
        face_out[i] = -1
        xi_out[i] = vec2(nan, nan)
        point_out[i] = vec3(nan, nan, nan)
        gap_out[i] = nan
        dist_out[i] = nan
        normal_out[i] = vec3(nan, nan, nan)
        feature_out[i] = -1
        local_out[i] = -1
        status_out[i] = status
        if status != 5:
            status_out[i] = 1


OUTPUTS = (
    ("active", wp.int32),
    ("face", int),
    ("xi", vec2),
    ("point", vec3),
    ("gap", real),
    ("distance", real),
    ("normal", vec3),
    ("feature", int),
    ("master_node", int),
    ("status", int),
    ("local", int),
)


class Constants(NamedTuple):
    """A plan's scalars, host floats handed to the kernels in the plan's precision."""

    d_max: float  # the search distance
    tie: float  # equal distances within this are ties
    slack: float  # rounding slack of the pruning tests (never of the answer)
    tol: float  # KKT tolerance of the projections, natural coordinates
    iterations: int  # the projections' Newton budget (0 on tri3: closed form)
    lebesgue: float  # the element's Lebesgue constant (face boxes from node boxes)
    quantum: float  # the Morton order's cell: a 1024th of the scene's box


class SweptConstants(NamedTuple):
    """A swept plan's scalars (arraycontact._sweep's tolerances in the plan's precision)."""

    pad_rel: float  # capture boxes and segments grow by pad_rel x their size (capture_pads)
    pad_abs: float  # and capture boxes by pad_abs (the tests' rounding in the plan's frame)
    t_tol: float  # time resolution, relative to the step
    space_rtol: float  # a box within space_rtol * scale of 0 is a contact
    feature_tol: float  # natural coordinates this close to a constraint: edge or vertex
    lebesgue: float  # the element's Lebesgue constant


@dataclass(eq=False)
class Plan:
    """Every buffer of a Warp detection (see `plan`)."""

    device: object
    master: Surface
    n_slaves: int
    element: Element
    kernel_element: object  # the detection kernels' element type (`_element_structs`)
    m: Master
    node_grid: _grid.Grid
    face_grid: _grid.Grid
    node_layout: _grid.Layout  # the trees' allocations
    face_layout: _grid.Layout
    node_ids: wp.array  # the master's used nodes
    n_nodes: int
    slave_world: wp.array
    shared: int
    origin: np.ndarray
    constants: Constants
    slave_in: wp.array
    master_in: wp.array
    rebuild: wp.array  # int32 [1]: the last refit found the trees' order stale and rebuilt
    world_bits: int  # the key bits above the Morton code that hold the world id
    out: dict
    dtype: np.dtype  # what the kernels compute in
    order: wp.array  # [2 n]: the slaves in the order the threads take them (Morton or identity)
    order_keys: wp.array  # [2 n] Morton keys (radix sort scratch), None when not sorting
    dist: wp.array  # [n] between kernels: the closest node's distance, then the face's
    item: wp.array  # [n] between kernels: the chosen face's item in the face grid
    mode: int = 0  # 0 exact, 1 node
    # Exact mode where NODES_IN_FACE_SCAN says: the face scan finds the closest node too,
    # and there is no node tree.
    nodes_too: int = 0
    passing_by: int = 0  # node mode on an open master: the boundary test of eqs. (12)-(13)
    # Self-contact (the slaves are the master's nodes): each slave's node, every node's
    # normal and mesh size, every face's normal box and size (recomputed with the master).
    self_contact: int = 0
    own_nodes: wp.array = None
    normals: wp.array = None
    h_node: wp.array = None
    face_nlo: wp.array = None
    face_nhi: wp.array = None
    face_slab: wp.array = None  # each face's Slab (self-contact's scan)
    h_face: wp.array = None
    finer: wp.array = None  # [n] int32: the `finer` output (self-contact)
    kept: Kept = None  # [n] between kernels: the chosen face's projection by the face scan
    # (or an Unkept: none)
    master_ready: bool = False  # the master stages have run at least once
    built: bool = False  # the trees hold a master (the plan's or a detect's): a refit may do
    graphs: bool = True  # CUDA: replay repeated calls on the same buffers as a graph
    refit: bool = True  # refit the master's grids where the device can choose (see `plan`)
    # CUDA: the captured graphs by the inputs they were captured for (the latest GRAPHS), the
    # inputs of the latest calls, and the trees' conditional rebuild as a graph of its own.
    graph_of: dict = field(default_factory=dict)
    seen: dict = field(default_factory=dict)  # (ordered sets)
    dropped: dict = field(default_factory=dict)
    build_graph: object = None
    # CUDA, exact mode with a node tree: a stream where a graph refits the node tree and runs
    # the closest-node scan beside the face tree's refit (`_master_stages`), and that refit's
    # own stale flag.
    side: object = None
    rebuild_nodes: wp.array = None
    cmds: dict = field(default_factory=dict)  # the per-slave kernels' recorded launches
    cuts: dict = field(default_factory=dict)  # CPU: their parts' balanced cuts (_parts.launch)


#: Graphs a plan keeps, one per set of input buffers (double-buffered inputs alternate).
GRAPHS = 4
#: The side stream's priority: high (-1), its closest-node scan being what the face scan waits
#: for (default priority: the same within noise).
SIDE_PRIORITY = -1


def _worlds(world, n, what):
    if world is None:
        return np.zeros(n, np.int32)
    w = np.asarray(world)
    if w.shape != (n,) or w.dtype.kind not in "iu":
        raise ValueError(
            f"{what} must be an integer array of shape ({n},), got {w.dtype} {w.shape}"
        )
    if len(w) and w.min() < 0:
        raise ValueError(f"{what} row {int(np.argmin(w))} is negative")
    return w.astype(np.int32)


def plan(
    master: Surface,
    slave_points,
    *,
    slave_world=None,
    master_world=None,
    d_max=None,
    device=None,
    growth=GROWTH,
    dtype="float32",
    sort_slaves="plan",
    mode="exact",
    graphs=True,
    refit=True,
    self_contact=False,
    frame=None,
    box=None,
) -> Plan:
    """Allocate a detection of slaves [n, 3] against `master` computing in dtype (float32 or
    float64). mode: "exact" or "node" (seed 000: the faces attached to the closest node, blind
    spots, passing-by nodes on an open master's boundary), as arraycontact.detect.

    slave_world [n] and master_world [n_points]: world ids (non-negative ints). Without
    master_world the master is shared by all worlds. d_max: default the longest master edge.
    growth: how far an item may move before a refit sorts the trees again: (growth - 1)
    times a small face's radius (the tenth percentile at plan time).
    sort_slaves: the order the threads take the slaves in, so that the threads of a GPU warp
    take neighbouring slaves and walk the same tree entries (results are the same in any order):
    "plan" (default), the Morton order of slave_points, once (the slaves of a body keep their
    neighbours as it moves and deforms); "detect" (or True), each detect sorts them again
    first (slaves that mix, like particles: about 0.08 ms at 2^20 on an H100); False, the
    order they are numbered in.
    graphs: on CUDA, a detect called again with input buffers it has seen (wp.array or NumPy
    staged into the plan's own) replays their launches as a CUDA graph, captured then (one a
    set of buffers, the latest GRAPHS: double-buffered inputs alternate): the same kernels
    without Python's launch overhead. A call on buffers new to it launches one by one, the
    trees' rebuild decided on the device by a graph of its own. False: launches one by one,
    and a GPU sorts the trees in every call after the first.
    refit: where the device can choose without the host (with conditional graph nodes, CUDA
    12.4+: in a CUDA graph, detect's own or the caller's, or outside one through the plan's
    graph of the rebuild alone; on the CPU), the master's trees keep their
    order (their boxes recomputed: exact for any motion) while every face centre and node
    stays within that margin of where it was sorted, and are sorted again when one does not;
    `rebuild[0]` says which the last call did. The results are the same either way; a refit
    skips the keys and the sorts. False: sorts in every call. In a graph (a GPU, exact mode)
    the node tree's refit and the closest-node scan run on a stream of the plan's own
    (`Plan.side`), forked from the capturing stream and joined back before detect returns,
    and a stale node tree is sorted again after its scan.
    self_contact: the slaves are the master's own nodes, slave_points = the master's points
    at master.nodes (use `plan_self` / `detect_self`).
    frame: the origin of the local frame the kernels compute in (default: the corner of the
    slaves' box less d_max). Plans of the parts of one scene take the whole scene's, so that
    float32 rounds alike in every part and the parts answer as one plan would.
    box: (lo, hi), the box the Morton cells (trees, slave order) and the rounding slack are
    sized over (default: the slaves' and the master's, widened by d_max); points outside it
    take its border cells. Parts of one scene take the whole scene's, so that their items
    have one plan's keys (a part's padding far off would otherwise coarsen them)."""
    here = precision(dtype)
    if here.real is not real:
        return here.plan(
            master,
            slave_points,
            slave_world=slave_world,
            master_world=master_world,
            d_max=d_max,
            device=device,
            growth=growth,
            dtype=dtype,
            sort_slaves=sort_slaves,
            mode=mode,
            graphs=graphs,
            refit=refit,
            self_contact=self_contact,
            frame=frame,
            box=box,
        )
    if not isinstance(master, Surface):
        raise ValueError("master must be an arraycontact.Surface")
    if mode not in MODES:
        raise ValueError(f"mode must be one of {MODES}, got {mode!r}")
    if master.n_faces == 0:
        raise ValueError("master has no faces")
    if not growth >= 1:
        raise ValueError(f"growth must be >= 1, got {growth}")
    sort_slaves = {True: "detect", None: False}.get(sort_slaves, sort_slaves)
    if sort_slaves not in ("plan", "detect", False):
        raise ValueError(f"sort_slaves must be 'plan', 'detect' or False, got {sort_slaves!r}")
    device = wp.get_device(device)
    _preload(device, master.element.name, bool(self_contact), mode == "exact")
    # The slaves on the device in float64, checked and bounded there.
    xd, x_lo, x_hi = _surface.device_points(slave_points, "slave_points", device)
    n = xd.shape[0]
    if n == 0:
        raise ValueError("slave_points is empty: there is nothing to plan for")
    if slave_world is None:
        slave_world = wp.zeros(n, dtype=int, device=device)
    else:
        slave_world = wp.array(_worlds(slave_world, n, "slave_world"), dtype=int, device=device)
    shared = master_world is None
    if not shared:
        nw = _worlds(master_world, len(master.points), "master_world")
        fw = nw[master.faces[:, 0]]
        bad = (nw[master.faces] != fw[:, None]).any(1)
        if bad.any():
            r = int(np.argmax(bad))
            raise ValueError(
                f"master face {r} has nodes of different worlds: {nw[master.faces[r]]}"
            )
    topo = _surface.topology(master, device)
    if self_contact and n != topo.n_nodes:
        raise ValueError(
            f"self-contact: slave_points must be the master's {topo.n_nodes} used nodes"
        )
    if d_max is None:
        d_max = topo.longest_edge
    if not (np.isscalar(d_max) and np.isfinite(d_max) and d_max > 0):
        raise ValueError(f"d_max must be a positive finite number, got {d_max}")
    e = master.element
    r_max = topo.r_max
    lo = np.minimum(x_lo, topo.node_box[0]) - d_max
    hi = np.maximum(x_hi, topo.node_box[1]) + d_max
    if box is not None:
        b = np.asarray(box, np.float64)
        if b.shape != (2, 3) or not np.isfinite(b).all() or not (b[1] > b[0]).all():
            raise ValueError(f"box must be two finite points (lo, hi) with lo < hi, got {box!r}")
        lo, hi = b
    extent = 2 * float((hi - lo).max())
    # The local frame at the slaves' box (less d_max): float32 keeps its precision where the
    # contacts are, however large the master is around them (a fine patch in a coarse plate).
    origin = x_lo - d_max
    if frame is not None:
        origin = np.asarray(frame, np.float64)
        if origin.shape != (3,) or not np.isfinite(origin).all():
            raise ValueError(f"frame must be a finite point [3], got {frame!r}")
    eps = float(np.finfo(NP_REAL).eps)
    tie = TIE_RTOL[NP_REAL] * topo.longest_edge
    consts = Constants(
        d_max=float(d_max),
        tie=tie,
        slack=tie + 16 * eps * (extent + d_max + r_max),
        tol=KKT_TOL[NP_REAL],
        iterations=ITERATIONS.get(e.name, 0),
        lebesgue=float(e.lebesgue),
        quantum=float((hi - lo).max()) / 1024,
    )

    def arr(a, dtype):
        return wp.array(a, dtype=dtype, device=device)

    m = Master()
    m.points = wp.zeros(len(master.points), dtype=vec3, device=device)
    m.faces = topo.faces
    if shared:
        m.face_world = wp.zeros(master.n_faces, dtype=int, device=device)
        m.node_world = wp.zeros(len(master.points), dtype=int, device=device)
    else:
        m.face_world, m.node_world = arr(fw, int), arr(nw, int)
    m.nf_offsets, m.nf_ids = topo.nf_offsets, topo.nf_ids
    m.face_edges, m.edge_faces = topo.face_edges, topo.edge_faces
    m.prev_node, m.next_node = topo.prev_node, topo.next_node
    m.prev_face, m.next_face = topo.prev_face, topo.next_face
    out = {k: wp.zeros(n, dtype=t, device=device) for k, t in OUTPUTS}
    element, kernel_element = _element_structs(e.name, device)
    # Morton keys over the plan's box in the local frame; worlds above them in the key.
    margin = (growth - 1) * topo.r_small
    n_worlds = 1 if shared else int(nw.max()) + 1
    box = (lo - origin, float((hi - lo).max()), device, margin, n_worlds)
    nodes_too = mode == "exact" and NODES_IN_FACE_SCAN[device.is_cuda]
    n_tree = 0 if nodes_too else topo.n_nodes
    node_grid, world_bits = _grid.new_grid(n_tree, *box, normals=self_contact)
    # Self-contact: the face tree sorts each cell of 4 d_max by the faces' normal classes
    # (_grid._side_key; a thin solid's two sides, one element apart, then share no leaf), so
    # that normal boxes drop a slave's own side above the leaves. The face scan's time, quad4
    # at 2^16 on Warp's CPU device (thread time) and 2^17 on an H100, cells alone -> 4 d_max:
    # spiral 86 -> 78 ms and 1.82 -> 1.64 ms, coil 104 -> 94 and 2.01 -> 1.90, two bodies
    # 52-54 -> 45-46 and 1.16 -> 1.08, folded sheet 61-63 -> 57-59 and 2.02 -> 1.92, the
    # crumpled sheet (steep folds: classes in patches) 132 -> 135 and 4.36 -> 4.37. 8 d_max
    # and more: the crumpled sheet 6-12 % slower on the H100.
    sides = 4 * d_max if self_contact else 0.0
    face_grid, _ = _grid.new_grid(master.n_faces, *box, normals=self_contact, sides=sides)
    tri3 = e.name == "tri3"
    # On a GPU the trees are sized by how the master at plan time groups (_grid.measure: room
    # for 1.25x its groups) and built from it, so that a first detect refits them; on the
    # CPU, where the sorts and the grouping are a one-shot call's largest set-up cost, the
    # first detect builds them in room for groups of W / 2 on average (_grid.layout).
    built = device.is_cuda and not self_contact  # (self-contact's normal boxes: detect's)
    node_means, face_means = (), ()
    o64 = wp.vec3d(*[float(v) for v in origin])
    if built:
        n_pts = len(master.points)
        wp.launch(
            _prepare.localise64, n_pts, inputs=[topo.points, o64], outputs=[m.points], device=device
        )
        if n_tree:
            node_means = _grid.measure_nodes(
                node_grid, m.points, topo.nodes, m.node_world, n_tree, device, world_bits
            )
        if mode == "exact":  # node mode reads no face grid
            face_means = _grid.measure_faces(
                face_grid, m.points, m.faces, e.lebesgue, m.face_world, device, world_bits
            )
    node_layout = _grid.allot(node_grid, n_tree, device, node_means)
    face_layout = _grid.allot(face_grid, master.n_faces, device, face_means, corners=tri3)
    if built:  # the keys are sorted: the rest of a build
        rebuild = wp.zeros(1, dtype=wp.int32, device=device)
        if n_tree:
            _grid.place(node_grid, node_layout, m.points, m.node_world, n_tree, device, rebuild)
        if mode == "exact":
            args = (m.points, m.faces, e.lebesgue, m.face_world, device, tri3, rebuild)
            _grid.place_faces(face_grid, face_layout, *args)
    p = Plan(
        device=device,
        master=master,
        n_slaves=n,
        element=element,
        kernel_element=kernel_element,
        m=m,
        node_grid=node_grid,
        face_grid=face_grid,
        node_layout=node_layout,
        face_layout=face_layout,
        world_bits=world_bits,
        node_ids=topo.nodes,
        n_nodes=topo.n_nodes,
        slave_world=slave_world,
        shared=int(shared),
        origin=origin,
        constants=consts,
        slave_in=wp.zeros(n, dtype=vec3, device=device),
        master_in=wp.zeros(len(master.points), dtype=vec3, device=device),
        rebuild=wp.zeros(1, dtype=wp.int32, device=device),
        built=built,
        out=out,
        dtype=NP_REAL,
        order=_surface.iota(n, 2 * n, device),  # [n:]: the radix sort's scratch
        order_keys=wp.zeros(2 * n, dtype=int, device=device) if sort_slaves == "detect" else None,
        dist=wp.zeros(n, dtype=real, device=device),
        item=wp.zeros(n, dtype=int, device=device),
        mode=MODES.index(mode),
        nodes_too=int(nodes_too),
        passing_by=int(mode == "node" and not topo.closed),
        graphs=bool(graphs),
        refit=bool(refit),
    )
    n_self = n if self_contact else 1
    n_pts = len(master.points) if self_contact else 1
    n_faces = master.n_faces if self_contact else 1
    p.self_contact = int(bool(self_contact))
    p.own_nodes = topo.nodes if self_contact else wp.zeros(1, int)
    p.normals = wp.zeros(n_pts, dtype=vec3, device=device)
    p.h_node = wp.zeros(n_pts, dtype=real, device=device)
    p.face_nlo = wp.zeros(n_faces, dtype=vec3, device=device)
    p.face_nhi = wp.zeros(n_faces, dtype=vec3, device=device)
    p.face_slab = wp.zeros(n_faces, dtype=Slab, device=device)
    p.h_face = wp.zeros(n_faces, dtype=real, device=device)
    p.finer = wp.zeros(n_self, dtype=wp.int32, device=device)
    kept = kept_type(_kernel_type(e.name), wp.get_device(device).is_cuda) is Kept
    p.kept = Kept() if kept else Unkept()
    p.kept.item = wp.full(n if kept else 1, -1, dtype=int, device=device)
    if kept:
        p.kept.xi = wp.zeros(n, dtype=vec2, device=device)
        p.kept.tag = wp.zeros(n, dtype=int, device=device)
    if self_contact:
        out["finer"] = p.finer
    if wp.get_device(device).is_cuda and mode == "exact" and not nodes_too:
        p.side = wp.Stream(device, priority=SIDE_PRIORITY)
        p.rebuild_nodes = wp.zeros(1, dtype=wp.int32, device=device)
    _declare(p)
    if sort_slaves == "plan":  # the per-call sort, run once on the plan's points
        wp.launch(_prepare.localise64, n, inputs=[xd, o64], outputs=[p.slave_in], device=device)
        _grid.spatial_order(
            p.slave_in,
            vec3(0.0, 0.0, 0.0),
            real(consts.quantum),
            wp.empty(2 * n, dtype=int, device=device),
            p.order,
            n,
            device,
        )
    _slave_stages(p, p.slave_in, vec3(0.0, 0.0, 0.0), record_only=True)
    if built and refit:
        _record_master_stages(p)
    return p


_ELEMENTS = {}


#: The struct types a plan's detection kernels specialise on, with their data: Triangles for
#: tri3 (closed form), Quads for quad4 (no curved-face code); other elements the Element.
_SPECIALISED = {"tri3": (Triangles, triangle_data), "quad4": (Quads, quad_data)}


def _kernel_type(name: str):
    """The struct type a plan's detection kernels specialise on (`_SPECIALISED`)."""
    return _SPECIALISED.get(name, (Element, None))[0]


def _element_structs(name: str, device):
    """The element's structs for a plan's kernels, the Element and its `_kernel_type`'s, made
    once a device: their arrays are constants no kernel writes (building them took 0.5 ms of
    a 15 ms plan on the CPU)."""
    key = (name, device.alias)
    if key not in _ELEMENTS:
        el = element_data(name, device)
        data = _SPECIALISED.get(name, (Element, None))[1]
        _ELEMENTS[key] = (el, data(device) if data else el)
    return _ELEMENTS[key]


def _declare(p: Plan):
    """Adds the overloads of the scan kernels that the plan's detections launch before the
    first launch. Warp rebuilds a module whenever a launch adds an overload, so a first detect
    compiled this module three times, the scans again each time (cold kernel cache, quad4,
    CPU: first call 10.5 -> 7.9 s; tri3 8.6 -> 6.9 s). Now it compiles once."""
    cuda = wp.get_device(p.device).is_cuda
    el = _kernel_type(p.master.element.name)
    _declare_kernels(el, bool(p.self_contact), p.mode == 0, cuda)


_DECLARED = set()
_PRELOADED = set()


def _preload(device, name: str, self_contact: bool, exact: bool):
    """On a GPU, a plan's kernel overloads declared and its Warp modules compiled at once, one
    thread a module, once a process: else each compiles when a launch first needs it, one
    after the other (H100, an empty kernel cache, float64, `benchmarks/warp_first_call.py`,
    two runs: quad4 self-contact 13.5 / 15.5 -> 9.6 / 9.6 s, tri3 two bodies 6.3 / 6.6 -> 4.5 /
    5.2 s). Not on the CPU, where Warp's compilations do not overlap (tri3 two bodies 4.0 ->
    4.5 s, quad4 self-contact 9.1 -> 7.1 s)."""
    key = (device.alias, name, self_contact, exact)
    if not device.is_cuda or key in _PRELOADED:
        return
    _declare_kernels(_kernel_type(name), self_contact, exact, True)
    kernels = [(_surface._box, None), (_prepare.localise64, None), (_grid._keys, None)]
    kernels.append((_face_kernel, BLOCK))  # (the detection module's block size)
    if self_contact:
        kernels += [(_self_face_kernel, None), (self_face_geometry, None)]
    _parts.load_at_once(device, kernels)
    _PRELOADED.add(key)


def _declare_kernels(el, self_contact: bool, exact: bool, cuda: bool, nodes_too=None):
    kind = _grid.Own if self_contact else _grid.Plain
    kp = kept_type(el, cuda)
    if nodes_too is None:
        nodes_too = NODES_IN_FACE_SCAN[cuda]
    nodes_too = nodes_too and exact
    key = (el, self_contact, exact, cuda, nodes_too)
    if key in _DECLARED:  # (each plan declared them again: 0.6 ms of a 15 ms CPU plan)
        return
    _DECLARED.add(key)
    if not nodes_too:
        wp.overload(_node_kernel, {"kind": kind})
    if exact:
        face_kernel = _self_face_kernel if self_contact else _face_kernel
        nt = Nodes if nodes_too else NoNodes
        wp.overload(face_kernel, {"el": el, "kind": kind, "kp": kp, "nt": nt})
    wp.overload(_finish_kernel, {"el": el, "kp": kp, "md": Exact if exact else NodeSearch})
    if self_contact:
        wp.overload(self_face_geometry, {"el": el})
        wp.overload(self_node_geometry, {"el": el})


def declare_all(cuda: bool | None = None):
    """Every overload of the generic kernels (both element structs, both scan kinds, both
    modes, swept), before any launch, so that each module compiles once whatever the process
    detects next. For the test suite: its Warp warm-up and its workers call it, so the workers
    load what the warm-up compiled instead of compiling each new mix of overloads again. (A
    plan declares only what its detections launch: on a GPU the scans of an unused element
    type would add their compile time.) cuda: a GPU's overloads (its scans keep no
    projection: kept_type), or the CPU's; None: those of each kind of device present (a GPU
    machine's tests declared the CPU's alone, so every GPU plan added overloads to modules
    that held the CPU's too, and each module was compiled again for each: a cold kernel
    cache's GPU tests did not finish in 10 minutes)."""
    if cuda is None:
        kinds = [False] * wp.is_cpu_available() + [True] * wp.is_cuda_available()
        for c in kinds:
            declare_all(c)
        return
    for el in (Triangles, Quads, Element):
        wp.overload(_swept().swept_scan, {"el": el})
        for self_contact in (False, True):
            _declare_kernels(el, self_contact, False, cuda)  # node mode
            for nodes_too in (False, True):
                _declare_kernels(el, self_contact, True, cuda, nodes_too)


def _kind(a):
    if isinstance(a, wp.array):
        return "warp"
    if type(a).__module__.startswith("jax"):
        return "jax"
    return "numpy"


def _input(p: Plan, a, staging, what, n):
    """A vec3 device array holding `a` and the origin the kernels must subtract from it."""
    kind = _kind(a)
    if kind == "numpy":
        # float64 host data: subtract the origin in float64 before a float32 cast.
        x = validate_points(a, what, copy=False)
        if len(x) != n:
            raise ValueError(f"{what} must have {n} rows (the plan's), got {len(x)}")
        staging.assign((x - p.origin).astype(NP_REAL))
        return staging, vec3(0.0, 0.0, 0.0)
    if kind == "jax":
        a = wp.from_jax(a, dtype=vec3)  # DLPack: no copy on the same device
    if a.dtype != vec3 or a.shape != (n,):
        raise ValueError(
            f"{what} must be a wp.array of {n} {vec3.__name__} (the plan's dtype), "
            f"got {a.dtype} {a.shape}"
        )
    if a.device != p.device:
        raise ValueError(f"{what} is on {a.device}, the plan on {p.device}")
    return a, vec3(*[float(v) for v in p.origin])


def _normal_boxes(p: Plan):
    """Self-contact: the trees' item normal boxes (nodes: their normal; faces: their box)."""
    if not p.self_contact:
        return None, None
    return (p.normals, p.normals), (p.face_nlo, p.face_nhi)


#: The trees' builds and refits whose kernels this process has loaded (see `_both_trees`).
_LOADED = set()


def _build(p: Plan, nodes_too=True, faces_too=True):
    """The master's trees from its localised points (on the CPU the two at once); either
    alone where the other is not asked for."""
    c = p.constants
    dev = p.device
    m = p.m
    node_n, face_n = _normal_boxes(p)

    def nodes():
        args = (m.points, p.node_ids, m.node_world, p.n_nodes, dev, p.rebuild, p.world_bits)
        _grid.build(p.node_grid, p.node_layout, *args, node_n)

    def faces():
        tri3 = p.master.element.name == "tri3"
        args = (m.points, m.faces, c.lebesgue, m.face_world, dev, tri3, p.rebuild)
        _grid.build_faces(p.face_grid, p.face_layout, *args, p.world_bits, face_n)

    if not faces_too:
        nodes()
    elif not nodes_too:
        faces()
    else:
        _both_trees(p, "build", nodes, faces)


def _both_trees(p: Plan, phase: str, nodes, faces):
    """nodes() and faces() (node mode, which reads no face grid: nodes() alone; a plan whose
    face scan finds the closest node, `nodes_too`: faces() alone), each a chain of launches on
    its own tree: on the CPU at once once this phase of this kind of plan has loaded their
    kernels in this process (two threads must not compile a module), else one after the
    other, the nodes' first (a GPU's launches queue on one stream)."""
    chains = ((faces,) if p.nodes_too else (faces, nodes)) if p.mode == 0 else (nodes,)
    kind = (phase, str(p.device), NP_REAL, p.self_contact, p.mode)
    if p.device.is_cpu and kind in _LOADED:
        # (loaded here, not in two threads: another plan's overloads may have made it stale)
        _parts.load(_grid._keys, p.device)
        _parts.concurrently(p.device, *chains)
        return
    for chain in reversed(chains):
        chain()
    _LOADED.add(kind)


def _master_stages(p: Plan, xm, m_origin, beside=None, later=None):
    """The master's stages: its points localised, self-contact's geometry, its trees refitted
    (sorted again where stale) or built. beside(): the slaves' launches up to the closest-node
    scan, run here on the plan's side stream where it takes them (returns whether it did).
    later: a list that takes what is to run after the scans."""
    dev = p.device
    m = p.m
    _localise_master(p, xm, m_origin)
    if p.self_contact:
        _slave_launch(
            self_face_geometry,
            p.master.n_faces,
            [0, p.kernel_element, m],
            [p.face_nlo, p.face_nhi, p.h_face, p.face_slab],
            dev,
            first=0,
        )
        _slave_launch(
            self_node_geometry,
            p.n_nodes,
            [0, p.kernel_element, m, p.own_nodes, p.h_face],
            [p.normals, p.h_node],
            dev,
            first=0,
        )
    # A refit where the device decides without the host: in a CUDA graph (detect's own or the
    # caller's) with conditional nodes, on the CPU, and on a GPU outside a graph through the
    # plan's graph of the conditional rebuild alone, captured once (launched one by one, the
    # sorts and the grouping made a call 3.3-5.1 ms at 2^15 on an H100, against 0.65 ms).
    # (A first call refits the trees a GPU plan built, reading the check on the host; on the
    # CPU, and for self-contact, a first call builds: its trees hold nothing yet.)
    conditional = dev.is_cuda and wp.is_conditional_graph_supported()
    outside = dev.is_cuda and not dev.is_capturing and p.master_ready  # a later call, no graph
    if p.refit and (
        (p.built and (dev.is_cpu or not p.master_ready))
        or (dev.is_capturing and conditional)
        or (outside and p.graphs and conditional)
    ):
        p.rebuild.zero_()

        def nodes(stale=p.rebuild):
            _refit_nodes(p, stale)

        def faces():
            _refit_faces(p)

        if beside is not None and p.side is not None and dev.is_capturing and conditional:
            # In a graph, the node tree's refit and the closest-node scan (latency-bound) run
            # on a stream of their own beside the face tree's refit (bandwidth-bound): both
            # read only the localised points (H100, 2^20: uniform 1.57 -> 1.45-1.50 ms, tyre
            # 0.64 -> 0.55, apart 0.50 -> 0.43). A refitted tree holds its items however far
            # they moved (only its tightness is at stake), so the scan runs on it, and a stale
            # node tree is sorted again after the scan, for the next call.
            p.rebuild_nodes.zero_()
            with wp.ScopedStream(p.side):  # (waits for this stream's launches so far)
                nodes(p.rebuild_nodes)
                beside()
            faces()
            # (joined first: a conditional node cannot be made while a stream is forked)
            wp.get_stream(dev).wait_stream(p.side)
            _rebuild_if(p, lambda: _build(p, nodes_too=False), False)
            wp.capture_if(p.rebuild_nodes, on_true=lambda: _nodes_again(p))
            p.master_ready = p.built = True
            return True
        # (at once on the CPU: self-contact 2^16 1.6-2 ms of 89-120 faster; two bodies: same)
        _both_trees(p, "refit", nodes, faces)
        if dev.is_cuda and not dev.is_capturing and not outside and later is not None:
            # A first call reads the flag on the host: after the scans, which are exact on a
            # refitted tree (only its tightness is at stake), so that the read does not hold
            # their launches back; a stale tree is sorted for the next call. One H200, 2^20,
            # medians of 8 plans: first detect tyre 1.12 -> 1.01 ms, apart 1.00 -> 0.86,
            # ball_block_300 0.75 -> 0.69 (steady 0.54, 0.40, 0.28). (The plan capturing the
            # graph of the rebuild for it instead: plans 5-10 ms longer, first calls no shorter.)
            later.append(lambda: wp.capture_if(p.rebuild, on_true=lambda: _build(p)))
        else:
            _rebuild_if(p, lambda: _build(p), outside)
    else:
        _build(p)
    p.master_ready = p.built = True
    return False


def _localise_master(p: Plan, xm, m_origin, record_only=False):
    args = [xm, m_origin, p.m.points]
    n = len(p.master.points)
    replayed(p.cmds, "master", _prepare.localise, n, args, p.device, record_only)


def _refit_nodes(p: Plan, stale, record_only=False):
    args = (p.m.points, p.m.node_world, p.device, stale, _normal_boxes(p)[0])
    _grid.refit(p.node_grid, p.node_layout, *args, cmds=p.cmds, record_only=record_only)


def _refit_faces(p: Plan, record_only=False):
    m = p.m
    tri3 = p.master.element.name == "tri3"
    face_n = _normal_boxes(p)[1]
    args = (m.points, m.faces, p.constants.lebesgue, m.face_world, p.device, tri3, p.rebuild)
    _grid.refit_faces(p.face_grid, p.face_layout, *args, face_n, p.cmds, record_only)


def _record_master_stages(p: Plan):
    """A GPU plan's first detect refits the trees the plan built: its master stages recorded
    here (as the slave stages are), so that it packs only the arguments that differ (one
    H200, medians of 8 plans: first detect ball_block_100 0.65 -> 0.44 ms, ball_block_300
    0.61 -> 0.46, tyre 0.87 -> 0.77; steady 0.23-0.25, 0.28, 0.53 ms)."""
    _localise_master(p, p.master_in, vec3(0.0, 0.0, 0.0), record_only=True)
    if p.mode != 0 or not p.nodes_too:  # (as _both_trees: a node tree)
        _refit_nodes(p, p.rebuild, record_only=True)
    if p.mode == 0:
        _refit_faces(p, record_only=True)


def _nodes_again(p: Plan):
    """The node tree sorted again after its scan (the side stream's stale flag raised), and
    rebuild[0] raised with it."""
    _build(p, faces_too=False)
    wp.copy(p.rebuild, p.rebuild_nodes)


@wp.kernel
def _gather_rows(x: wp.array(dtype=vec3), rows: wp.array(dtype=int), out: wp.array(dtype=vec3)):
    k = wp.tid()
    out[k] = x[rows[k]]


def _self_kind(p: Plan):
    """The scans' self-contact type (see _grid.Plain)."""
    return _grid.Own() if p.self_contact else _grid.Plain()


def _rebuild_if(p, build, by_graph: bool):
    """`build` (the plan's trees sorted again) where p.rebuild[0] says: a conditional node
    (in a capture; outside one, Warp reads the flag on the host), or by_graph, the plan's
    graph of that node alone, captured once (`build` reads only the plan's own buffers)."""
    if not by_graph:
        wp.capture_if(p.rebuild, on_true=build)
        return
    if p.build_graph is None:
        with wp.ScopedCapture(device=p.device) as cap:
            wp.capture_if(p.rebuild, on_true=build)
        p.build_graph = cap.graph
    wp.capture_launch(p.build_graph)


def _launch(p: Plan, xs, s_origin, master):
    """Every launch of one detection (master: its points and origin, or None). Self-contact:
    the slaves (xs, the plan's staging buffer) are gathered from the master's points."""
    c = p.constants
    dev = p.device

    def slaves():  # up to the closest-node scan
        if master is not None and p.self_contact:
            args = [master[0], p.own_nodes, xs]
            wp.launch(_gather_rows, p.n_slaves, inputs=args, device=dev, block_dim=BLOCK)
        if p.order_keys is not None:
            o = p.order_keys
            _grid.spatial_order(xs, s_origin, real(c.quantum), o, p.order, p.n_slaves, dev)
        _slave_stages(p, xs, s_origin, nodes_too=True, faces_too=False)

    later = []
    if master is None or not _master_stages(p, *master, beside=slaves, later=later):
        slaves()
    _slave_stages(p, xs, s_origin, nodes_too=False)
    for then in later:
        then()


def _slave_stages(p: Plan, xs, s_origin, record_only=False, nodes_too=True, faces_too=True):
    """The three per-slave kernels, each through the plan's recorded command (record_only:
    the plan records them, so that its first detect packs only the arguments that differ);
    the closest-node scan alone (faces_too=False) or the others alone (nodes_too=False)."""
    c = p.constants
    dev = p.device
    o = p.out
    n = p.n_slaves
    rec = dict(cmds=p.cmds, record_only=record_only, cuts=p.cuts)
    # Self-contact's face scan, in a module of its own, one block of 256 an SM at its 255
    # registers, ran 2-5 % slower in blocks of 128 (BLOCK).
    scan = 256 if p.self_contact else BLOCK
    if nodes_too and not p.nodes_too:
        _slave_launch(
            _node_kernel,
            n,
            [
                p.node_grid,
                p.m,
                xs,
                p.order,
                p.slave_world,
                p.shared,
                s_origin,
                real(c.d_max),
                real(c.tie),
                _self_kind(p),
                p.own_nodes,
                p.normals,
            ],
            [o["master_node"], p.dist],
            dev,
            order=3,
            block=BLOCK,
            **rec,
        )
    if not faces_too:
        return
    if p.mode == 0:
        _slave_launch(
            _self_face_kernel if p.self_contact else _face_kernel,
            n,
            [
                p.kernel_element,
                p.m,
                p.face_grid,
                xs,
                p.order,
                p.slave_world,
                p.shared,
                s_origin,
                real(c.d_max),
                real(c.tie),
                real(c.slack),
                c.iterations,
                real(c.tol),
                _self_kind(p),
                p.own_nodes,
                p.normals,
                o["master_node"],
                p.face_nlo,
                p.face_nhi,
                p.face_slab,
                p.kept,
                Nodes() if p.nodes_too else NoNodes(),
            ],
            [p.dist, o["face"], p.item],
            dev,
            order=4,
            block=scan,
            **rec,
        )
    _slave_launch(
        _finish_kernel,
        n,
        [
            p.kernel_element,
            p.m,
            p.face_grid,
            xs,
            s_origin,
            real(c.d_max),
            real(c.tie),
            c.iterations,
            real(c.tol),
            _EXACT if p.mode == 0 else _NODE_SEARCH,
            p.passing_by,
            p.self_contact,
            p.own_nodes,
            p.h_node,
            p.h_face,
            p.dist,
            p.item,
            p.kept,
            0,
        ],
        [p.finer] + [o[k] for k, _ in OUTPUTS],
        dev,
        first=18,
        block=BLOCK,
        **rec,
    )


def detect(p: Plan, slave_points, master_points=None):
    """Launch the detection. Inputs: wp.array of wp.vec3 on the plan's device (used in place:
    capturable), JAX arrays (DLPack) or NumPy [n, 3]. Returns a dict of output arrays of the
    slaves' kind (the plan's own buffers for wp.array input, overwritten by the next call):
    active, face, xi, point, gap, distance, normal, feature, master_node, status, local (the
    edge or corner of an edge or vertex feature, else -1).
    master_points=None reuses the master's geometry and grids of the previous call (a master
    that does not move: only the slave kernel runs)."""
    if not isinstance(p, Plan):
        # A plan of the other precision: its own module's detect.
        if not hasattr(p, "dtype"):
            raise ValueError(f"p must be a Plan from arraycontact_warp.plan, got {type(p)}")
        return precision(p.dtype).detect(p, slave_points, master_points)
    if p.self_contact:
        if slave_points is not None or master_points is None:
            raise ValueError("a self-contact plan detects with detect_self(plan, points)")
        master = _input(p, master_points, p.master_in, "points", len(p.master.points))
        xs, s_origin = p.slave_in, master[1]
        slave_points = master_points
    else:
        xs, s_origin = _input(p, slave_points, p.slave_in, "slave_points", p.n_slaves)
    master = master if p.self_contact else None
    if master_points is None:
        # A master that does not move keeps its geometry and grids from the last call.
        if not p.master_ready:
            raise ValueError("master_points=None needs a previous detect with the master")
    elif master is None:
        master = _input(p, master_points, p.master_in, "master_points", len(p.master.points))
    dev = p.device
    if dev.is_cuda and p.graphs and not dev.is_capturing:
        # Called again on the same buffers: the launches as one CUDA graph, captured on the
        # second such call and replayed from then on (no Python launch overhead). A caller
        # capturing detect in a graph of its own gets the launches themselves.
        key = (
            xs.ptr,
            tuple(float(v) for v in s_origin),
            None if master is None else (master[0].ptr, tuple(float(v) for v in master[1])),
        )
        action = _graph_action(p, key)
        if action == "capture":
            with wp.ScopedCapture(device=dev) as cap:
                _launch(p, xs, s_origin, master)
            _keep_graph(p, key, cap.graph)
        if action == "launch":
            _launch(p, xs, s_origin, master)
        else:
            wp.capture_launch(p.graph_of[key])
    else:
        _launch(p, xs, s_origin, master)
    return _outputs(p.out, slave_points, p.origin)


def _graph_action(p: Plan, key) -> str:
    """What a CUDA detect does with the input buffers `key`: "replay" their graph, "capture"
    one (buffers seen in one of the latest calls), or "launch" one by one. At most GRAPHS
    graphs, the oldest dropped; buffers whose graph was dropped are not captured again (inputs
    rotating over more sets than that would capture on every call)."""
    if key in p.graph_of:
        action = "replay"
    elif key in p.seen and key not in p.dropped:
        action = "capture"
    else:
        action = "launch"
    _book(p.seen, key, 2 * GRAPHS)
    return action


def _keep_graph(p: Plan, key, graph):
    p.graph_of[key] = graph
    if len(p.graph_of) > GRAPHS:
        old = next(iter(p.graph_of))
        del p.graph_of[old]
        _book(p.dropped, old, 16 * GRAPHS)


def _book(keys: dict, key, most: int):
    """key into the ordered set `keys` as its latest, the oldest dropped past `most`."""
    keys.pop(key, None)
    keys[key] = True
    if len(keys) > most:
        del keys[next(iter(keys))]


def _outputs(o: dict, like, origin):
    """The plan's output buffers as the kind of the caller's slaves (`like`): themselves
    (wp.array), JAX arrays, or NumPy copies with `point` in the global frame."""
    kind = _kind(like)
    if kind == "warp":
        return o
    if kind == "jax":
        return {k: wp.to_jax(v) for k, v in o.items()}
    # Copies: on the CPU device .numpy() is a view of the plan's buffers, which the next call
    # overwrites.
    res = {k: v.numpy().copy() for k, v in o.items()}
    # NumPy slaves were staged in the plan's frame: back to the global frame in float64.
    res["point"] = res["point"].astype(np.float64) + origin
    return res


def plan_self(
    surface: Surface,
    *,
    world=None,
    d_max=None,
    device=None,
    growth=GROWTH,
    dtype="float32",
    sort_slaves="plan",
    mode="exact",
    graphs=True,
    refit=True,
) -> Plan:
    """`plan` for self-contact (arraycontact.detect_self's rule): every node the surface's
    faces use is a slave, every face a master. world [n_points]: world ids (each world's
    self-contact alone; default: one world). Detect with `detect_self(plan, points)`."""
    if not isinstance(surface, Surface):
        raise ValueError("surface must be an arraycontact.Surface")
    w = None if world is None else _worlds(world, len(surface.points), "world")
    return plan(
        surface,
        surface.points[surface.nodes],
        slave_world=None if w is None else w[surface.nodes],
        master_world=w,
        d_max=d_max,
        device=device,
        growth=growth,
        dtype=dtype,
        sort_slaves=sort_slaves,
        mode=mode,
        graphs=graphs,
        refit=refit,
        self_contact=True,
    )


def detect_self(p: Plan, points):
    """Self-contact of the plan's surface at node coordinates `points` [n_points, 3] (kinds as
    `detect`'s; launches only, capturable). Rows: the surface's used nodes, in order; the
    outputs of `detect` and `finer` (int32)."""
    if not getattr(p, "self_contact", 0):
        raise ValueError("detect_self needs a plan from plan_self")
    return detect(p, None, points)


def run_one_shot(slave_x, master, d_max, dtype, mode, self_contact):
    """`arraycontact.detect(backend="warp")` and `detect_self` (slave_x: every used node, in
    master.nodes order): plan and detect on the default device; host arrays (global frame),
    the device, and the master's (nodes, faces) in the trees."""
    if self_contact:
        p = plan_self(master, d_max=d_max, dtype=dtype, mode=mode)
        out = detect_self(p, master.points)
    else:
        p = plan(master, slave_x, d_max=d_max, dtype=dtype, mode=mode)
        out = detect(p, slave_x, master.points)
    out["active"] = out["active"].astype(bool)
    if "finer" in out:
        out["finer"] = out["finer"].astype(bool)
    n_nodes = _surface.topology(master, p.device).n_nodes
    if len(out["active"]) != len(slave_x):
        raise ValueError(f"self-contact: the slaves must be the master's {n_nodes} used nodes")
    return out, str(p.device), (n_nodes, master.n_faces)


# --- swept detection -----------------------------------------------------------------------

#: The pair list's default length on a GPU, a slave: 32 B a pair in float32 with the deferred
#: lists (0.8 GB at 2^20 slaves, and 64 B a slave for the walk's window); the graded scene at
#: 2^16 needs 8 a slave, rough surfaces 1.3-7.2.
PAIRS_PER_SLAVE = 24

#: Boxes a pair's swept search may visit in each pair_search launch but the last, by device
#: kind and element: a longer search goes on to the next launch, the last has no budget (a
#: CPU's threads do not step together: one launch). H100, 2^20, two launches against one:
#: triangles at 4 graded 19.7 -> 18.7 ms, rough 6.75 -> 6.21, steep 5.91 -> 5.37, fast 11.7
#: -> 9.7 (at 8 and 16 less); rough quad4 at 16 26.8 -> 23.1 ms (at 4 none). Since the one
#: walk and the refit, triangles at 2 against 4: graded 17.1 -> 16.4 ms, rough 4.31 -> 4.03,
#: fast 7.78 -> 7.46 (at 3: 17.1, 4.11, 7.40); since the corner shift, a third launch past 16
#: (against two): graded 8.22 -> 8.05, fast 6.41 -> 5.85, rough tri3 3.68 either way (past 32:
#: 8.01, 5.97, 3.93). Since the slabs of 2^-7, triangles at 1 against 2 (one H200, 2^20):
#: graded 7.29 -> 6.92 ms, rough tri3 3.24 -> 3.06, steep 2.73 -> 2.63 (the second launch's
#: 8, 12, 24 or 32 instead of 16 gained on one scene what they lost on another; a third
#: deferral, (2, 12, 48) or (2, 8, 32), lost 0.4-3 ms on graded).
SWEPT_BUDGET = {
    "cuda": {"tri3": (1, 16), "other": (16,)},
    "cpu": {"tri3": (), "other": ()},
}
#: pair_search's threads: the list's length over these (each takes every so many slots).
#: The list is sized for the densest scenes (PAIRS_PER_SLAVE): a half of it still gives a
#: thread a slot at most up to 12 pairs a slave (H100 2^20, against a thread a slot: tyre,
#: 0.08 pairs a slave, 2.33 -> 2.17 ms, rough tri3 6.21 -> 6.09, graded 18.9 either way; a
#: quarter: graded 20.7; quad4 not measured).
FIRST_SHARE = 2
LATER_SHARE = 8

SWEPT_OUTPUTS = (
    ("hit", int),
    ("toi", real),
    ("face", int),
    ("xi", vec2),
    ("point", vec3),
    ("normal", vec3),
    ("feature", int),
    ("normal_velocity", real),
    ("converged", int),
    ("visits", int),
)


@dataclass(eq=False)
class SweptPlan:
    """Every buffer of a Warp swept detection (see `plan_swept`)."""

    device: object
    master: Surface
    n_slaves: int
    kernel_element: object
    faces: wp.array
    face_world: wp.array
    slave_world: wp.array
    shared: int
    grid: _grid.Grid
    layout: _grid.Layout
    world_bits: int
    origin: np.ndarray
    constants: SweptConstants
    staging: list  # slave x0, x1, master x0, x1 in the local frame
    out: dict
    dtype: np.dtype
    pairs: object  # _sweep.Pairs, or None: every slave searched by swept_scan
    lost: wp.array  # per slave, 1: searched by swept_scan (its pairs did not fit)
    scratch: wp.array  # the pair counts' prefix sum's
    refit: bool
    rebuild: wp.array  # int32 [1]: the last refit found the capture tree's order stale
    built: bool = False  # the capture tree holds an order (a detect has run)
    build_graph: object = None  # CUDA: the conditional rebuild alone (calls outside a graph)
    cuts: dict = field(default_factory=dict)  # CPU: the swept scan's balanced cuts

    def pairs_needed(self) -> int:
        """The pair list's length the last detect_swept needed (a host copy: synchronises).
        Slaves whose pairs did not fit the plan's `pairs` were searched one thread a slave:
        the same answers, slower on a GPU."""
        if self.pairs is None:
            return 0
        n = self.n_slaves
        return int(self.pairs.offset.numpy()[n - 1] + self.pairs.count.numpy()[n - 1])


def plan_swept(
    master: Surface,
    slave_points,
    *,
    slave_world=None,
    master_world=None,
    device=None,
    dtype="float32",
    pairs=None,
    growth=GROWTH,
    refit=True,
) -> SweptPlan:
    """Allocate a swept detection (arraycontact.detect_swept's contract) of n slaves
    (slave_points [n, 3]: their positions at plan time, which place the local frame) against
    `master`; worlds as in `plan`. Detect with `detect_swept(plan, slave_x0, slave_x1,
    master_x0, master_x1)`: one sort of the faces' capture boxes a call.

    pairs: the length of the (slave, face) pair list whose pairs are searched one thread a
    pair (a GPU's threads then wait less on one another than one thread a slave would);
    slaves whose pairs do not fit are searched one thread a slave (the same answers;
    `plan.pairs_needed()` says how many the last call needed). None: PAIRS_PER_SLAVE x n on
    a GPU, 0 on the CPU (no list: each CPU thread takes its slaves one after the other).

    refit, growth: as `plan`'s, for the faces' capture boxes. A detect after the first, where
    the device can choose without the host (on a GPU with conditional graph nodes, in a CUDA
    graph or outside one through the plan's graph of the rebuild alone; on the CPU), keeps
    the capture tree's order and recomputes its boxes (exact for any motion)
    while every capture box's centre stays within (growth - 1) times a small face's radius of
    where it was sorted, and sorts again when one does not (`rebuild[0]` says which). False:
    one sort every call."""
    here = precision(dtype)
    if here.real is not real:
        return here.plan_swept(
            master,
            slave_points,
            slave_world=slave_world,
            master_world=master_world,
            device=device,
            dtype=dtype,
            pairs=pairs,
            growth=growth,
            refit=refit,
        )
    if not isinstance(master, Surface):
        raise ValueError("master must be an arraycontact.Surface")
    if master.n_faces == 0:
        raise ValueError("master has no faces")
    if not growth >= 1:
        raise ValueError(f"growth must be >= 1, got {growth}")
    x = validate_points(slave_points, "slave_points")
    if len(x) == 0:
        raise ValueError("slave_points is empty: there is nothing to plan for")
    device = wp.get_device(device)
    if pairs is None:
        pairs = PAIRS_PER_SLAVE * len(x) if device.is_cuda else 0
    if isinstance(pairs, bool) or not isinstance(pairs, (int, np.integer)) or pairs < 0:
        raise ValueError(f"pairs must be an integer >= 0 or None, got {pairs!r}")
    sw = _worlds(slave_world, len(x), "slave_world")
    shared = master_world is None
    nw = _worlds(master_world, len(master.points), "master_world")
    fw = nw[master.faces[:, 0]]
    if not shared and (nw[master.faces] != fw[:, None]).any():
        r = int(np.argmax((nw[master.faces] != fw[:, None]).any(1)))
        raise ValueError(f"master face {r} has nodes of different worlds: {nw[master.faces[r]]}")
    e = master.element
    lo = np.minimum(bounds(x)[0], master.node_box[0])
    hi = np.maximum(bounds(x)[1], master.node_box[1])
    origin = lo
    extent = float((hi - lo).max())
    dt = np.dtype(NP_REAL)
    rel, rounding = capture_pads(dt)
    consts = SweptConstants(
        pad_rel=rel,
        pad_abs=rounding * 2 * extent,  # (the frame's coordinates, at plan time)
        t_tol=SWEPT_T_TOL[dt],
        space_rtol=SWEPT_SPACE_RTOL[dt],
        feature_tol=SWEPT_FEATURE_TOL[dt],
        lebesgue=float(e.lebesgue),
    )
    n_worlds = 1 if shared else int(nw.max()) + 1
    # plan's margin (a tenth of the faces are smaller), from every k-th face: a margin needs
    # no more, and all of the master's geometry took 0.4 s at 2^21 faces
    few = master.faces[:: max(master.n_faces // 4096, 1)]
    radii = face_bounds(e, master.points[few])[1]
    margin = (growth - 1) * float(np.quantile(radii, 0.1))
    grid, world_bits = _grid.new_grid(
        master.n_faces, np.zeros(3), max(extent, 1e-30), device, margin, n_worlds
    )
    layout = _grid.allot(grid, master.n_faces, device)

    def arr(a, t):
        return wp.array(a, dtype=t, device=device)

    n, npts = len(x), len(master.points)
    return SweptPlan(
        device=device,
        master=master,
        n_slaves=n,
        kernel_element=_element_structs(e.name, device)[1],
        faces=arr(master.faces.astype(np.int32), int),
        face_world=arr(0 * fw if shared else fw, int),
        slave_world=arr(sw, int),
        shared=int(shared),
        grid=grid,
        layout=layout,
        world_bits=world_bits,
        origin=origin,
        constants=consts,
        staging=[wp.zeros(m, dtype=vec3, device=device) for m in (n, n, npts, npts)],
        out={k: wp.zeros(n, dtype=t, device=device) for k, t in SWEPT_OUTPUTS},
        dtype=NP_REAL,
        pairs=_pair_list(n, int(pairs), device) if pairs > 0 else None,
        lost=wp.full(n, 0 if pairs > 0 else 1, dtype=int, device=device),
        scratch=wp.empty(_grid.scan_scratch(n), dtype=int, device=device),
        refit=bool(refit),
        rebuild=wp.zeros(1, dtype=wp.int32, device=device),
    )


def _swept():
    """The swept detection's module, imported on its first use: a static detection launches
    none of its kernels, and Warp declaring them was a third of the float64 modules' import
    (0.14 of 0.45 s on the 2-core machine) in a new process's first call."""
    from . import _sweep

    return _sweep


def _pair_list(n: int, room: int, device):
    _sweep = _swept()
    q = _sweep.Pairs()
    for name, size, t in (
        ("slave", room, int),
        ("face", room, int),
        ("count", n, int),
        ("offset", n, int),
        ("toi", room, real),
        ("where", room, vec2),
        ("conv", room, int),
        ("first", n, real),
        ("later", (2, room), int),
        ("n_later", 2, int),
        ("window", _sweep.WINDOW * n, int),
        ("more", n, int),
        ("n_more", 1, int),
    ):
        setattr(q, name, wp.empty(size, dtype=t, device=device))
    return q


def _swept_launch(p: SweptPlan, xs):
    _sweep = _swept()
    c = p.constants
    dev = p.device
    nf = p.master.n_faces
    n = p.n_slaves
    s0, s1, m0, m1 = xs
    g = p.grid
    args = [m0, m1, p.faces, real(c.lebesgue), p.face_world]
    gather = [0, *args, real(c.pad_rel), real(c.pad_abs), g, p.rebuild]

    def build():
        _slave_launch(_sweep.capture_keys, nf, [0, *args, g], [], dev, first=0)
        _grid._sort(g, nf, p.world_bits)
        _grid.arrange(g, nf, p.layout, dev)
        _slave_launch(_sweep.capture_gather, nf, [*gather, 0], [], dev, first=0)
        _grid.fill(g, p.layout, dev)

    # As `detect`'s trees: a refit where the device decides without the host (on a GPU
    # outside a graph, through the plan's graph of the conditional rebuild: `build` reads only
    # the plan's staging buffers).
    if p.refit and p.built and (dev.is_cpu or wp.is_conditional_graph_supported()):
        p.rebuild.zero_()
        _slave_launch(_sweep.capture_gather, nf, [*gather, 1], [], dev, first=0)
        _grid.refit_up(g, p.layout, dev)
        _rebuild_if(p, build, dev.is_cuda and not dev.is_capturing)
    else:
        build()
    p.built = True
    out = _sweep.Out()
    for k, _ in SWEPT_OUTPUTS:
        setattr(out, k, p.out[k])
    q = p.pairs
    el = p.kernel_element
    walk = [g, s0, s1, p.slave_world, p.shared, real(c.pad_rel)]
    if q is not None:
        room = q.slave.shape[0]
        # One walk a slave writes its count and a window of faces; the few slaves that meet
        # more walk again once their offset is known (a second walk of every slave was 0.8-1.4
        # ms at 2^20 on an H100).
        _slave_launch(_sweep.pair_walk, n, [*walk, 0, q], [], dev, first=6)
        _grid.exclusive_scan(q.count, q.offset, n, p.scratch, dev)
        q.n_more.zero_()
        # (one launch: its atomics, on the CPU plain read-modify-writes, would race in parts)
        wp.launch(_sweep.pair_fill, n, inputs=[q, p.lost, p.out["visits"]], device=dev)
        more = [*walk, q, max(n // LATER_SHARE, 1)]
        wp.launch(_sweep.pair_more, more[-1], inputs=more, device=dev)
        # One launch: the pairs of a slave update its entries by atomics, which a CPU part
        # of its own would race.
        inputs = [el, m0, m1, p.faces, s0, s1, real(c.t_tol), real(c.space_rtol), 0, q]
        tri = p.master.element.name == "tri3"
        search = _sweep.pair_search_tri if tri else _sweep.pair_search
        # On a GPU the long searches go on to later launches (pair_search, SWEPT_BUDGET).
        budgets = SWEPT_BUDGET["cuda" if dev.is_cuda else "cpu"]["tri3" if tri else "other"]
        q.n_later.zero_()
        for d, b in enumerate((*budgets, _sweep.ALL_BOXES)):
            threads = max(room // (LATER_SHARE if d else FIRST_SHARE), 1)
            args = [*inputs, p.out["visits"], b, d, threads]
            wp.launch(_concrete(search, args), threads, inputs=args, device=dev)
    scan = [g, el, m0, m1, p.faces, s0, s1, p.slave_world, p.shared, real(c.pad_rel)]
    scan += [real(c.t_tol), real(c.space_rtol), real(c.feature_tol), p.lost, 0, out]
    _slave_launch(_sweep.swept_scan, n, scan, [], dev, first=14, cuts=p.cuts)
    if q is not None:
        finish = [el, m0, m1, p.faces, s0, s1, real(c.feature_tol), real(c.t_tol), p.lost, 0]
        finish += [q, out]
        _slave_launch(_sweep.pair_finish, n, finish, [], dev, first=9)


def detect_swept(p: SweptPlan, slave_x0, slave_x1, master_x0, master_x1):
    """Launch a swept detection: each slave's earliest contact as it moves from slave_x0 to
    slave_x1 while the master's points move from master_x0 to master_x1 (kinds as `detect`'s:
    wp.array of the plan's vec3, used in place (capturable), JAX or NumPy). Returns a dict of
    arrays: hit, toi (3e38 where no hit), face, xi, point, normal, feature, normal_velocity,
    converged, visits (boxes searched)."""
    if not isinstance(p, SweptPlan):
        if not hasattr(p, "dtype"):
            raise ValueError(f"p must be a SweptPlan from plan_swept, got {type(p)}")
        return precision(p.dtype).detect_swept(p, slave_x0, slave_x1, master_x0, master_x1)
    xs = []
    names = ("slave_x0", "slave_x1", "master_x0", "master_x1")
    sizes = (p.n_slaves, p.n_slaves, len(p.master.points), len(p.master.points))
    for a, st, what, n in zip((slave_x0, slave_x1, master_x0, master_x1), p.staging, names, sizes):
        x, org = _input(p, a, st, what, n)
        if x is not st:  # the caller's own array: into the plan's frame
            wp.launch(_prepare.localise, n, inputs=[x, org], outputs=[st], device=p.device)
        xs.append(st)
    _swept_launch(p, xs)
    return _outputs(p.out, slave_x0, p.origin)


def run_swept(x0, x1, master, m1, su, dtype):
    """`arraycontact.detect_swept(backend="warp")`: plan, detect, host arrays out."""
    rows = su.slave_rows
    p = plan_swept(master, x0[rows], dtype=dtype)
    out = detect_swept(p, x0[rows], x1[rows], master.points, m1)
    k = np.nonzero(out["hit"] == 1)[0]
    res = {n: out[n][k] for n in ("face", "toi", "xi", "point", "normal", "feature")}
    res["normal_velocity"] = out["normal_velocity"][k]
    res["point"] = res["point"] - su.origin  # detect_swept adds su's origin back
    res["converged"] = out["converged"][k].astype(bool)
    res["rows"] = k
    return res, {"visits": int(out["visits"].sum())}, str(p.device)


__all__ = [
    "Plan",
    "SweptPlan",
    "plan",
    "plan_self",
    "plan_swept",
    "detect",
    "detect_self",
    "detect_swept",
    "run_one_shot",
    "run_swept",
]
