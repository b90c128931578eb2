"""Stage 2 in Warp: one hashed key per item (cell and world), a radix sort of the keys' table
bits, and the range of every table slot from the sorted keys (adjacent differences) with the
box around its items. No dense cell array. An item is a box (a point for a node) with its id
and world, in key order. A refit computes the items and slot boxes again in the previous
build's order, and says when an item moved farther than its cell allows."""

from __future__ import annotations

import warp as wp

from ._prepare import face_bounds
from ._real import real, vec3

# Forward only, no loop unrolling: the 27-cell stencil unrolled would copy the whole
# projection 27 times into the kernel (minutes of CUDA compilation for no speed).
wp.set_module_options({"enable_backward": False, "max_unroll": 1})


@wp.struct
class Slot:
    """One table slot: its items' range in key order and the box around their balls (a scan
    skips a cell whose items are all out of reach without reading them: on a surface most of
    a cell is empty space). One 32-byte record, so one memory transaction reads it."""

    lo: vec3
    begin: int
    hi: vec3
    end: int


@wp.struct
class Item:
    """One item in key order: the box around it (lo = hi for a node), its id and world. One
    32-byte record in float32: a scan's one read per item. A face's box rejects far more
    faces of a surface than its ball (which bounds the face's extent in every direction).
    `id` repeats sorted_ids[k] to fill the first half; the scans read sorted_ids, only for
    the items they keep."""

    lo: vec3
    id: int
    hi: vec3
    world: int


@wp.struct
class Grid:
    cell: real
    # How far a node may be from the cell it was keyed in (a refit's allowance, which the
    # closest-node scan adds to its reach when it picks cells); 0 for faces, whose allowance
    # is in r_cap.
    margin: real
    table: int  # slots, a power of two
    sorted_ids: wp.array(dtype=int)  # item ids in key order (first n of 2n: radix scratch)
    keys: wp.array(dtype=int)
    # [table]; a slot no item of the current build hashes to has begin = end (its box is stale
    # and unread).
    slots: wp.array(dtype=Slot)
    # In key order, so the scans read each cell's items contiguously.
    items: wp.array(dtype=Item)
    # tri3 face grids: the three corners of each face in key order (the projection's only
    # data, read contiguously); [1, 3] otherwise.
    corners: wp.array2d(dtype=vec3)
    # Each item's centre (a node: its position) when its key was computed, in key order (a
    # refit keeps the keys while the items stay near them); 1e30 before the first build.
    centres: wp.array(dtype=vec3)


# Item and Slot are records of two 16-byte halves (a vec3 and an int each). Warp moves a struct
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
    def _slot_vec(a: wp.array(dtype=Slot), k: int, h: int) -> vec3: ...

    @wp.func_native(_HALF_INT)
    def _slot_int(a: wp.array(dtype=Slot), k: int, h: int) -> int: ...

    @wp.func_native(_STORE)
    def _store_slot(a: wp.array(dtype=Slot), k: int, lo: vec3, i: int, hi: vec3, j: int): ...

    @wp.func
    def item_lo(grid: Grid, k: int):
        return _item_vec(grid.items, k, 0)

    @wp.func
    def item_hi(grid: Grid, k: int):
        return _item_vec(grid.items, k, 1)

    @wp.func
    def read_slot(grid: Grid, key: int):
        slot = Slot()
        slot.lo = _slot_vec(grid.slots, key, 0)
        slot.hi = _slot_vec(grid.slots, key, 1)
        slot.begin = _slot_int(grid.slots, key, 0)
        slot.end = _slot_int(grid.slots, key, 1)
        return slot

    @wp.func
    def write_item(grid: Grid, k: int, lo: vec3, i: int, hi: vec3, world: int):
        _store_item(grid.items, k, lo, i, hi, world)

    @wp.func
    def write_slot(grid: Grid, key: int, slot: Slot):
        _store_slot(grid.slots, key, slot.lo, slot.begin, slot.hi, slot.end)
else:
    @wp.func
    def item_lo(grid: Grid, k: int):
        return grid.items[k].lo

    @wp.func
    def item_hi(grid: Grid, k: int):
        return grid.items[k].hi

    @wp.func
    def read_slot(grid: Grid, key: int):
        return grid.slots[key]

    @wp.func
    def write_item(grid: Grid, k: int, lo: vec3, i: int, hi: vec3, world: int):
        item = Item()
        item.lo = lo
        item.id = i
        item.hi = hi
        item.world = world
        grid.items[k] = item

    @wp.func
    def write_slot(grid: Grid, key: int, slot: Slot):
        grid.slots[key] = slot


