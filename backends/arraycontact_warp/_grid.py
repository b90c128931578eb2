"""Stage 2 in Warp: the size-adaptive tree of arraycontact._grid (read its docstring for the
structure and the cost model), built by one radix sort, a grouping pass and one reduction
launch per level.

Items (master nodes as points, faces as boxes) are sorted by a 63-bit key, the world id in the
high bits and the Morton code of the item's centre below (21 bits an axis with one world), so
each world's items are contiguous. The items are then grouped by Morton prefixes (the comment
above `_splits`): each group, at most W items in key order, is the largest node of the keys'
binary radix tree that holds no more, and takes W slots (the empty ones lo > hi). The groups
of level k are the entries of level k + 1, grouped by the same rule, and so on up to one
root. A slot of level k >= 1 holds the box around its group of W slots in level k - 1 (level
0: the item slots), where that group starts (`first`) and the world of the items under it;
`up` gives a group's parent slot. The scans walk the tree depth first; a visit of a slot
tests its W children at once (one 256-byte read, the same work for every thread of a GPU
warp), goes on with the nearest child and keeps the others as a bit mask per level (the
whole stack: a thread's state stays in registers), each tested again against the reach when
its turn comes: the reach shrinks as answers come, and the nearest-first path finds a close
answer at once. A refit keeps the slots and recomputes the boxes (always exact); a build
sorts and groups again, which a refit asks for when an item moved farther than the plan's
margin from where it was sorted (the tree would stay exact, but grow loose).
"""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np
import warp as wp

from arraycontact_warp._surface import spread21

from ._parts import launch, replayed
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
    """One tree slot: the box around the items under it, where its children start in the
    level below (a group of W slots) and the world of its items (-1: several, -2: none, an
    empty slot, whose lo > hi). One 32-byte record, so one memory transaction reads it."""

    lo: vec3
    first: int
    hi: vec3
    world: int


@wp.struct
class Item:
    """One item slot (items in key order, in groups of W): the box around it (lo = hi for a
    node), its id and world (an empty slot: lo > hi, id -1, world -2). One 32-byte record in
    float32: a scan's one read per item."""

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
    # Levels of the allocation: the tree's root is at level root[0] <= top (its slot 0).
    top: int
    root: wp.array(dtype=int)
    # Where level k >= 1's slots start in `boxes` (multiples of W; the items are level 0),
    # read by every thread alike (a vector indexed at run time would be copied to each
    # thread's local memory).
    offsets: wp.array(dtype=int)
    # The build's bookkeeping (the module docstring): entries per level (counts[0] = n), the
    # slot of each entry of level k at slots[slot_offsets[k] + entry], the groups each level
    # may hold in Morton-aligned groups (0: none, W consecutive entries a group), whether it
    # does (aligned[k]), and the parent slot of each group of slots (levels >= 1:
    # up[(offsets[k] + slot) / W]), for a scan that goes back up.
    counts: wp.array(dtype=int)
    slots: wp.array(dtype=int)
    slot_offsets: wp.array(dtype=int)
    capacity: wp.array(dtype=int)
    aligned: wp.array(dtype=int)
    up: wp.array(dtype=int)
    # A refit (`_refit_up`): the occupied slots of each group of slots (levels >= 1, indexed
    # as `up`) and the arrivals counted at each (zero between launches).
    need: wp.array(dtype=int)
    arrived: wp.array(dtype=int)
    # Scratch of the grouping: the split of each pair of neighbours (two halves, the level's
    # and the next's), group ends, group ids, the prefix sum's.
    split: wp.array(dtype=int)
    ends: wp.array(dtype=int)
    group: wp.array(dtype=int)
    scratch: wp.array(dtype=int)  # exclusive_scan's
    corner: vec3  # the lower corner of the plan's box (local frame): the Morton cells' origin
    quantum: real  # the Morton cell: 2^bits of them a side over the plan's box
    bits: int  # Morton bits an axis (fewer when world ids take the key's high bits)
    sides: int  # > 0: the Morton level of the faces' normal classes in their keys
    # A build sorts again when a refit finds an item farther than this from where it was
    # sorted (a tree's refit is always exact: only its tightness is at stake).
    margin: real
    sorted_ids: wp.array(dtype=int)  # item ids in key order (first n of 2n: radix scratch)
    keys: wp.array(dtype=wp.int64)
    boxes: wp.array(dtype=Box)
    items: wp.array(dtype=Item)  # item slots: a leaf's items are contiguous
    # tri3 face trees: the three corners of each face by item slot (the projection's only
    # data, read contiguously); [1, 3] otherwise.
    corners: wp.array2d(dtype=vec3)
    # Each item's centre (a node: its position) when it was sorted, in key order.
    centres: wp.array(dtype=vec3)
    # Self-contact (normals = 1): the normal boxes of the slots (as `boxes`) and of the
    # items (by slot), so that a scan skips what nowhere faces the slave's normal.
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
    def item_id(grid: Grid, k: int):
        return _item_int(grid.items, k, 0)

    @wp.func
    def read_box(grid: Grid, key: int):
        box = Box()
        box.lo = _box_vec(grid.boxes, key, 0)
        box.hi = _box_vec(grid.boxes, key, 1)
        box.first = _box_int(grid.boxes, key, 0)
        box.world = _box_int(grid.boxes, key, 1)
        return box

    @wp.func
    def write_item(grid: Grid, k: int, lo: vec3, i: int, hi: vec3, world: int):
        _store_item(grid.items, k, lo, i, hi, world)

    @wp.func
    def write_box(grid: Grid, key: int, box: Box):
        _store_box(grid.boxes, key, box.lo, box.first, box.hi, box.world)
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
    def item_id(grid: Grid, k: int):
        return grid.items[k].id

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


