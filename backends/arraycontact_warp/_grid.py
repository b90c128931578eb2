"""Stage 2 in Warp: the size-adaptive tree of arraycontact._grid (read its docstring for the
structure and the cost model), built by one radix sort and one reduction launch per level.

Items (master nodes as points, faces as boxes) are sorted by a 63-bit key, the world id in the
high bits and the Morton code of the item's centre below (21 bits an axis with one world), so
each world's items are contiguous and every run of consecutive items is a compact cluster.
Entry j of level k >= 1 is the box around entries W j ... W j + W - 1 of level k - 1 (level 0:
the items) with the range of world ids under it. The scans walk the tree depth first; a visit
of an entry tests its W children at once (one 256-byte read, the same work for every thread
of a GPU warp), goes on with the nearest child and keeps the others as a bit mask per level
(the whole stack: a thread's state stays in registers), each tested again against the reach
when its turn comes: the reach shrinks as answers come, and the nearest-first path finds a
close answer at once. A refit keeps
the order and recomputes the boxes (always exact); a build sorts again, which a refit asks
for when an item moved farther than the plan's margin from where it was sorted (the tree
would stay exact, but grow loose).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import warp as wp

from arraycontact_warp._surface import spread21

from ._prepare import face_bounds
from ._real import real, vec3

# Forward only, no loop unrolling (a scan's loops unrolled copy the projection many times into
# the kernel: minutes of CUDA compilation for no speed).
wp.set_module_options({"enable_backward": False, "max_unroll": 1})

#: Fan-out (the NumPy tree's): the 8 children of an entry are 256 contiguous bytes.
W = 8
#: Levels above the items: a scan keeps W bits of pending children per level in one 64-bit
#: word (up to 8^9 items).
MAX_LEVELS = 9


@wp.struct
class Box:
    """One tree entry: the box around the items under it and the range of their world ids
    (an empty entry: lo > hi, wmin > wmax). One 32-byte record, so one memory transaction
    reads it."""

    lo: vec3
    wmin: int
    hi: vec3
    wmax: int


@wp.struct
class Item:
    """One item in key order: the box around it (lo = hi for a node), its id and world. One
    32-byte record in float32: a scan's one read per item. `id` repeats sorted_ids[k] to fill
    the first half; the scans read sorted_ids, only for the items they keep."""

    lo: vec3
    id: int
    hi: vec3
    world: int


@wp.struct
class NBox:
    """Self-contact: a box holding the unit normals of the items under a tree entry
    (arraycontact._surface.normal_boxes); an empty one has lo > hi."""

    lo: vec3
    hi: vec3


@wp.struct
class Grid:
    n: int  # items
    top: int  # the root's level (>= 1)
    # Where level k >= 1 starts in `boxes` (levels padded to multiples of W), and the entries
    # of level k (sizes[0] = n; the padding past them is empty): arrays, read by every thread
    # alike (a vector indexed at run time would be copied to each thread's local memory).
    offsets: wp.array(dtype=int)
    sizes: wp.array(dtype=int)
    corner: vec3  # the lower corner of the plan's box (local frame): the Morton cells' origin
    quantum: real  # the Morton cell: 2^bits of them a side over the plan's box
    bits: int  # Morton bits an axis (fewer when world ids take the key's high bits)
    # A build sorts again when a refit finds an item farther than this from where it was
    # sorted (a tree's refit is always exact: only its tightness is at stake).
    margin: real
    sorted_ids: wp.array(dtype=int)  # item ids in key order (first n of 2n: radix scratch)
    keys: wp.array(dtype=wp.int64)
    boxes: wp.array(dtype=Box)
    items: wp.array(dtype=Item)  # in key order: a leaf's items are contiguous
    # tri3 face trees: the three corners of each face in key order (the projection's only
    # data, read contiguously); [1, 3] otherwise.
    corners: wp.array2d(dtype=vec3)
    # Each item's centre (a node: its position) when it was sorted, in key order.
    centres: wp.array(dtype=vec3)
    # Self-contact (normals = 1): the normal boxes of the entries (as `boxes`) and of the
    # items (in key order), so that a scan skips what nowhere faces the slave's normal.
    normals: int
    nboxes: wp.array(dtype=NBox)
    nitems: wp.array(dtype=NBox)


# Item and Box are records of two 16-byte halves (a vec3 and an int each). Warp moves a struct
# a component at a time, and a scan's scattered reads (or a gather's strided writes) pay one
# cache request per access: in float32 each half moves in one 16-byte access on a GPU
# (whole detection 1.88 -> 1.72 ms at 2^20 on an H100, with the graphs). float64 records take
# Warp's own path.
if real is wp.float32:
    _HALF = """
    #if defined(__CUDA_ARCH__)
    const float4 v = __ldg(reinterpret_cast<const float4*>(a.data) + 2 * k + h);
    return wp::vec_t<3, wp::float32>(v.x, v.y, v.z);
    #else
    const float* p = reinterpret_cast<const float*>(a.data) + 8 * k + 4 * h;
    return wp::vec_t<3, wp::float32>(p[0], p[1], p[2]);
    #endif
    """
    _HALF_INT = """
    #if defined(__CUDA_ARCH__)
    return __ldg(reinterpret_cast<const int*>(a.data) + 8 * k + 4 * h + 3);
    #else
    return reinterpret_cast<const int*>(a.data)[8 * k + 4 * h + 3];
    #endif
    """
    _STORE = """
    #if defined(__CUDA_ARCH__)
    float4* p = reinterpret_cast<float4*>(a.data) + 2 * k;
    p[0] = make_float4(lo[0], lo[1], lo[2], __int_as_float(i));
    p[1] = make_float4(hi[0], hi[1], hi[2], __int_as_float(j));
    #else
    float* p = reinterpret_cast<float*>(a.data) + 8 * k;
    p[0] = lo[0]; p[1] = lo[1]; p[2] = lo[2]; reinterpret_cast<int*>(p)[3] = i;
    p[4] = hi[0]; p[5] = hi[1]; p[6] = hi[2]; reinterpret_cast<int*>(p)[7] = j;
    #endif
    """

    @wp.func_native(_HALF)
    def _item_vec(a: wp.array(dtype=Item), k: int, h: int) -> vec3: ...

    @wp.func_native(_STORE)
    def _store_item(a: wp.array(dtype=Item), k: int, lo: vec3, i: int, hi: vec3, j: int): ...

    @wp.func_native(_HALF)
    def _box_vec(a: wp.array(dtype=Box), k: int, h: int) -> vec3: ...

    @wp.func_native(_HALF_INT)
    def _box_int(a: wp.array(dtype=Box), k: int, h: int) -> int: ...

    @wp.func_native(_STORE)
    def _store_box(a: wp.array(dtype=Box), k: int, lo: vec3, i: int, hi: vec3, j: int): ...

    @wp.func
    def item_lo(grid: Grid, k: int):
        return _item_vec(grid.items, k, 0)

    @wp.func
    def item_hi(grid: Grid, k: int):
        return _item_vec(grid.items, k, 1)

    @wp.func_native(_HALF_INT)
    def _item_int(a: wp.array(dtype=Item), k: int, h: int) -> int: ...

    @wp.func
    def item_world(grid: Grid, k: int):
        return _item_int(grid.items, k, 1)

    @wp.func
    def read_box(grid: Grid, key: int):
        box = Box()
        box.lo = _box_vec(grid.boxes, key, 0)
        box.hi = _box_vec(grid.boxes, key, 1)
        box.wmin = _box_int(grid.boxes, key, 0)
        box.wmax = _box_int(grid.boxes, key, 1)
        return box

    @wp.func
    def write_item(grid: Grid, k: int, lo: vec3, i: int, hi: vec3, world: int):
        _store_item(grid.items, k, lo, i, hi, world)

    @wp.func
    def write_box(grid: Grid, key: int, box: Box):
        _store_box(grid.boxes, key, box.lo, box.wmin, box.hi, box.wmax)
else:

    @wp.func
    def item_lo(grid: Grid, k: int):
        return grid.items[k].lo

    @wp.func
    def item_hi(grid: Grid, k: int):
        return grid.items[k].hi

    @wp.func
    def item_world(grid: Grid, k: int):
        return grid.items[k].world

    @wp.func
    def read_box(grid: Grid, key: int):
        return grid.boxes[key]

    @wp.func
    def write_item(grid: Grid, k: int, lo: vec3, i: int, hi: vec3, world: int):
        item = Item()
        item.lo = lo
        item.id = i
        item.hi = hi
        item.world = world
        grid.items[k] = item

    @wp.func
    def write_box(grid: Grid, key: int, box: Box):
        grid.boxes[key] = box


@wp.func
def entry(grid: Grid, k: int, j: int):
    """Entry j of level k >= 1."""
    return read_box(grid, grid.offsets[k] + j)


@wp.func
def box_gap_sq(s: vec3, lo: vec3, hi: vec3):
    """The squared distance from s to the box [lo, hi]."""
    return wp.length_sq(wp.max(wp.max(lo - s, s - hi), vec3(0.0)))


#: arraycontact._grid.FACING_MARGIN: an entry is skipped when every normal in its box has
#: n_i . n >= this.
FACING_MARGIN = 1.0e-4


@wp.func
def facing(n: vec3, b: NBox):
    """Whether some normal in the box b may face n (arraycontact._grid.facing)."""
    low = real(0.0)
    for a in range(3):
        low += real(0.5) * (n[a] * (b.lo[a] + b.hi[a]) - wp.abs(n[a]) * (b.hi[a] - b.lo[a]))
    return low < real(FACING_MARGIN)


# Self-contact's tests specialise the scans by type: `Plain` (two bodies) compiles them away,
# `Own` (the slave's node and normal) makes them. A runtime flag kept the normal live in
# registers in every two-body scan too (uniform 2^20 on an H100: 2.55 -> 3.0 ms).
@wp.struct
class Plain:
    unused: int


@wp.struct
class Own:
    node: int
    normal: vec3


@wp.func
def may_face(o: Plain, grid: Grid, key: int):
    """Whether the tree entry at `key` may hold a face (or node) facing the slave."""
    return True


@wp.func
def may_face(o: Own, grid: Grid, key: int):  # noqa: F811 (a Warp overload)
    return facing(o.normal, grid.nboxes[key])


@wp.func
def may_face_item(o: Plain, grid: Grid, k: int):
    """Whether item k (key order) may face the slave."""
    return True


@wp.func
def may_face_item(o: Own, grid: Grid, k: int):  # noqa: F811 (a Warp overload)
    return facing(o.normal, grid.nitems[k])


@wp.func
def enters(s: vec3, world: int, shared: int, box: Box, reach: real):
    """Whether a scan enters an entry: its box is within reach of s and (a master with world
    ids) it holds items of the slave's world."""
    ok = box_gap_sq(s, box.lo, box.hi) <= reach * reach
    if ok and shared == 0:
        ok = box.wmin <= world and world <= box.wmax
    return ok