@wp.func
def cell_of(x: vec3, cell: real):
    return wp.vec3i(int(wp.floor(x[0] / cell)), int(wp.floor(x[1] / cell)),
                    int(wp.floor(x[2] / cell)))


@wp.func
def cell_key(c: wp.vec3i, world: int, table: int):
    # Large odd multipliers (Teschner et al. 2003) in wrap-around unsigned arithmetic.
    h = (wp.uint32(c[0]) * wp.uint32(73856093)) ^ (wp.uint32(c[1]) * wp.uint32(19349663))
    h = h ^ (wp.uint32(c[2]) * wp.uint32(83492791)) ^ (wp.uint32(world) * wp.uint32(16777619))
    return int(h & wp.uint32(table - 1))


@wp.kernel
def _keys(x: wp.array(dtype=vec3), ids: wp.array(dtype=int), world: wp.array(dtype=int),
          grid: Grid):
    k = wp.tid()
    i = ids[k]
    grid.keys[k] = cell_key(cell_of(x[i], grid.cell), world[i], grid.table)
    grid.sorted_ids[k] = i


@wp.kernel
def _clear(grid: Grid):
    """Empty the slots the previous build filled (the keys still hold its items)."""
    k = wp.tid()
    key = grid.keys[k]
    if k == 0 or grid.keys[k - 1] != key:
        write_slot(grid, key, Slot())


@wp.kernel
def _face_keys(points: wp.array(dtype=vec3), faces: wp.array2d(dtype=int), lebesgue: real,
               r_cap: real, world: wp.array(dtype=int), grid: Grid,
               overflow: wp.array(dtype=int)):
    """The face grid's keys (the cells of the faces' centres); a face whose radius outgrew
    the one the grid was planned for raises `overflow`."""
    f = wp.tid()
    c, r, lo, hi = face_bounds(points, faces, f, lebesgue)
    grid.keys[f] = cell_key(cell_of(c, grid.cell), world[f], grid.table)
    grid.sorted_ids[f] = f
    if r > r_cap:
        wp.atomic_max(overflow, 0, 1)


@wp.kernel
def _gather(x: wp.array(dtype=vec3), world: wp.array(dtype=int), refit: int, grid: Grid,
            rebuild: wp.array(dtype=wp.int32)):
    """Each node's record in key order (a point: lo = hi). refit = 1: the keys are the
    previous build's; rebuild[0] is raised unless every node is within grid.margin of where it
    was keyed."""
    k = wp.tid()
    i = grid.sorted_ids[k]
    if refit == 1:
        # (a thousandth under the margin the scan adds: room for rounding)
        if wp.length(x[i] - grid.centres[k]) > real(0.999) * grid.margin:
            rebuild[0] = 1
    else:
        grid.centres[k] = x[i]
    write_item(grid, k, x[i], i, x[i], world[i])


@wp.kernel
def _face_gather(points: wp.array(dtype=vec3), faces: wp.array2d(dtype=int), lebesgue: real,
                 world: wp.array(dtype=int), corners: int, refit: int, r_cap: real, grid: Grid,
                 rebuild: wp.array(dtype=wp.int32)):
    """Each face's record in key order, and (corners = 1, tri3) its corners. refit = 1: the
    keys are the previous build's; rebuild[0] is raised unless every face still lies within
    r_cap of the centre it was keyed by (the scans' assumption, which a build checks as
    radius <= r_cap)."""
    k = wp.tid()
    i = grid.sorted_ids[k]
    c, r, lo, hi = face_bounds(points, faces, i, lebesgue)
    if refit == 1:
        if r + wp.length(c - grid.centres[k]) > r_cap:
            rebuild[0] = 1
    else:
        grid.centres[k] = c
    write_item(grid, k, lo, i, hi, world[i])
    if corners == 1:
        for j in range(3):
            grid.corners[k, j] = points[faces[i, j]]


@wp.kernel
def _fill_slots(n: int, grid: Grid):
    """The first item of each slot walks the slot's items (about ten, contiguous in key order)
    for its range and box."""
    k = wp.tid()
    key = grid.keys[k]
    if k == 0 or grid.keys[k - 1] != key:
        slot = Slot()
        slot.lo = item_lo(grid, k)
        slot.hi = item_hi(grid, k)
        slot.begin = k
        j = k + 1
        while j < n and grid.keys[j] == key:
            slot.lo = wp.min(slot.lo, item_lo(grid, j))
            slot.hi = wp.max(slot.hi, item_hi(grid, j))
            j += 1
        slot.end = j
        write_slot(grid, key, slot)


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
def box_gap_sq(s: vec3, lo: vec3, hi: vec3):
    """The squared distance from s to the box [lo, hi]."""
    return wp.length_sq(wp.max(wp.max(lo - s, s - hi), vec3(0.0)))