# Reads through L2 alone (`_refit_up`: records that other threads of the launch wrote; an
# SM's L1 may hold a line of them loaded before), a record's lo (h = 0) or hi half.
_T = "float" if real is wp.float32 else "double"
_CG_VEC = f"""
const auto& r = a.data[k];
const {_T}* p = reinterpret_cast<const {_T}*>(h == 0 ? &r.lo : &r.hi);
#if defined(__CUDA_ARCH__)
return wp::vec_t<3, {_T}>(__ldcg(p), __ldcg(p + 1), __ldcg(p + 2));
#else
return wp::vec_t<3, {_T}>(p[0], p[1], p[2]);
#endif
"""


# A record's half in one 16-byte read in float32 (as _HALF).
_CG_REC = _HALF.replace("__ldg", "__ldcg") if real is wp.float32 else _CG_VEC


@wp.func_native(_CG_REC)
def _box_half_cg(a: wp.array(dtype=Box), k: int, h: int) -> vec3: ...


@wp.func_native(_CG_VEC)
def _nbox_half_cg(a: wp.array(dtype=NBox), k: int, h: int) -> vec3: ...


@wp.func_native("""
#if defined(__CUDA_ARCH__)
return __ldcg(&a.data[k].world);
#else
return a.data[k].world;
#endif
""")
def _box_world_cg(a: wp.array(dtype=Box), k: int) -> int: ...


@wp.func_native("""
#if defined(__CUDA_ARCH__)
int old;
asm volatile("atom.acq_rel.gpu.add.s32 %0, [%1], 1;"
             : "=r"(old) : "l"(a.data + k) : "memory");
return old;
#else
return a.data[k]++;
#endif
""")
def _arrive(a: wp.array(dtype=int), k: int) -> int:
    """a[k] += 1, returning the count before: on a GPU an atomic that releases this thread's
    writes and acquires those of the threads that added before it (what the climb needs; a
    __threadfence is a sequentially consistent fence)."""
    ...


@wp.func
def entry(grid: Grid, k: int, j: int):
    """Slot j of level k >= 1."""
    return read_box(grid, grid.offsets[k] + j)


@wp.func
def of_world(w: int, world: int):
    """Whether a slot whose items are of world w (-1: several) may hold items of `world`."""
    return w == world or w == -1


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


#: A face surely counts for a self-contact slave of normal n when n . n_f stays below this
#: over its normal box: far below the scans' own threshold (-FACING_TOL), whatever the
#: rounding of the normal a scan computes at the face's closest point.
SURELY_FACING = -0.01


@wp.func
def surely_facing(n: vec3, lo: vec3, hi: vec3):
    """Whether every normal in the box [lo, hi] faces n (facing's other side)."""
    high = real(0.0)
    for a in range(3):
        high += real(0.5) * (n[a] * (lo[a] + hi[a]) + wp.abs(n[a]) * (hi[a] - lo[a]))
    return high < real(SURELY_FACING)


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


@wp.struct
class Segment:
    """A swept scan's slave: the segment a + t d, t in [0, 1] (its path over the step),
    grown by pad (arraycontact._sweep.capture_pads)."""

    a: vec3
    d: vec3
    pad: real


@wp.func
def meets(o: Segment, lo: vec3, hi: vec3):
    """Whether the segment meets the box [lo, hi] (slab test; an axis along which the segment
    does not move: its coordinate within the box's). Far tighter than the ball around the
    segment for the long paths of fast or steep motion (pairs a slave at 2^12: steep 25 ->
    3.4, rough_fast 26 -> 7.2)."""
    t0 = real(0.0)
    t1 = real(1.0)
    ok = bool(True)
    for c in range(3):
        b_lo = lo[c] - o.pad
        b_hi = hi[c] + o.pad
        if o.d[c] != real(0.0):
            u = (b_lo - o.a[c]) / o.d[c]
            v = (b_hi - o.a[c]) / o.d[c]
            t0 = wp.max(t0, wp.min(u, v))
            t1 = wp.min(t1, wp.max(u, v))
        elif o.a[c] < b_lo or o.a[c] > b_hi:
            ok = False
    return ok and t0 <= t1


@wp.func
def may_face(o: Plain, grid: Grid, key: int, box: Box):
    """Whether the tree entry at `key` (box) may hold a face (or node) facing the slave, or
    (swept) met by its segment."""
    return True


@wp.func
def may_face(o: Own, grid: Grid, key: int, box: Box):  # noqa: F811 (a Warp overload)
    return facing(o.normal, grid.nboxes[key])


@wp.func
def may_face(o: Segment, grid: Grid, key: int, box: Box):  # noqa: F811 (a Warp overload)
    return meets(o, box.lo, box.hi)


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
        ok = of_world(box.world, world)
    return ok