@wp.func
def children(
    grid: Grid,
    s: vec3,
    world: int,
    shared: int,
    k: int,
    j: int,
    reach: real,
    centred: int,
    o: Any,
):
    """Which children (level k - 1 >= 1) of entry j of level k a scan enters: a bit mask, and
    the child with the nearest box (-1 when none), which the scan visits first. centred = 1:
    among boxes that hold s (near the root, several), the one whose centre is nearest (node
    scan at 2^20 on an H100: 0.68 -> 0.58 ms uniform, 4.67 -> 3.53 ms graded_1000; the face
    scan, which starts from the closest node's distance, runs slower with it). o: Plain, or
    Own (self-contact: only the children that may face the slave's normal)."""
    mask = int(0)
    near = int(-1)
    near_d2 = real(3.0e38)
    for c in range(W):
        box = entry(grid, k - 1, W * j + c)
        d2 = box_gap_sq(s, box.lo, box.hi)
        ok = d2 <= reach * reach
        if ok and shared == 0:
            ok = box.wmin <= world and world <= box.wmax
        if ok:
            ok = may_face(o, grid, grid.offsets[k - 1] + W * j + c)
        if ok:
            mask = mask | (1 << c)
            if centred == 1 and d2 == real(0.0):
                # Inside: rank by the centre's distance, below every box outside.
                d2 = -real(1.0) / (real(1.0) + wp.length_sq(real(0.5) * (box.lo + box.hi) - s))
            if d2 < near_d2:
                near_d2 = d2
                near = c
    return mask, near