@wp.func
def box_near(s: vec3, slot: Slot, reach: real):
    """Whether the box of a slot's items is within reach of s."""
    return box_gap_sq(s, slot.lo, slot.hi) <= reach * reach


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
def _morton(x: wp.array(dtype=vec3), origin: vec3, quantum: real, keys: wp.array(dtype=int),
            order: wp.array(dtype=int)):
    i = wp.tid()
    c = cell_of(x[i] - origin, quantum)
    keys[i] = int(_spread(c[0]) | (_spread(c[1]) << wp.uint32(1)) | (_spread(c[2]) << wp.uint32(2)))
    order[i] = i


def spatial_order(x, origin, quantum, keys, order, n: int, device):
    """order[:n]: the rows of x in Morton order of cells of size `quantum` (1024 per axis over
    the plan's box), so that the threads of a GPU warp work on neighbouring slaves and scan the
    same grid cells (launches only: capturable; keys and order hold 2n for the radix sort)."""
    wp.launch(_morton, n, inputs=[x, origin, quantum, keys, order], device=device)
    wp.utils.radix_sort_pairs(keys, order, n, end_bit=30)


def _sort(grid: Grid, n: int):
    # Only the key bits the table uses (fewer radix passes).
    wp.utils.radix_sort_pairs(grid.keys, grid.sorted_ids, n,
                              end_bit=(grid.table - 1).bit_length())


def build(grid: Grid, x, ids, world, n: int, device, rebuild):
    """Fill `grid` with the points x[ids[:n]] (launches only: capturable)."""
    wp.launch(_clear, n, inputs=[grid], device=device)
    wp.launch(_keys, n, inputs=[x, ids, world, grid], device=device)
    _sort(grid, n)
    wp.launch(_gather, n, inputs=[x, world, 0, grid, rebuild], device=device)
    fill(grid, n, device)


def build_faces(grid: Grid, points, faces, lebesgue: float, r_cap: float, world, overflow,
                device, corners: bool, rebuild):
    """Fill `grid` with the faces (launches only: capturable); corners (tri3): also their
    corners in key order. overflow[0] is raised when a face's radius exceeds r_cap."""
    n = faces.shape[0]
    wp.launch(_clear, n, inputs=[grid], device=device)
    wp.launch(_face_keys, n, inputs=[points, faces, real(lebesgue), real(r_cap), world, grid,
                                     overflow], device=device)
    _sort(grid, n)
    wp.launch(_face_gather, n, inputs=[points, faces, real(lebesgue), world, int(corners), 0,
                                       real(r_cap), grid, rebuild], device=device)
    fill(grid, n, device)


# A refit: the records of a grid again in the previous build's key order, raising rebuild[0]
# where an item left the allowance its cell was planned with; then `fill`, or a build when
# raised (the caller's choice on the device: wp.capture_if).
def refit(grid: Grid, x, world, n: int, device, rebuild):
    wp.launch(_gather, n, inputs=[x, world, 1, grid, rebuild], device=device)


def refit_faces(grid: Grid, points, faces, lebesgue: float, r_cap: float, world, device,
                corners: bool, rebuild):
    wp.launch(_face_gather, faces.shape[0], inputs=[points, faces, real(lebesgue), world,
                                                    int(corners), 1, real(r_cap), grid,
                                                    rebuild], device=device)


def fill(grid: Grid, n: int, device):
    """Every slot's range and box from the records in key order."""
    wp.launch(_fill_slots, n, inputs=[n, grid], device=device)


def new_grid(n: int, cell: float, device, margin=0.0, corners=False) -> Grid:
    table = max(64, 1 << int(max(2 * n, 1) - 1).bit_length())
    g = Grid()
    g.cell, g.margin, g.table = real(cell), real(margin), table
    g.sorted_ids = wp.zeros(2 * max(n, 1), dtype=int, device=device)
    g.keys = wp.zeros(2 * max(n, 1), dtype=int, device=device)
    g.slots = wp.zeros(table, dtype=Slot, device=device)
    g.items = wp.zeros(max(n, 1), dtype=Item, device=device)
    g.corners = wp.zeros((max(n, 1) if corners else 1, 3), dtype=vec3, device=device)
    g.centres = wp.full(max(n, 1), vec3(1.0e30), dtype=vec3, device=device)
    return g