@wp.func
def children(
    grid: Grid,
    s: vec3,
    world: int,
    shared: int,
    k: int,
    first: int,
    reach: real,
    centred: int,
    o: Any,
):
    """Which children (slots first .. first + W - 1 of level k - 1 >= 1) of a slot of level k
    a scan enters: a bit mask, and
    the child with the nearest box (-1 when none), which the scan visits first. centred = 1:
    among boxes that hold s (near the root, several), the one whose centre is nearest (node
    scan at 2^20 on an H100: 0.68 -> 0.58 ms uniform, 4.67 -> 3.53 ms graded_1000; the face
    scan, which starts from the closest node's distance, runs slower with it). o: Plain, or
    Own (self-contact: only the children that may face the slave's normal), or Segment (swept:
    only the children its segment meets)."""
    mask = int(0)
    near = int(-1)
    near_d2 = real(3.0e38)
    for c in range(W):
        box = entry(grid, k - 1, first + c)
        d2 = box_gap_sq(s, box.lo, box.hi)
        ok = d2 <= reach * reach
        if ok and shared == 0:
            ok = of_world(box.world, world)
        if ok:
            ok = may_face(o, grid, grid.offsets[k - 1] + first + c, box)
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
def descend(stack: wp.uint64, k: int, first: int, mask: int, near: int):
    """Go on with child `near` of a slot of level k whose children start at `first`, keeping
    the other children of `mask` pending: (stack, level, slot)."""
    return with_pending(stack, k - 1, mask & ~(1 << near)), k - 1, first + near


@wp.func
def next_pending(grid: Grid, top: int, stack: wp.uint64, k: int, j: int):
    """The slot to visit after (k, j) and what is under it: the next pending sibling, here or
    on a level above (up to the root's level `top`). Returns (stack, level, slot, 1), or
    (..., 0) when none is left."""
    kk = k
    jj = j
    while kk < top and pending(stack, kk) == 0:
        jj = grid.up[(grid.offsets[kk] + jj) // W]
        kk += 1
    if kk >= top:
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
    first: int,
    x: wp.array(dtype=vec3),
    ids: wp.array(dtype=int),
    world: wp.array(dtype=int),
    grid: Grid,
):
    k = first + wp.tid()
    i = ids[k]
    grid.keys[k] = morton_key(x[i] - grid.corner, world[i], grid.quantum, grid.bits)
    grid.sorted_ids[k] = i


@wp.kernel
def _face_keys(
    first: int,
    points: wp.array(dtype=vec3),
    faces: wp.array2d(dtype=int),
    lebesgue: real,
    world: wp.array(dtype=int),
    grid: Grid,
):
    f = first + wp.tid()
    c, r, lo, hi = face_bounds(points, faces, f, lebesgue)
    key = morton_key(c - grid.corner, world[f], grid.quantum, grid.bits)
    if grid.sides > 0:
        key = _side_key(key, _face_normal(points, faces, f), grid.sides)
    grid.keys[f] = key
    grid.sorted_ids[f] = f


@wp.func
def _face_normal(points: wp.array(dtype=vec3), faces: wp.array2d(dtype=int), f: int):
    """The face's corner normal (unnormalised): its diagonals' cross product on quads."""
    x0 = points[faces[f, 0]]
    x1 = points[faces[f, 1]]
    x2 = points[faces[f, 2]]
    k = faces.shape[1]
    if k == 4 or k == 8 or k == 9:
        return wp.cross(x2 - x0, points[faces[f, 3]] - x1)
    return wp.cross(x1 - x0, x2 - x0)


@wp.func
def _side_key(key: wp.int64, n: vec3, level: int):
    """key with the class of normal n (its largest component's axis and sign: 6 classes) put
    in as three bits at Morton level `level` (the finest level's bits dropped), so that
    within each cell of that level the faces are sorted by class."""
    a = int(0)
    if wp.abs(n[1]) > wp.abs(n[a]):
        a = 1
    if wp.abs(n[2]) > wp.abs(n[a]):
        a = 2
    c = 2 * a
    if n[a] < real(0.0):
        c += 1
    b = wp.int64(3 * level)
    one = wp.int64(1)
    low = (key & ((one << b) - one)) >> wp.int64(3)
    return ((key >> b) << b) | (wp.int64(c) << (b - wp.int64(3))) | low


@wp.func
def slot(grid: Grid, p: int):
    """The item slot of the p-th item in key order."""
    return grid.slots[p]


@wp.kernel
def _gather(
    first: int,
    x: wp.array(dtype=vec3),
    world: wp.array(dtype=int),
    refit: int,
    grid: Grid,
    rebuild: wp.array(dtype=wp.int32),
):
    """Each node's record in its slot (a point: lo = hi). refit = 1: the order is the
    previous build's; rebuild[0] is raised when a node moved farther than grid.margin."""
    k = first + wp.tid()
    i = grid.sorted_ids[k]
    if refit == 1:
        if wp.length(x[i] - grid.centres[k]) > grid.margin:
            rebuild[0] = 1
    else:
        grid.centres[k] = x[i]
    write_item(grid, slot(grid, k), x[i], i, x[i], world[i])