@wp.func
def pending(stack: wp.uint64, k: int):
    """The children of level k still to visit (level k's W bits of the scan's stack)."""
    return int((stack >> wp.uint64(W * (k - 1))) & wp.uint64(255))


@wp.func
def with_pending(stack: wp.uint64, k: int, mask: int):
    """The stack with level k's bits replaced by mask."""
    shift = wp.uint64(W * (k - 1))
    return (stack & ~(wp.uint64(255) << shift)) | (wp.uint64(mask) << shift)


@wp.func_native("""
#if defined(__CUDA_ARCH__)
return __ffs(x) - 1;
#else
return __builtin_ffs(x) - 1;
#endif
""")
def lowest_bit(x: int) -> int:
    """The index of x's lowest set bit (-1 for 0)."""
    ...


@wp.func
def descend(stack: wp.uint64, k: int, j: int, mask: int, near: int):
    """Go on with child `near` of entry j of level k, keeping the other children of `mask`
    pending: (stack, level, entry)."""
    return with_pending(stack, k - 1, mask & ~(1 << near)), k - 1, W * j + near


@wp.func
def next_pending(grid: Grid, stack: wp.uint64, k: int, j: int):
    """The entry to visit after (k, j) and what is under it: the next pending sibling, here or
    on a level above. Returns (stack, level, entry, 1), or (..., 0) when none is left."""
    kk = k
    jj = j
    while kk < grid.top and pending(stack, kk) == 0:
        kk += 1
        jj = jj // W
    if kk >= grid.top:
        return stack, kk, jj, 0
    left = pending(stack, kk)
    return with_pending(stack, kk, left & (left - 1)), kk, W * (jj // W) + lowest_bit(left), 1


@wp.func
def morton_key(c: vec3, world: int, quantum: real, bits: int):
    """The world id above the Morton code of c's cell (bits <= 21 an axis, clamped to the
    box): bit b of axis a at bit 3 b + a (spread by masks, not a loop over the bits: the face
    keys on Warp's CPU device at 2^16, 12.7 -> 3.2 ms)."""
    top = (1 << bits) - 1
    key = wp.int64(world) << wp.int64(3 * bits)
    for a in range(3):
        v = wp.int64(wp.clamp(int(wp.floor(c[a] / quantum)), 0, top))
        key = key | (spread21(v) << wp.int64(a))
    return key


@wp.kernel
def _keys(
    x: wp.array(dtype=vec3), ids: wp.array(dtype=int), world: wp.array(dtype=int), grid: Grid
):
    k = wp.tid()
    i = ids[k]
    grid.keys[k] = morton_key(x[i] - grid.corner, world[i], grid.quantum, grid.bits)
    grid.sorted_ids[k] = i


@wp.kernel
def _face_keys(
    points: wp.array(dtype=vec3),
    faces: wp.array2d(dtype=int),
    lebesgue: real,
    world: wp.array(dtype=int),
    grid: Grid,
):
    f = wp.tid()
    c, r, lo, hi = face_bounds(points, faces, f, lebesgue)
    grid.keys[f] = morton_key(c - grid.corner, world[f], grid.quantum, grid.bits)
    grid.sorted_ids[f] = f


@wp.kernel
def _gather(
    x: wp.array(dtype=vec3),
    world: wp.array(dtype=int),
    refit: int,
    grid: Grid,
    rebuild: wp.array(dtype=wp.int32),
):
    """Each node's record in key order (a point: lo = hi). refit = 1: the order is the
    previous build's; rebuild[0] is raised when a node moved farther than grid.margin."""
    k = wp.tid()
    i = grid.sorted_ids[k]
    if refit == 1:
        if wp.length(x[i] - grid.centres[k]) > grid.margin:
            rebuild[0] = 1
    else:
        grid.centres[k] = x[i]
    write_item(grid, k, x[i], i, x[i], world[i])


@wp.kernel
def _face_gather(
    points: wp.array(dtype=vec3),
    faces: wp.array2d(dtype=int),
    lebesgue: real,
    world: wp.array(dtype=int),
    corners: int,
    refit: int,
    grid: Grid,
    rebuild: wp.array(dtype=wp.int32),
):
    """Each face's record (its box) in key order, and (corners = 1, tri3) its corners.
    refit = 1: as _gather, for the faces' centres."""
    k = wp.tid()
    i = grid.sorted_ids[k]
    c, r, lo, hi = face_bounds(points, faces, i, lebesgue)
    if refit == 1:
        if wp.length(c - grid.centres[k]) > grid.margin:
            rebuild[0] = 1
    else:
        grid.centres[k] = c
    write_item(grid, k, lo, i, hi, world[i])
    if corners == 1:
        for j in range(3):
            grid.corners[k, j] = points[faces[i, j]]


@wp.func
def _empty_box():
    box = Box()
    box.lo = vec3(real(1.0e30))
    box.hi = vec3(real(-1.0e30))
    box.wmin = int(2147483647)
    box.wmax = int(-1)
    return box


@wp.func
def _empty_nbox():
    b = NBox()
    b.lo = vec3(real(1.0))
    b.hi = vec3(real(-1.0))
    return b


@wp.func
def _nbox_union(a: NBox, b: NBox):
    c = NBox()
    c.lo = wp.min(a.lo, b.lo)
    c.hi = wp.max(a.hi, b.hi)
    return c


@wp.kernel
def _gather_normals(grid: Grid, lo: wp.array(dtype=vec3), hi: wp.array(dtype=vec3)):
    """Self-contact: each item's normal box (lo, hi by item id) in key order."""
    k = wp.tid()
    i = grid.sorted_ids[k]
    b = NBox()
    b.lo = lo[i]
    b.hi = hi[i]
    grid.nitems[k] = b


@wp.kernel
def _leaves(grid: Grid):
    """Level 1: each entry's box and world range over its W items (empty past the last)."""
    j = wp.tid()
    box = _empty_box()
    for t in range(W):
        k = W * j + t
        if k < grid.n:
            box.lo = wp.min(box.lo, item_lo(grid, k))
            box.hi = wp.max(box.hi, item_hi(grid, k))
            w = item_world(grid, k)
            box.wmin = wp.min(box.wmin, w)
            box.wmax = wp.max(box.wmax, w)
    write_box(grid, grid.offsets[1] + j, box)
    if grid.normals == 1:
        nb = _empty_nbox()
        for t in range(W):
            if W * j + t < grid.n:
                nb = _nbox_union(nb, grid.nitems[W * j + t])
        grid.nboxes[grid.offsets[1] + j] = nb


@wp.kernel
def _level(grid: Grid, k: int):
    """Level k >= 2: each entry's box and world range over its W children (empty past the
    last: the padding of a level has no children)."""
    j = wp.tid()
    box = _empty_box()
    for c in range(W):
        if W * j + c < grid.sizes[k - 1]:
            b = entry(grid, k - 1, W * j + c)
            box.lo = wp.min(box.lo, b.lo)
            box.hi = wp.max(box.hi, b.hi)
            box.wmin = wp.min(box.wmin, b.wmin)
            box.wmax = wp.max(box.wmax, b.wmax)
    write_box(grid, grid.offsets[k] + j, box)
    if grid.normals == 1:
        nb = _empty_nbox()
        for c in range(W):
            if W * j + c < grid.sizes[k - 1]:
                nb = _nbox_union(nb, grid.nboxes[grid.offsets[k - 1] + W * j + c])
        grid.nboxes[grid.offsets[k] + j] = nb


def level_sizes(n: int):
    """Entries of levels 1 .. top (the NumPy tree's level_sizes without level 0), each padded
    to a whole group of W in the allocation."""
    sizes = [max(n, 1)]
    while sizes[-1] > 1 or len(sizes) < 2:
        sizes.append(-(-sizes[-1] // W))
    return sizes[1:]


def fill(grid: Grid, n: int, device):
    """Every level's boxes from the items in key order: one launch a level, leaves first."""
    sizes = level_sizes(n)
    wp.launch(_leaves, sizes[0] + (-sizes[0]) % W, inputs=[grid], device=device)
    for k, size in enumerate(sizes[1:], start=2):
        wp.launch(_level, size + (-size) % W, inputs=[grid, k], device=device)


def _sort(grid: Grid, n: int, world_bits: int):
    wp.utils.radix_sort_pairs(
        grid.keys, grid.sorted_ids, n, end_bit=3 * int(grid.bits) + world_bits
    )


def _normals(grid: Grid, n: int, normals, device):
    if normals is not None:
        wp.launch(_gather_normals, n, inputs=[grid, *normals], device=device)


def build(grid: Grid, x, ids, world, n: int, device, rebuild, world_bits: int, normals=None):
    """Fill `grid` with the points x[ids[:n]] (launches only: capturable). normals
    (self-contact): the items' normal boxes (lo, hi) by item id."""
    wp.launch(_keys, n, inputs=[x, ids, world, grid], device=device)
    _sort(grid, n, world_bits)
    wp.launch(_gather, n, inputs=[x, world, 0, grid, rebuild], device=device)
    _normals(grid, n, normals, device)
    fill(grid, n, device)


def build_faces(
    grid: Grid,
    points,
    faces,
    lebesgue: float,
    world,
    device,
    corners: bool,
    rebuild,
    world_bits: int,
    normals=None,
):
    """Fill `grid` with the faces (launches only: capturable); corners (tri3): also their
    corners in key order. normals: as `build`'s."""
    n = faces.shape[0]
    wp.launch(_face_keys, n, inputs=[points, faces, real(lebesgue), world, grid], device=device)
    _sort(grid, n, world_bits)
    wp.launch(
        _face_gather,
        n,
        inputs=[points, faces, real(lebesgue), world, int(corners), 0, grid, rebuild],
        device=device,
    )
    _normals(grid, n, normals, device)
    fill(grid, n, device)


# A refit: the records again in the previous build's key order, raising rebuild[0] where an
# item left the margin; then `fill`, or a build when raised (the caller's choice on the
# device: wp.capture_if).
def refit(grid: Grid, x, world, n: int, device, rebuild, normals=None):
    wp.launch(_gather, n, inputs=[x, world, 1, grid, rebuild], device=device)
    _normals(grid, n, normals, device)


def refit_faces(
    grid: Grid, points, faces, lebesgue: float, world, device, corners: bool, rebuild, normals=None
):
    wp.launch(
        _face_gather,
        faces.shape[0],
        inputs=[points, faces, real(lebesgue), world, int(corners), 1, grid, rebuild],
        device=device,
    )
    _normals(grid, faces.shape[0], normals, device)


def new_grid(
    n: int,
    corner,
    extent: float,
    device,
    margin: float,
    n_worlds: int = 1,
    corners=False,
    normals=False,
):
    """A tree for n items in the cube of side `extent` at `corner` (local frame), with
    `margin` the distance an item may move before a refit asks for a build; normals: with
    normal boxes (self-contact). Returns (grid, world bits)."""
    world_bits = max(int(n_worlds - 1).bit_length(), 0)
    sizes = level_sizes(n)
    if len(sizes) > MAX_LEVELS:
        raise ValueError(f"{n} items need more than {MAX_LEVELS} tree levels")
    g = Grid()
    g.n, g.top = max(n, 0), len(sizes)
    offsets = np.zeros(MAX_LEVELS + 1, np.int32)
    counts = np.zeros(MAX_LEVELS + 1, np.int32)
    counts[0] = n
    total = 0
    for k, size in enumerate(sizes, start=1):
        offsets[k], counts[k] = total, size
        total += size + (-size) % W
    g.offsets = wp.array(offsets, dtype=int, device=device)
    g.sizes = wp.array(counts, dtype=int, device=device)
    g.bits = min(21, (63 - world_bits) // 3)
    g.corner = vec3(*[float(v) for v in corner])
    g.quantum = real(max(float(extent), 1e-30) / (1 << g.bits))
    g.margin = real(margin)
    g.sorted_ids = wp.zeros(2 * max(n, 1), dtype=int, device=device)
    g.keys = wp.zeros(2 * max(n, 1), dtype=wp.int64, device=device)
    g.boxes = wp.zeros(total, dtype=Box, device=device)
    g.items = wp.zeros(max(n, 1), dtype=Item, device=device)
    g.corners = wp.zeros((max(n, 1) if corners else 1, 3), dtype=vec3, device=device)
    g.centres = wp.full(max(n, 1), vec3(1.0e30), dtype=vec3, device=device)
    g.normals = int(normals)
    g.nboxes = wp.zeros(total if normals else 1, dtype=NBox, device=device)
    g.nitems = wp.zeros(max(n, 1) if normals else 1, dtype=NBox, device=device)
    return g, world_bits


@wp.func
def _spread(v: int):
    """The low 10 bits of v moved to every third bit (a Morton code's interleaving)."""
    x = wp.uint32(wp.clamp(v, 0, 1023))
    x = (x | (x << wp.uint32(16))) & wp.uint32(0x030000FF)
    x = (x | (x << wp.uint32(8))) & wp.uint32(0x0300F00F)
    x = (x | (x << wp.uint32(4))) & wp.uint32(0x030C30C3)
    x = (x | (x << wp.uint32(2))) & wp.uint32(0x09249249)
    return x


@wp.kernel
def _morton(
    x: wp.array(dtype=vec3),
    origin: vec3,
    quantum: real,
    keys: wp.array(dtype=int),
    order: wp.array(dtype=int),
):
    i = wp.tid()
    c = x[i] - origin
    cx = int(wp.floor(c[0] / quantum))
    cy = int(wp.floor(c[1] / quantum))
    cz = int(wp.floor(c[2] / quantum))
    keys[i] = int(_spread(cx) | (_spread(cy) << wp.uint32(1)) | (_spread(cz) << wp.uint32(2)))
    order[i] = i


def spatial_order(x, origin, quantum, keys, order, n: int, device):
    """order[:n]: the rows of x in Morton order of cells of size `quantum` (1024 per axis over
    the plan's box), so that the threads of a GPU warp work on neighbouring slaves and walk the
    same tree entries (launches only: capturable; keys and order hold 2n for the radix sort)."""
    wp.launch(_morton, n, inputs=[x, origin, quantum, keys, order], device=device)
    wp.utils.radix_sort_pairs(keys, order, n, end_bit=30)