@wp.kernel
def _face_gather(
    first: int,
    points: wp.array(dtype=vec3),
    faces: wp.array2d(dtype=int),
    lebesgue: real,
    world: wp.array(dtype=int),
    corners: int,
    refit: int,
    grid: Grid,
    rebuild: wp.array(dtype=wp.int32),
):
    """Each face's record (its box) in its slot, and (corners = 1, tri3) its corners.
    refit = 1: as _gather, for the faces' centres."""
    k = first + wp.tid()
    i = grid.sorted_ids[k]
    c, r, lo, hi = face_bounds(points, faces, i, lebesgue)
    q = slot(grid, k)
    if corners == 1:  # before any other store: the compiler reuses face_bounds' loads
        grid.corners[q, 0] = points[faces[i, 0]]
        grid.corners[q, 1] = points[faces[i, 1]]
        grid.corners[q, 2] = points[faces[i, 2]]
    if refit == 1:
        if wp.length(c - grid.centres[k]) > grid.margin:
            rebuild[0] = 1
    else:
        grid.centres[k] = c
    write_item(grid, q, lo, i, hi, world[i])


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
    """Self-contact: each item's normal box (lo, hi by item id) in its slot."""
    k = wp.tid()
    i = grid.sorted_ids[k]
    b = NBox()
    b.lo = lo[i]
    b.hi = hi[i]
    grid.nitems[slot(grid, k)] = b


# The grouping. The items in key order are the leaves of a binary radix tree (Karras 2012):
# the node over a run of items is the longest key prefix they share, and the split between
# neighbours p and p + 1 is the length of theirs (`_split`). A group is a largest node of at
# most W items: a Morton-aligned cluster, which a run of W items in key order is not when it
# straddles two cells (a row of a stretched zone and the next, a dense patch and the sparse
# plate after it). Pair p | p + 1 ends a group when the node over it, the run of pairs around
# it with splits at least its own, holds more than W items: looked up within W pairs each
# side. Each group takes W slots (the empty ones lo > hi), and the groups of level k are the
# entries of level k + 1 with the splits between them that ended them: the same rule builds
# every level. On a graded master this keeps each box as tight as its items (closest-node
# scan at 2^16 on fine_patch: 37 -> 1 leaves a slave); a level whose groups would not fit its
# capacity (a mean group below W / 2, seen on no mesh here) takes W consecutive entries a
# group instead, as does every level above the lowest `aligned` ones of a tree too deep for
# a scan's stack.


@wp.func_native("""
#if defined(__CUDA_ARCH__)
return __clzll(x);
#else
return x == 0 ? 64 : __builtin_clzll((unsigned long long)x);
#endif
""")
def _clz64(x: wp.int64) -> int: ...


@wp.func_native("""
#if defined(__CUDA_ARCH__)
return __clz(x);
#else
return x == 0 ? 32 : __builtin_clz((unsigned int)x);
#endif
""")
def _clz32(x: int) -> int: ...


@wp.kernel
def _splits(grid: Grid):
    """The split of each pair of neighbours in key order; equal keys split by their
    positions', so that a run of equal keys still forms groups of W."""
    p = wp.tid()
    if p + 1 < grid.n:
        x = grid.keys[p] ^ grid.keys[p + 1]
        d = _clz64(x)
        if x == wp.int64(0):
            d = 64 + _clz32(p ^ (p + 1))
        grid.split[p] = d


@wp.kernel
def _ends(first: int, grid: Grid, k: int, src: int):
    """ends[e] = 1 where entry e of level k ends a group (the last entry always)."""
    e = first + wp.tid()
    m = grid.counts[k]
    end = int(0)
    if e == m - 1:
        end = 1
    elif e < m - 1:
        d = grid.split[src + e]
        left = int(0)
        right = int(0)
        for t in range(1, W):
            if left == t - 1 and e - t >= 0:
                if grid.split[src + e - t] >= d:
                    left = t
            if right == t - 1 and e + t < m - 1:
                if grid.split[src + e + t] >= d:
                    right = t
        end = int(left + right + 2 > W)
    grid.ends[e] = end


@wp.func
def _empty_slot(grid: Grid, k: int, q: int):
    """Slot q of level k (0: an item slot) left empty: lo > hi, no item, no world."""
    lo = vec3(real(1.0e30))
    hi = vec3(real(-1.0e30))
    if k == 0:
        write_item(grid, q, lo, -1, hi, -2)
        if grid.normals == 1:
            grid.nitems[q] = _empty_nbox()
    else:
        box = Box()
        box.lo = lo
        box.hi = hi
        box.first = -1
        box.world = -2
        write_box(grid, grid.offsets[k] + q, box)
        if grid.normals == 1:
            grid.nboxes[grid.offsets[k] + q] = _empty_nbox()


@wp.kernel
def _place(first: int, grid: Grid, k: int, src: int, dst: int):
    """Whether level k groups by the rule (its groups fit), the next level's entry count, each
    entry's slot in level k (a group's last entry empties the slots after it), and the splits
    between the next level's entries."""
    e = first + wp.tid()
    m = grid.counts[k]
    if m == 0:  # no items: one empty group
        if e == 0:
            grid.aligned[k] = 0
            grid.counts[k + 1] = 1
            for q in range(W):
                _empty_slot(grid, k, q)
        return
    groups = grid.group[m - 1] + 1
    aligned = int(groups <= grid.capacity[k])
    if e == 0:
        grid.aligned[k] = aligned
        if aligned == 0:
            groups = (m + W - 1) // W
        grid.counts[k + 1] = groups
    if e >= m:
        return
    g = e // W
    pos = e - W * g
    last = int(pos == W - 1 or e == m - 1)
    if aligned == 1:
        # A group holds at most W entries: its start is within W - 1 before e.
        g = grid.group[e]
        pos = int(0)
        walk = int(1)
        while walk == 1:  # (Warp evaluates every operand of `and`: no read before 0)
            walk = 0
            if pos < e and pos < W - 1:
                if grid.ends[e - pos - 1] == 0:
                    pos += 1
                    walk = 1
        last = grid.ends[e]
    grid.slots[grid.slot_offsets[k] + e] = W * g + pos
    if last == 1:
        for q in range(pos + 1, W):
            _empty_slot(grid, k, W * g + q)
        if e < m - 1:
            grid.split[dst + g] = grid.split[src + e]


@wp.kernel
def _root(grid: Grid):
    k = int(1)
    while k < grid.top and grid.counts[k] > 1:
        k += 1
    grid.root[0] = k


@wp.func
def _worlds(w: int, c: int):
    """The world of a slot's items so far (w: -2 none yet, -1 several) and a child's (c)."""
    if c == -2 or w == c:
        return w
    if w == -2:
        return c
    return -1


@wp.kernel
def _reduce(first: int, grid: Grid, k: int):
    """Level k >= 1: each entry's box over its group of W slots in level k - 1, into its
    slot, and that group's parent slot."""
    e = first + wp.tid()
    if e >= grid.counts[k]:
        return
    box = Box()
    box.lo = vec3(real(1.0e30))
    box.hi = vec3(real(-1.0e30))
    box.first = W * e
    box.world = -2
    nb = _empty_nbox()
    need = int(0)
    for c in range(W):
        q = W * e + c
        if k == 1:
            box.lo = wp.min(box.lo, item_lo(grid, q))
            box.hi = wp.max(box.hi, item_hi(grid, q))
            box.world = _worlds(box.world, item_world(grid, q))
            if grid.normals == 1:
                nb = _nbox_union(nb, grid.nitems[q])
        else:
            b = entry(grid, k - 1, q)
            need += int(b.world != -2)
            box.lo = wp.min(box.lo, b.lo)
            box.hi = wp.max(box.hi, b.hi)
            box.world = _worlds(box.world, b.world)
            if grid.normals == 1:
                nb = _nbox_union(nb, grid.nboxes[grid.offsets[k - 1] + q])
    j = grid.slots[grid.slot_offsets[k] + e]
    write_box(grid, grid.offsets[k] + j, box)
    if grid.normals == 1:
        grid.nboxes[grid.offsets[k] + j] = nb
    if k >= 2:
        grid.up[grid.offsets[k - 1] // W + e] = j
        grid.need[grid.offsets[k - 1] // W + e] = need


#: Items a thread of the prefix sum adds up in order.
SCAN_CHUNK = 128


@wp.kernel
def _chunk_sums(a: wp.array(dtype=int), n: int, sums: wp.array(dtype=int)):
    t = wp.tid()
    total = int(0)
    for i in range(t * SCAN_CHUNK, wp.min(t * SCAN_CHUNK + SCAN_CHUNK, n)):
        total += a[i]
    sums[t] = total


@wp.kernel
def _chunk_scan(
    a: wp.array(dtype=int),
    n: int,
    offsets: wp.array(dtype=int),
    alone: int,
    out: wp.array(dtype=int),
):
    """Chunk t's exclusive prefix sum from offsets[t] (alone = 1: the only chunk, from 0)."""
    t = wp.tid()
    total = int(0)
    if alone == 0:
        total = offsets[t]
    for i in range(t * SCAN_CHUNK, wp.min(t * SCAN_CHUNK + SCAN_CHUNK, n)):
        v = a[i]
        out[i] = total
        total += v


def exclusive_scan(a, out, n: int, scratch, device):
    """out[:n] = the exclusive prefix sum of a[:n], chunk by chunk (launches only, scratch
    [scan_scratch(n)]): Warp's array_scan may allocate, which a conditional graph node (a
    rebuild inside detect's graph) cannot."""
    t = -(-n // SCAN_CHUNK)
    if t <= 1:
        wp.launch(_chunk_scan, 1, inputs=[a, n, scratch, 1, out], device=device)
        return
    sums, offsets, rest = scratch[:t], scratch[t : 2 * t], scratch[2 * t :]
    wp.launch(_chunk_sums, t, inputs=[a, n, sums], device=device)
    exclusive_scan(sums, offsets, t, rest, device)
    wp.launch(_chunk_scan, t, inputs=[a, n, offsets, 0, out], device=device)


def scan_scratch(n: int) -> int:
    """The scratch `exclusive_scan` of n items needs."""
    t = -(-n // SCAN_CHUNK)
    return 1 if t <= 1 else 2 * t + scan_scratch(t)


class Layout(NamedTuple):
    """A tree's allocation: per level k, the most entries it holds (entries[0]: the items) and
    its slots (slots[k] = W x the most groups; slots[0]: the item slots), and which levels
    may group by the rule."""

    entries: tuple
    slots: tuple
    aligned: tuple

    @property
    def top(self):
        return len(self.entries) - 1


#: Room for this many times the groups a level held when the plan measured it.
GROWTH = 1.25


def layout(n: int, means=()) -> Layout:
    """The allocation for n items. Level k may group by the rule with room for its measured
    mean group size (means[k], see `measure`) divided by GROWTH, or W / 2 where not measured;
    a level whose mean is below 2 takes W consecutive entries a group, as do the levels above
    the lowest ones that keep the root within MAX_LEVELS (the scan's stack)."""
    for n_aligned in range(MAX_LEVELS, -1, -1):
        entries, slots, aligned = [max(n, 1)], [], []
        while True:
            k = len(slots)
            mean = min(means[k] / GROWTH, W) if k < len(means) else W / 2
            rule = k < n_aligned and entries[-1] > W and mean >= 2
            groups = int(np.ceil(entries[-1] / (mean if rule else W)))
            slots.append(W * groups)
            aligned.append(int(rule))
            if entries[-1] == 1 and k >= 1:
                break  # the root's level
            entries.append(groups)
        if len(entries) - 1 <= MAX_LEVELS:
            break
    else:
        raise ValueError(f"{n} items need more than {MAX_LEVELS} tree levels")
    return Layout(tuple(entries), tuple(slots), tuple(aligned))


def _group(grid: Grid, k: int, m: int, device):
    """Level k's groups (capacity m entries): the next level's count and splits, and the
    level's slots."""
    half = grid.ends.shape[0]
    src, dst = half * (k % 2), half * ((k + 1) % 2)
    launch(_ends, m, [0, grid, k, src], [], device, first=0)
    exclusive_scan(grid.ends, grid.group, m, grid.scratch, device)
    launch(_place, m, [0, grid, k, src, dst], [], device, first=0)


def measure(grid: Grid, n: int, device) -> list:
    """The mean group size of the items by the rule, [] for W items or fewer (from the keys
    the grid holds sorted: a plan's, to size the tree's item slots; one read)."""
    if n <= W:
        return []
    wp.launch(_splits, n - 1, inputs=[grid], device=device)
    launch(_ends, n, [0, grid, 0, 0], [], device, first=0)
    exclusive_scan(grid.ends, grid.group, n, grid.scratch, device)
    return [n / (int(grid.group[n - 1 : n].numpy()[0]) + 1)]


def arrange(grid: Grid, n: int, lay: Layout, device):
    """The slots of every level from the items' keys, sorted (launches only: capturable); the
    slots no entry takes emptied, for the items and `fill` to write theirs."""
    wp.launch(_splits, max(n - 1, 1), inputs=[grid], device=device)
    for k in range(lay.top + 1):
        _group(grid, k, lay.entries[k], device)
    wp.launch(_root, 1, inputs=[grid], device=device)


def fill(grid: Grid, lay: Layout, device):
    """Every level's boxes from the item slots: one launch a level, leaves first."""
    for k in range(1, lay.top + 1):
        launch(_reduce, lay.entries[k], [0, grid, k], [], device, first=0)


def _sort(grid: Grid, n: int, world_bits: int):
    wp.utils.radix_sort_pairs(
        grid.keys, grid.sorted_ids, n, end_bit=3 * int(grid.bits) + world_bits
    )


def _normals(grid: Grid, n: int, normals, device):
    if normals is not None:
        wp.launch(_gather_normals, n, inputs=[grid, *normals], device=device)


def build(
    grid: Grid, lay: Layout, x, ids, world, n: int, device, rebuild, world_bits, normals=None
):
    """Fill `grid` with the points x[ids[:n]] (launches only: capturable). normals
    (self-contact): the items' normal boxes (lo, hi) by item id."""
    launch(_keys, n, [0, x, ids, world, grid], [], device, first=0)
    _sort(grid, n, world_bits)
    place(grid, lay, x, world, n, device, rebuild, normals)


def place(grid: Grid, lay: Layout, x, world, n: int, device, rebuild, normals=None):
    """`build` after the sort (the keys sorted in the grid)."""
    arrange(grid, n, lay, device)
    launch(_gather, n, [0, x, world, 0, grid, rebuild], [], device, first=0)
    _normals(grid, n, normals, device)
    fill(grid, lay, device)


def build_faces(
    grid: Grid,
    lay: Layout,
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
    corners by slot. normals: as `build`'s."""
    n = faces.shape[0]
    launch(_face_keys, n, [0, points, faces, real(lebesgue), world, grid], [], device, first=0)
    _sort(grid, n, world_bits)
    place_faces(grid, lay, points, faces, lebesgue, world, device, corners, rebuild, normals)


def place_faces(
    grid: Grid, lay: Layout, points, faces, lebesgue, world, device, corners, rebuild, normals=None
):
    """`build_faces` after the sort."""
    n = faces.shape[0]
    arrange(grid, n, lay, device)
    args = [0, points, faces, real(lebesgue), world, int(corners), 0, grid, rebuild]
    launch(_face_gather, n, args, [], device, first=0)
    _normals(grid, n, normals, device)
    fill(grid, lay, device)


def measure_nodes(grid: Grid, x, ids, world, n: int, device, world_bits: int):
    """`measure` on the points x[ids[:n]] (a plan's, before `allot`)."""
    launch(_keys, n, [0, x, ids, world, grid], [], device, first=0)
    _sort(grid, n, world_bits)
    return measure(grid, n, device)


def measure_faces(grid: Grid, points, faces, lebesgue: float, world, device, world_bits: int):
    """`measure` on the faces (a plan's, before `allot`)."""
    n = faces.shape[0]
    launch(_face_keys, n, [0, points, faces, real(lebesgue), world, grid], [], device, first=0)
    _sort(grid, n, world_bits)
    return measure(grid, n, device)


# A refit: the records again in the previous build's slots, raising rebuild[0] where an
# item left the margin, and every level's boxes; a build follows when raised (the caller's
# choice on the device: wp.capture_if).
@wp.kernel
def _refit_up(grid: Grid):
    """Every level's boxes over the item slots in one launch, as Karras refits a binary tree:
    thread e makes entry e of level 1 and goes up; the last slot of a group to arrive
    (counted in grid.arrived, `_arrive`) makes the parent's box from its siblings' (read
    through L2) and resets the count for the next launch, the others stop. The same boxes
    as `fill`'s launch a level (tested), without `fill`'s launches (a dozen a tree)."""
    e = wp.tid()
    if e >= grid.counts[1]:
        return
    box = Box()
    box.lo = vec3(real(1.0e30))
    box.hi = vec3(real(-1.0e30))
    box.first = W * e
    box.world = -2
    nb = _empty_nbox()
    for c in range(W):
        q = W * e + c
        box.lo = wp.min(box.lo, item_lo(grid, q))
        box.hi = wp.max(box.hi, item_hi(grid, q))
        box.world = _worlds(box.world, item_world(grid, q))
        if grid.normals == 1:
            nb = _nbox_union(nb, grid.nitems[q])
    k = int(1)
    j = grid.slots[grid.slot_offsets[1] + e]
    top = grid.root[0]
    while k <= top:
        key = grid.offsets[k] + j
        write_box(grid, key, box)
        if grid.normals == 1:
            grid.nboxes[key] = nb
        if k == top:
            return
        g = key // W  # this slot's group (offsets are multiples of W)
        if _arrive(grid.arrived, g) < grid.need[g] - 1:
            return  # a sibling yet to arrive goes on
        grid.arrived[g] = 0
        box.lo = vec3(real(1.0e30))
        box.hi = vec3(real(-1.0e30))
        box.first = W * (j // W)
        box.world = -2
        nb = _empty_nbox()
        for c in range(W):
            box.lo = wp.min(box.lo, _box_half_cg(grid.boxes, W * g + c, 0))
            box.hi = wp.max(box.hi, _box_half_cg(grid.boxes, W * g + c, 1))
            box.world = _worlds(box.world, _box_world_cg(grid.boxes, W * g + c))
            if grid.normals == 1:
                nb.lo = wp.min(nb.lo, _nbox_half_cg(grid.nboxes, W * g + c, 0))
                nb.hi = wp.max(nb.hi, _nbox_half_cg(grid.nboxes, W * g + c, 1))
        j = grid.up[g]
        k += 1


# A refit's launches take `cmds`, a plan's recorded commands: on a GPU outside a graph (a
# first call, buffers new to the plan) they replay them rather than pack every argument again
# (one H200, medians of 8 plans, with the master's localisation: a call on new buffers
# ball_block_300 0.65 -> 0.36 ms, ball_block_1000 0.83 -> 0.56, tyre 0.73 -> 0.63; steady
# 0.28, 0.48, 0.53 ms).


def refit(
    grid: Grid, lay: Layout, x, world, device, rebuild, normals=None, cmds=None, record_only=False
):
    args = [0, x, world, 1, grid, rebuild]
    gpu = _on_gpu(cmds, device)
    launch(_gather, grid.n, args, [], device, first=0, cmds=gpu, record_only=record_only)
    _refit_boxes(grid, lay, normals, device, cmds, "nodes", record_only)


def refit_faces(
    grid: Grid,
    lay: Layout,
    points,
    faces,
    lebesgue,
    world,
    device,
    corners,
    rebuild,
    normals=None,
    cmds=None,
    record_only=False,
):
    args = [0, points, faces, real(lebesgue), world, int(corners), 1, grid, rebuild]
    gpu = _on_gpu(cmds, device)
    n = faces.shape[0]
    launch(_face_gather, n, args, [], device, first=0, cmds=gpu, record_only=record_only)
    _refit_boxes(grid, lay, normals, device, cmds, "faces", record_only)


def _on_gpu(cmds, device):
    """cmds on a GPU; none on the CPU, whose launches run in parts (`launch`)."""
    return cmds if wp.get_device(device).is_cuda else None


def _refit_boxes(grid: Grid, lay: Layout, normals, device, cmds=None, tree=None, record_only=False):
    if normals is not None:
        args = [grid, *normals]
        key = (tree, _gather_normals)
        replayed(cmds, key, _gather_normals, grid.n, args, device, record_only)
    refit_up(grid, lay, device, cmds, tree, record_only)


def refit_up(grid: Grid, lay: Layout, device, cmds=None, tree=None, record_only=False):
    """Every level's boxes from the item slots, in the order of the last build."""
    # (One thread on the CPU, whose Warp atomics are plain additions: not in parts.)
    args = [grid]
    replayed(cmds, (tree, _refit_up), _refit_up, lay.entries[1], args, device, record_only)


def new_grid(
    n: int,
    corner,
    extent: float,
    device,
    margin: float,
    n_worlds: int = 1,
    normals=False,
    sides: float = 0.0,
):
    """A tree for n items in the cube of side `extent` at `corner` (local frame), with
    `margin` the distance an item may move before a refit asks for a build; normals: with
    normal boxes (self-contact); sides > 0 (faces): the keys sort each Morton cell of at
    least that side by the class of the face's normal (`_side_key`). Its levels: `allot`.
    Returns (grid, world bits). (Arrays that a build writes before any read are left unset:
    on the CPU, zeroing them cost more than the build.)"""
    world_bits = max(int(n_worlds - 1).bit_length(), 0)
    g = Grid()
    g.n = max(n, 0)
    m = max(n, 1)
    counts = np.zeros(MAX_LEVELS * 2 + 2, np.int32)
    counts[0] = n
    g.counts = wp.array(counts, dtype=int, device=device)
    g.aligned = wp.zeros_like(g.counts)
    g.capacity = wp.zeros_like(g.counts)
    g.slot_offsets = wp.zeros_like(g.counts)
    g.slots = wp.empty(m, dtype=int, device=device)
    g.split = wp.empty(2 * m, dtype=int, device=device)
    g.ends = wp.empty(m, dtype=int, device=device)
    g.group = wp.empty(m, dtype=int, device=device)
    g.scratch = wp.empty(scan_scratch(m), dtype=int, device=device)
    g.bits = min(21, (63 - world_bits) // 3)
    g.corner = vec3(*[float(v) for v in corner])
    g.quantum = real(max(float(extent), 1e-30) / (1 << g.bits))
    g.margin = real(margin)
    g.sorted_ids = wp.empty(2 * m, dtype=int, device=device)
    g.keys = wp.empty(2 * m, dtype=wp.int64, device=device)
    g.centres = wp.full(m, vec3(1.0e30), dtype=vec3, device=device)
    g.normals = int(normals)
    g.sides = 0
    if sides > 0:
        # (below the top level: classes above every cell split the tree into six that a
        # slave walks side by side, the crumpled sheet's walk twice as long)
        level = int(np.ceil(np.log2(max(sides / float(g.quantum), 2.0))))
        g.sides = min(level, g.bits - 1)
    return g, world_bits


def allot(g: Grid, n: int, device, means=(), corners=False) -> Layout:
    """Give `g` its levels for n items (`layout`: means, the mean group size of each level,
    `measure`'s, or none); corners (tri3 faces): room for the faces' corners by slot."""
    lay = layout(n, means)
    g.top = lay.top
    g.root = wp.full(1, lay.top, dtype=int, device=device)
    offsets = np.zeros(MAX_LEVELS * 2 + 2, np.int32)
    slot_offsets = np.zeros(MAX_LEVELS * 2 + 2, np.int32)
    capacity = np.zeros(MAX_LEVELS * 2 + 2, np.int32)
    total = 0
    for k in range(1, lay.top + 1):
        offsets[k] = total
        total += lay.slots[k]
    for k in range(lay.top + 1):
        slot_offsets[k + 1] = slot_offsets[k] + lay.entries[k]
        capacity[k] = lay.slots[k] // W if lay.aligned[k] else 0
    g.offsets = wp.array(offsets, dtype=int, device=device)
    g.slot_offsets = wp.array(slot_offsets, dtype=int, device=device)
    g.capacity = wp.array(capacity, dtype=int, device=device)
    g.slots = wp.empty(int(slot_offsets[lay.top + 1]), dtype=int, device=device)
    g.up = wp.empty(max(total // W, 1), dtype=int, device=device)
    g.need = wp.empty(max(total // W, 1), dtype=int, device=device)
    g.arrived = wp.zeros(max(total // W, 1), dtype=int, device=device)
    g.boxes = wp.empty(total, dtype=Box, device=device)
    g.items = wp.empty(lay.slots[0], dtype=Item, device=device)
    g.corners = wp.empty((lay.slots[0] if corners else 1, 3), dtype=vec3, device=device)
    g.nboxes = wp.empty(total if g.normals else 1, dtype=NBox, device=device)
    g.nitems = wp.empty(lay.slots[0] if g.normals else 1, dtype=NBox, device=device)
    return lay


@wp.func
def _spread10(v: int):
    """v clamped to 10 bits, moved to every third bit (the slaves' 30-bit Morton codes)."""
    return spread21(wp.int64(wp.clamp(v, 0, 1023)))


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
    keys[i] = int(_spread10(cx) | (_spread10(cy) << wp.int64(1)) | (_spread10(cz) << wp.int64(2)))
    order[i] = i


def spatial_order(x, origin, quantum, keys, order, n: int, device):
    """order[:n]: the rows of x in Morton order of cells of size `quantum` (1024 per axis over
    the plan's box), so that the threads of a GPU warp work on neighbouring slaves and walk the
    same tree entries (launches only: capturable; keys and order hold 2n for the radix sort)."""
    wp.launch(_morton, n, inputs=[x, origin, quantum, keys, order], device=device)
    wp.utils.radix_sort_pairs(keys, order, n, end_bit=30)
