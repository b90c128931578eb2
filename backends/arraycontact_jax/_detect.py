"""Jitted detection: the stages of arraycontact._detect.run_stages on jax.numpy.

Two entry points share the stages:

* `plan` / `detect` (jax-md's allocate / update): `plan` sizes every buffer eagerly from the
  data with a growth factor; `detect(plan, slave_points, master_points)` is jitted with static
  shapes, takes the coordinates as arrays (so a moving or deforming scene never recompiles),
  recomputes the master's geometry from them, and returns a `Contacts` pytree whose counts may
  exceed their capacities (`overflow`). `update_plan` re-plans outside `jit` on overflow.
  Gradients flow to both coordinate arrays (see _gradients).
* `run_one_shot`, behind `arraycontact.detect(backend="jax")`: prepares on the host (box
  intersection, only the nodes and faces that can matter), then grows the capacities and runs
  again until nothing overflows.

The plan fixes the Morton order of the master's nodes and faces (the trees of _grid); each
detect computes the trees' boxes from the current coordinates in that order (a refit: exact
for any motion, less tight as the master deforms, which shows as higher counts; update_plan
orders them again).

`plan(..., search="warp")` (exact mode) runs the discrete search (stages 1-5 without
gradients) as the Warp back end's kernels inside the jitted `detect`, through Warp's JAX FFI
(`wp.jax_callable`, on the device of the JAX arrays; on a GPU a CUDA graph captured by Warp
on staging buffers); the differentiable
outputs are computed from its answer by the same `smooth` as the JAX search's. It has no pair
buffers and nothing to overflow.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

from arraycontact._contacts import Contacts, Counts, Feature, Status, SweptContacts
from arraycontact._detect import (
    Master,
    Scalars,
    Static,
    build_grids,
    check_options,
    master_arrays,
    master_geometry,
    master_topology,
    run_stages,
    scalars,
    self_reach,
)
from arraycontact._elements import get_element
from arraycontact._grid import consecutive, grouping, morton_keys, morton_order
from arraycontact._prepare import Prepared
from arraycontact._surface import Surface, bounds, node_normals, validate_points
from arraycontact._sweep import FEATURE_TOL, T_TOL, feature_of

from . import _grid, _sweep
from ._gradients import MAX_VALENCE, padded_node_faces, smooth

# Capacities are the plan-time counts times this: the candidate faces of a slave grow when
# the slaves come closer to a rough master than they were at plan time.
GROWTH = 1.5
# Candidate faces a slave at least (a slave within reach of a flat triangulated master has
# about 6-12).
MIN_CANDIDATES = 8


#: The programs a plan runs once (the counts), compiled on a GPU at XLA's lowest backend
#: optimisation: there ptxas and LLVM at full optimisation took 27-60 s over the scans of some
#: scenes (the gmsh ball-on-block, run h100-s19) where level 0 takes about a second, and a
#: count's run time does not matter. Not on the CPU: there the count at level 0 ran 3-4x
#: longer (a second plan at 2^17: 0.4 -> 1.5 s) and compiling was not slow. Kept per program
#: and argument types, as jit keeps its own, the newest _ONCE_KEEP of them (a long run of
#: different scenes would otherwise keep every executable).
_ONCE = {}
_ONCE_KEEP = 64
_GPU_ONCE = {"xla_backend_optimization_level": 0}


def once(fn, *args, **static):
    """fn(*args, **static) (a jitted fn, static its static arguments) compiled as above."""
    leaves, tree = jax.tree.flatten(args)
    key = (
        fn,
        tuple(sorted(static.items())),
        tree,
        jax.config.jax_enable_x64,
        tuple((jnp.shape(a), jnp.result_type(a), getattr(a, "sharding", None)) for a in leaves),
    )
    if key not in _ONCE:
        if len(_ONCE) >= _ONCE_KEEP:
            del _ONCE[next(iter(_ONCE))]  # the oldest
        low = fn.lower(*args, **static)
        gpu = jax.devices()[0].platform == "gpu"
        _ONCE[key] = low.compile(_GPU_ONCE if gpu else None)
    return _ONCE[key](*args)


@partial(jax.jit, static_argnames=("st", "capacity"))
def _kernel(sc, m, slave_x, ids=None, *, st, capacity):
    grids = build_grids(jnp, st, m)
    out, counts = run_stages(
        jnp, st, sc, m, grids, slave_x, dict(capacity), search=_grid, slave_ids=ids
    )
    return out, counts


@partial(jax.jit, static_argnames=("st",))
def _count(sc, m, slave_x, ids=None, *, st):
    """The counts that size the capacities, on the device: the most candidate faces of one
    slave (exact mode), or the faces attached to the closest nodes (node mode)."""
    per = _per_slave(sc, m, slave_x, ids, st=st)
    if st.mode == "exact":
        return {"face_candidates": jnp.max(per, initial=0)}
    return {"attached": jnp.sum(per)}


@partial(jax.jit, static_argnames=("st",))
def _per_slave(sc, m, slave_x, ids=None, *, st):
    """Each slave's work (the scans of stages 3-4 with no candidate slots): its candidate
    faces (exact mode), or the faces attached to its closest node (node mode)."""
    grids = build_grids(jnp, st, m)
    own = None if ids is None else (ids, m.node_normals[ids], m.node_normals)
    node, dn, _ = _grid.closest_node(
        jnp,
        grids.node,
        m.nodes_x,
        slave_x,
        d_max=sc.d_max,
        tie=sc.tie,
        slack=sc.slack,
        self_contact=own,
    )
    if st.mode == "exact":
        rho = jnp.minimum(dn, sc.d_max) + sc.slack
        if own is not None:  # as run_stages
            rho = self_reach(jnp, st, sc, m, own, slave_x, node)
        normal = None if own is None else own[1]
        return _grid.candidate_counts(grids.face, slave_x, rho, slack=sc.slack, normal=normal)
    nd = jnp.maximum(node, 0)
    deg = m.nf_offsets[nd + 1] - m.nf_offsets[nd]
    return jnp.where(node >= 0, deg, 0)


def _grown(counts, growth, n_slaves, minimum=None):
    """Capacities from counts, times growth: at least MIN_CANDIDATES candidate faces a slave;
    at least 64 + 2 a slave for the attached faces of node mode (a total, which on a small
    scene a new configuration can double); at least `minimum` (counts) times growth."""
    floor = {"face_candidates": MIN_CANDIDATES}
    cap = {
        k: max(int(np.ceil(int(v) * growth)), floor.get(k, 64 + 2 * n_slaves))
        for k, v in counts.items()
    }
    for k, v in (minimum or {}).items():
        if k in cap:
            cap[k] = max(cap[k], int(np.ceil(v * growth)))
    return cap


def run_one_shot(slave_x, master, prep, st, dtype, slave_ids=None):
    """Plan on the host, run jitted, re-plan and re-run on overflow. Host arrays out.
    slave_ids: the slaves' node ids (self-contact)."""
    x64 = np.dtype(dtype) == np.float64
    with jax.enable_x64(x64):
        m = master_arrays(master, prep, dtype)
        sc = scalars(prep, master, dtype)
        x = (slave_x[prep.slave_rows] - prep.origin).astype(dtype)
        m_dev = jax.tree.map(jnp.asarray, m)
        sc_dev = Scalars(*(jnp.asarray(v, dtype=dtype) for v in sc))
        x_dev = jnp.asarray(x)
        ids = None
        if slave_ids is not None:
            ids = jnp.asarray(slave_ids[prep.slave_rows].astype(np.int32))
        # The counts of these very coordinates: no growth needed (the loop is a safeguard).
        cap = _grown(once(_count, sc_dev, m_dev, x_dev, ids, st=st), 1.0, len(x))
        for _ in range(4):
            out, counts = _kernel(
                sc_dev, m_dev, x_dev, ids, st=st, capacity=tuple(sorted(cap.items()))
            )
            counts = {k: int(v) for k, v in counts.items()}
            over = {k: v for k, v in counts.items() if k in cap and v > cap[k]}
            if not over:
                break
            cap.update(_grown(over, GROWTH, len(x)))
        out = {k: np.asarray(v) for k, v in out.items()}
    d = next(iter(x_dev.devices()))
    return out, counts, cap, f"{d.platform}:{d.id}"


# ---------------------------------------------------------------------------------------------
# plan / detect


@dataclass(frozen=True, eq=False)
class Plan:
    """Buffers and constants of a jitted detection; a pytree (topology arrays are its leaves).

    Build it with `plan`; pass it to `detect`. Everything but `topology` is static."""

    topology: Master  # int32 leaves (the geometry fields are None: computed in detect)
    master: Surface = field(repr=False)  # connectivity, element, plan-time coordinates
    static: Static = None
    capacity: tuple = ()  # sorted (name, capacity) items
    constants: Scalars = None  # d_max, tie band, slack, tolerance (floats)
    origin: tuple = (0.0, 0.0, 0.0)  # local frame of the computation
    dtype: str = "float32"
    n_slaves: int = 0
    growth: float = GROWTH
    search: object = None  # None: the stages in JAX; else the Warp search (_WarpSearch)

    @property
    def d_max(self) -> float:
        return self.constants.d_max


jax.tree_util.register_pytree_node(
    Plan,
    lambda p: (
        (p.topology,),
        (
            p.master,
            p.static,
            p.capacity,
            p.constants,
            p.origin,
            p.dtype,
            p.n_slaves,
            p.growth,
            p.search,
        ),
    ),
    lambda aux, ch: Plan(ch[0], *aux),
)


def plan(
    master,
    slave_points,
    *,
    mode="exact",
    d_max=None,
    displacement=None,
    dtype=None,
    growth=GROWTH,
    minimum=None,
    search="jax",
    self_contact=False,
    mesh=None,
    axis="space",
    margin=None,
) -> Plan:
    """Size every buffer of `detect` from the current coordinates (eager, on the host).

    master: a Surface (its connectivity is fixed for the plan's life; its coordinates are only
    the plan-time configuration). slave_points: [n, 3]. d_max: fixed for the plan (default:
    the seed's rule on the plan-time master). dtype: float32 or float64 (float64 needs
    `jax_enable_x64`); default: JAX's default float. Capacities are the counts found now times
    `growth` (and at least `minimum`, a dict of counts, used when re-planning).
    search: "jax" (the stages in jax.numpy) or "warp" (exact mode: the Warp kernels through
    Warp's JAX FFI on the JAX device, for speed; the same contacts and gradients).
    self_contact: the slaves are the master's own nodes (use `plan_self`).

    mesh: a `jax.sharding.Mesh` with the one axis `axis`: the detection runs over its devices
    (a ShardedPlan, see _shard): the slaves and faces split by recursive coordinate bisection
    weighted by each slave's candidate faces, each device detecting its part's slaves against
    its halo faces; `detect` takes arrays sharded over the axis (or replicated) and gives one
    device's answer row for row, sharded by rows (replicated where the slaves are not a
    multiple of the devices: JAX shards rows only in equal blocks). margin: how far slaves
    and master nodes may move from the plan's configuration, together, before `detect`
    reports the halos' overflow (count `halo_motion`; default (growth - 1)(d_max + largest
    face radius))."""
    if dtype is None:
        dtype = np.float64 if jax.config.jax_enable_x64 else np.float32
    dev_topo = None
    if mesh is None and isinstance(master, Surface) and master.n_faces:
        dev_topo = _device_topology(master)
    if dev_topo is None and isinstance(master, Surface) and master.n_faces:
        master.prepare()  # the host's tables, made at once
    longest = None if dev_topo is None else dev_topo[0].longest_edge
    d_max, dtype = check_options(master, mode, d_max, displacement, dtype, longest)
    if dtype == np.float64 and not jax.config.jax_enable_x64:
        raise ValueError(
            "dtype float64 needs jax_enable_x64 (jax.config.update or jax.enable_x64())"
        )
    if not growth >= 1:
        raise ValueError(f"growth must be >= 1, got {growth}")
    if search not in ("jax", "warp"):
        raise ValueError(f"search must be 'jax' or 'warp', got {search!r}")
    if search == "warp" and mode != "exact":
        raise ValueError("search='warp' implements mode='exact' only")
    slave_x = validate_points(slave_points, "slave_points")
    if master.n_faces == 0:
        raise ValueError("master has no faces")
    if len(slave_x) == 0:
        raise ValueError("slave_points is empty: there is nothing to plan for")
    if mesh is not None:
        from . import _shard

        return _shard.plan(
            master,
            slave_x,
            mesh=mesh,
            axis=axis,
            mode=mode,
            d_max=d_max,
            dtype=dtype,
            growth=growth,
            minimum=minimum,
            search=search,
            self_contact=self_contact,
            margin=margin,
        )
    x_lo, x_hi = bounds(slave_x)
    lo = np.minimum(x_lo, master.node_box[0]) - d_max
    hi = np.maximum(x_hi, master.node_box[1]) + d_max
    # float32 computes in a frame at the scene's corner (DESIGN section 7); float64 globally.
    origin = lo if dtype == np.float32 else np.zeros(3)
    extent = float((hi - lo).max())
    if search == "warp":
        # No Morton orders: the Warp plan orders and groups its own trees, and the JAX ones
        # are never built (CPU, uniform 2^16: the plan 19.6 -> 12.0 ms, two sorts and the
        # faces' balls).
        node_order = np.arange(len(master.nodes))
        face_ids = np.arange(master.n_faces)
        r_max = dev_topo[0].r_max if dev_topo is not None else float(master.face_bounds[1].max())
    elif dev_topo is not None:  # the Morton orders and their sorted keys on the device
        t, wdev = dev_topo
        order = partial(_warp_surface().morton_order, lo=lo, extent=extent, device=wdev)
        node_order, node_keys = order(t.points, t.nodes, t.n_nodes, keys_too=True)
        nf = master.n_faces
        ids = _warp_surface().iota(nf, nf, wdev)
        centres = _warp_surface().face_balls(t, wdev)[0]
        face_ids, face_keys = order(centres, ids, nf, keys_too=True)
        r_max = t.r_max
    else:
        centres, radii = master.face_bounds
        node_order = morton_order(master.points[master.nodes], lo, extent)
        face_ids = morton_order(centres, lo, extent)
        r_max = float(radii.max())
        node_keys = face_keys = None
    node_ids = master.nodes[node_order]
    node_groups, face_groups = consecutive(len(node_ids)), consecutive(len(face_ids))
    if search == "jax":  # the trees' groups, from the keys in the orders found
        if node_keys is None:  # (the device sorted these already: 0.31 s at 2^20, 2-core CPU)
            node_keys = morton_keys(master.points[node_ids], lo, extent)
            face_keys = morton_keys(centres[face_ids], lo, extent)
        node_groups, face_groups = grouping(node_keys), grouping(face_keys)
    prep = Prepared(
        slave_rows=np.arange(len(slave_x)),
        node_ids=node_ids,
        face_ids=face_ids,
        origin=origin,
        d_max=d_max,
        r_max=r_max * growth,
        node_groups=node_groups,
        face_groups=face_groups,
        extent=2 * float(np.abs(np.r_[lo - origin, hi - origin]).max()),
    )
    st = Static.of(master, mode, prep, self_contact)
    sc = scalars(prep, master, dtype, longest)
    if search == "warp":
        # No pair counts to size: only the topology that the smooth outputs read.
        engine = _WarpSearch(
            [warp_plan(master, slave_x, d_max, dtype, growth, origin, self_contact=self_contact)],
            dtype,
            self_contact,
        )
        topo = (
            _topology(master, prep, self_contact)
            if dev_topo is None
            else _device_topology_arrays(master, prep, self_contact, dev_topo)
        )
        return Plan(
            topo,
            master,
            st,
            (),
            sc,
            tuple(float(v) for v in origin),
            np.dtype(dtype).name,
            len(slave_x),
            growth,
            engine,
        )
    sc_dev = Scalars(*(jnp.asarray(v, dtype=dtype) for v in sc))
    ids = jnp.asarray(master.nodes.astype(np.int32)) if self_contact else None
    xs = jnp.asarray((slave_x - origin).astype(dtype))
    if dev_topo is not None:  # the plan-time geometry computed as detect does, on the device
        topo = _device_topology_arrays(master, prep, self_contact, dev_topo)
        nodes_x = jnp.asarray((master.points - origin).astype(dtype))
        bare = topo._replace(slave_nodes=None, node_faces=None)
        counts = once(_count_at, sc_dev, bare, nodes_x, xs, ids, st=st)
    else:
        topo = _topology(master, prep, self_contact)
        counts = once(_count, sc_dev, master_arrays(master, prep, dtype), xs, ids, st=st)
    cap = _grown(counts, growth, len(slave_x), minimum)
    return Plan(
        topo,
        master,
        st,
        tuple(sorted(cap.items())),
        sc,
        tuple(float(v) for v in origin),
        np.dtype(dtype).name,
        len(slave_x),
        growth,
    )


def _warp_surface():
    from arraycontact_warp import _surface

    return _surface


def _device_topology(master):
    """The master's topology made by the Warp back end's kernels on the Warp device of JAX's
    first device (its GPU, else Warp's CPU device), its exact tables put in the Surface's
    cache (arraycontact_warp._surface.fill_surface): (topology, Warp device), or None
    without Warp (the host's NumPy tables then)."""
    try:
        import warp as wp
    except ImportError:
        return None
    dev = jax.devices()[0]
    wdev = wp.device_from_jax(dev) if dev.platform == "gpu" else wp.get_device("cpu")
    return _warp_surface().fill_surface(master, wdev), wdev


def _device_topology_arrays(master, prep, self_contact, dev_topo):
    """`_topology`'s Master from the device topology (its int32 arrays as they are: no host
    copy on a GPU) with prep's trees' orders."""
    import warp as wp

    t, wdev = dev_topo

    def jx(a):
        return wp.to_jax(a) if wdev.is_cuda else jnp.asarray(a.numpy())

    table = _warp_surface().node_face_table(t, len(master.points), MAX_VALENCE, wdev)
    prev_face, next_face = jx(t.prev_face), jx(t.next_face)
    return Master(
        faces=jx(t.faces),
        node_ids=jnp.asarray(prep.node_ids.astype(np.int32)),
        face_ids=jnp.asarray(prep.face_ids.astype(np.int32)),
        face_edges=jx(t.face_edges),
        edge_faces=jx(t.edge_faces[: t.n_edges]),
        nf_offsets=jx(t.nf_offsets),
        nf_ids=jx(t.nf_ids),
        prev_node=jx(t.prev_node),
        next_node=jx(t.next_node),
        prev_face=prev_face,
        next_face=next_face,
        on_boundary=(prev_face >= 0) | (next_face >= 0),
        slave_nodes=jx(t.nodes[: t.n_nodes]) if self_contact else None,
        node_faces=None if table is None else jx(table),
        node_groups=tuple(jnp.asarray(g) for g in prep.node_groups),
        face_groups=tuple(jnp.asarray(g) for g in prep.face_groups),
    )


@partial(jax.jit, static_argnames=("st",))
def _count_at(sc, topo, nodes_x, slave_x, ids=None, *, st):
    """`_count` on the geometry of topo at nodes_x, made in the same program (one compilation
    where the geometry took one of its own)."""
    return _count(sc, master_geometry(jnp, st.element, topo, nodes_x), slave_x, ids, st=st)


def plan_self(
    surface,
    *,
    mode="exact",
    d_max=None,
    dtype=None,
    growth=GROWTH,
    minimum=None,
    search="jax",
    mesh=None,
    axis="space",
    margin=None,
) -> Plan:
    """`plan` for self-contact (arraycontact.detect_self's rule): the surface is master and
    slave, every node its faces use a slave. Detect with `detect_self(plan, points)`.
    mesh, axis, margin: over several devices, as `plan`."""
    if not isinstance(surface, Surface):
        raise ValueError("surface must be an arraycontact.Surface")
    return plan(
        surface,
        surface.points[surface.nodes],
        mode=mode,
        d_max=d_max,
        dtype=dtype,
        growth=growth,
        minimum=minimum,
        search=search,
        self_contact=True,
        mesh=mesh,
        axis=axis,
        margin=margin,
    )


def detect_self(p: Plan, points) -> Contacts:
    """Self-contact of the plan's surface at node coordinates `points` [n_points, 3] (jitted
    as `detect`, differentiable with respect to `points`); rows: the surface's nodes."""
    from ._shard import ShardedPlan

    if isinstance(p, ShardedPlan) and p.local.static.self_contact:
        return _detect_sharded(p, None, points)
    if not (isinstance(p, Plan) and p.static.self_contact):
        raise ValueError("detect_self needs a plan from plan_self")
    return detect(p, points[p.topology.slave_nodes], points)


@jax.jit
def _detect_sharded(p, slave_points, master_points):
    from . import _shard

    return _shard.detect(p, slave_points, master_points, self_points=slave_points is None)


def _shard_detect(p, slave_points, master_points):
    from . import _shard

    return _shard.detect(p, slave_points, master_points)


def _topology(master, prep, self_contact=False):
    return jax.tree.map(jnp.asarray, _topology_arrays(master, prep, self_contact))


def _topology_arrays(master, prep, self_contact=False, part=False, table=True):
    """The plan's topology on the host. part: `master` is a part of a sharded plan (its
    slaves are set by the plan), whose node-face table is kept where `table` (the whole
    master's is)."""
    topo = master_topology(master, prep)
    if self_contact and not part:
        topo = topo._replace(slave_nodes=master.nodes.astype(np.int32))
    # (the smooth outputs' vertex normals)
    return topo._replace(node_faces=padded_node_faces(master) if table else None)


def _check(p: Plan, slave_points, master_points):
    if not isinstance(p, Plan):
        raise ValueError("the first argument of detect must be a Plan (arraycontact_jax.plan)")
    if slave_points.ndim != 2 or slave_points.shape[1] != 3:
        raise ValueError(f"slave_points must have shape [n, 3], got {slave_points.shape}")
    if master_points.shape != p.master.points.shape:
        raise ValueError(
            f"master_points must have shape {p.master.points.shape} (the plan's "
            f"master), got {master_points.shape}"
        )


@jax.jit
def detect(p: Plan, slave_points, master_points) -> Contacts:
    """Contacts of `slave_points` [n, 3] on the plan's master at `master_points`.

    Jitted, static shapes, no host synchronisation; differentiable with respect to both
    coordinate arrays. Check `contacts.overflow` (or call `update_plan`): where a count exceeds
    its capacity the result may be incomplete. With a sharded plan (`plan(..., mesh=)`), the
    arrays may be sharded over its mesh axis by rows, or replicated; the result is sharded
    (replicated where the slaves are not a multiple of the devices)."""
    from ._shard import ShardedPlan

    if isinstance(p, ShardedPlan):
        if p.local.static.self_contact:
            raise ValueError("a self-contact plan detects with detect_self(plan, points)")
        return _shard_detect(p, slave_points, master_points)
    _check(p, slave_points, master_points)
    fields, counts = local_detect(p, p.topology, slave_points, master_points)
    ids = p.topology.slave_nodes
    n = slave_points.shape[0]
    ids = jnp.arange(n, dtype=jnp.int32) if ids is None else ids
    return contacts_of(fields, ids, p, counts, dict(p.capacity))


def contacts_of(fields, slave_ids, p, count, capacity) -> Contacts:
    """The Contacts pytree of a detection on plan `p` (one device's or sharded)."""
    return Contacts(
        **fields,
        slave_ids=slave_ids,
        d_max=p.d_max,
        counts=Counts(
            slaves_in_box=slave_ids.shape[0],
            master_nodes_in_box=len(p.master.nodes),
            master_faces_in_box=p.master.n_faces,
            count=count,
            capacity=capacity,
        ),
        backend="jax",
        dtype=jnp.dtype(p.dtype).name,
    )


def local_detect(p: Plan, topo, slave_points, master_points):
    """The detection of `detect` on topology `topo` (the plan's, or one part's under
    shard_map): (Contacts' per-slave fields, counts)."""
    dtype = jnp.dtype(p.dtype)
    origin = jnp.asarray(p.origin, dtype)

    def local(x):  # subtract in the input's precision, then cast
        return (x - jnp.asarray(p.origin, x.dtype)[None, :]).astype(dtype)

    s, xm = local(slave_points), local(master_points)
    st, sc = p.static, p.constants
    ids = topo.slave_nodes
    vertex = None
    if p.search is not None:
        out = p.search(jax.lax.stop_gradient(s), jax.lax.stop_gradient(xm), ids)
        counts = {}
    else:
        # The node pseudo-normals, once for the search (classification) and, differentiable,
        # the smooth outputs (whose own gathers of the faces around each slave's vertex took
        # 1.1 ms at 2^20 on an H100; the scatter's gradient is a gather).
        vertex = node_normals(get_element(st.element), topo.faces, xm, jnp)
        normals = jax.lax.stop_gradient(vertex)
        m = master_geometry(jnp, st.element, topo, jax.lax.stop_gradient(xm), normals)
        grids = build_grids(jnp, st, m)
        out, counts = run_stages(
            jnp,
            st,
            sc,
            m,
            grids,
            jax.lax.stop_gradient(s),
            dict(p.capacity),
            search=_grid,
            slave_ids=ids,
        )
    keep = out["active"] | (out["status"] == int(Status.PASSING_BY))
    face = jnp.where(keep, out["face"], -1)
    feature = jnp.where(keep, out["feature"], int(Feature.NONE))
    xi, point, gap, normal = smooth(
        get_element(st.element),
        s,
        xm,
        topo,
        face,
        feature,
        out["local"],
        out["xi"],
        sc.tie,
        vertex,
    )
    nan = jnp.asarray(jnp.nan, dtype)

    def masked(v):
        return jnp.where(keep.reshape(keep.shape + (1,) * (v.ndim - 1)), v, nan)

    fields = dict(
        active=out["active"],
        face=face,
        xi=masked(xi),
        point=masked(point + origin[None]),
        gap=masked(gap),
        distance=masked(jnp.abs(gap)),
        normal=masked(normal),
        feature=feature,
        master_node=out["master_node"],
        status=out["status"],
        finer=out.get("finer"),
    )
    return fields, counts


def warp_plan(
    master,
    slave_x,
    d_max,
    dtype,
    growth,
    origin,
    *,
    self_contact=False,
    device=None,
    tie=None,
    frame=None,
    box=None,
):
    """The Warp back end's plan of a search="warp" plan, taking coordinates in the JAX plan's
    frame `origin`, on the JAX device `device` (default: the first). tie: a part of a sharded
    plan takes the whole master's tie band (and the slack that goes with it), frame the
    whole scene's Warp frame, so that its ties and roundings resolve as on one device, and box
    the scene's box, so that its items have one device's Morton keys."""
    import warp as wp
    from arraycontact_warp._real import precision

    back = precision(dtype)  # (the dtype's Warp modules alone: float32's are not float64's)
    p = back.plan(
        master,
        slave_x,
        d_max=d_max,
        device=wp.device_from_jax(jax.devices()[0] if device is None else device),
        dtype=dtype,
        growth=growth,
        self_contact=self_contact,
        frame=frame,
        box=box,
    )
    # The inputs come in the JAX plan's frame: the kernels subtract the difference.
    origin = np.asarray(origin)
    p.origin = p.origin - origin
    if tie is not None:
        c = p.constants
        p.constants = c._replace(tie=tie, slack=c.slack + max(tie - c.tie, 0.0))
    if p.device.is_cuda:
        # One detection now, outside any capture: its first call loads the kernels' modules
        # and captures the plan's own CUDA graph, which inside jax_callable's capture would
        # happen within another (on an H100 the JAX program then failed with an illegal
        # address whenever a Warp self-contact detection had run before in the process).
        if self_contact:
            back.detect_self(p, master.points - origin)
        else:
            back.detect(p, slave_x - origin, master.points - origin)
    return p


class _WarpSearch:
    """The Warp back end's detection as a JAX primitive (wp.jax_callable): called in `detect`
    with the slave and master coordinates in the plan's frame, returns the search's answer
    (active, face, feature, local, xi, gap, master_node, status) as JAX arrays.

    plans: one Warp plan (`warp_plan`), or one per part of a sharded plan, called inside
    shard_map over `axis`: each device runs its part's plan, picked by the device of the call
    (GPUs) or by the part's index (CPU devices, which are one Warp device). A
    part's self-contact plan answers for every node of its surface (its points, all used but
    the last unused ones), and the part's own slaves are taken from those rows."""

    def __init__(self, plans, dtype, self_contact=False, axis=None):
        import warp as wp
        from arraycontact_warp._real import precision

        self.plans, self.axis = list(plans), axis
        self.by_point = self_contact and axis is not None
        back = precision(dtype)  # the dtype's Warp `_detect`, bound once (every search calls it)
        real, vec2, vec3 = back.real, back.vec2, back.vec3
        self.names = ("active", "face", "feature", "local", "xi", "gap", "master_node", "status")
        if self_contact:
            self.names += ("finer",)
        kinds = dict(
            active=wp.int32,
            face=int,
            feature=int,
            local=int,
            xi=vec2,
            gap=real,
            master_node=int,
            status=int,
            finer=wp.int32,
        )
        plans = self.plans
        # Parts on several GPUs: XLA calls each device's search from a thread of its own. The
        # plan is the one on the device of the call's arrays, launched on the stream XLA
        # gives (jax_callable's wp.ScopedStream). The inputs are staged into the plan's own
        # buffers, so that the plan's CUDA graph (detect's, keyed by its input buffers) is
        # one per device whatever buffers XLA hands the call. Not jax_callable's graphs:
        # its staged graph is one per call site, not per device (a second GPU replayed the
        # first's: on two H200s, a deadlock in the next all_to_all), and its mode WARP
        # captures a graph per device and call buffers, which calls dispatched back to back
        # renew on every call (two H200s: 5-6x the synchronised time, benchmarks/RESULTS.md).
        on_device = {str(q.device): q for q in plans}
        several_gpus = len(on_device) > 1

        def search(part, slaves, master_points, *outs):
            if len(plans) == 1:
                plan = plans[0]
            elif several_gpus:
                plan = on_device[str(master_points.device)]
                wp.copy(plan.master_in, master_points)
                master_points = plan.master_in
                if not self_contact:
                    wp.copy(plan.slave_in, slaves)
                    slaves = plan.slave_in
            else:  # the parts of CPU devices, one Warp device: the part's index
                plan = plans[int(part.numpy()[0])]
            if self_contact:  # the slaves are the master's nodes: gathered by the kernels
                o = back.detect_self(plan, master_points)
            else:
                o = back.detect(plan, slaves, master_points)
            for name, a in zip(self.names, outs):
                wp.copy(a, o[name], count=len(o[name]))

        # jax_callable reads the Warp types from the annotations.
        search.__annotations__ = {
            "part": wp.array(dtype=wp.int32),
            "slaves": wp.array(dtype=vec3),
            "master_points": wp.array(dtype=vec3),
            **{f"o_{k}": wp.array(dtype=kinds[k]) for k in self.names},
        }
        search.__signature__ = _signature(
            ["part", "slaves", "master_points", *[f"o_{k}" for k in self.names]]
        )
        # One GPU: Warp captures the search in a CUDA graph of its own, replayed on staging
        # buffers with the copies in and out outside it (JAX cannot take the radix sort's
        # temporary storage as a child graph); without the graph every call pays Python's
        # launch overhead. vmap over scenes calls the search once per scene (its plan holds
        # one scene's buffers). Several GPUs: the search's Python runs every call (under
        # jax_callable's lock, the devices in turn) and replays the plan's graph.
        mode = wp.JaxCallableGraphMode.NONE
        if self.plans[0].device.is_cuda and not several_gpus:
            mode = wp.JaxCallableGraphMode.WARP_STAGED_EX
        self.call = wp.jax_callable(
            search, num_outputs=len(self.names), graph_mode=mode, vmap_method="sequential"
        )

    def __call__(self, s, xm, slave_nodes=None):
        n = xm.shape[0] if self.by_point else s.shape[0]
        part = jnp.zeros(1, jnp.int32)
        if self.axis is not None:  # inside shard_map
            part = part + jax.lax.axis_index(self.axis)
        outs = self.call(part, s, xm, output_dims={f"o_{k}": n for k in self.names})
        out = dict(zip(self.names, outs))
        if self.by_point:  # the part's slaves: rows of their local point ids
            out = {k: v[slave_nodes] for k, v in out.items()}
        out["active"] = out["active"].astype(bool)
        if "finer" in out:
            out["finer"] = out["finer"].astype(bool)
        ok = out["active"]
        # Inactive rows hold NaN: keep them out of the smooth formulas' arithmetic.
        out["xi"] = jnp.where(ok[:, None], out["xi"], 0)
        out["gap"] = jnp.where(ok, out["gap"], 0)
        return out


def _signature(names):
    import inspect

    return inspect.Signature(
        [inspect.Parameter(n, inspect.Parameter.POSITIONAL_OR_KEYWORD) for n in names]
    )


def update_plan(p: Plan, contacts: Contacts, slave_points, master_points) -> Plan:
    """`p` itself when `contacts` did not overflow, else a plan sized for the current
    coordinates and at least the counts `contacts` reports (outside `jit`)."""
    if not bool(contacts.overflow):
        return p
    from ._shard import ShardedPlan

    count = {k: float(np.max(np.asarray(v))) for k, v in contacts.counts.count.items()}
    master = p.master.with_points(np.asarray(master_points, np.float64))
    if isinstance(p, ShardedPlan):  # partitioned again from the current configuration
        lp = p.local
        return plan(
            master,
            master.points[master.nodes]
            if lp.static.self_contact
            else np.asarray(slave_points, np.float64),
            mode=lp.static.mode,
            d_max=p.d_max,
            dtype=lp.dtype,
            growth=lp.growth,
            minimum=count,
            search="jax" if lp.search is None else "warp",
            self_contact=lp.static.self_contact,
            mesh=p.mesh,
            axis=p.axis,
            margin=p.partition.margin,
        )
    return plan(
        master,
        np.asarray(slave_points, np.float64),
        mode=p.static.mode,
        d_max=p.d_max,
        dtype=p.dtype,
        growth=p.growth,
        minimum=count,
        search="jax" if p.search is None else "warp",
        self_contact=p.static.self_contact,
    )


def _flatten_contacts(c):
    arrays = tuple(getattr(c, k) for k in _ARRAYS)
    return (arrays, c.counts.count), (
        c.d_max,
        tuple(sorted(c.timings.items())),
        c.counts.slaves_in_box,
        c.counts.master_nodes_in_box,
        c.counts.master_faces_in_box,
        tuple(sorted(c.counts.capacity.items())),
        c.backend,
        c.device,
        c.dtype,
    )


def _unflatten_contacts(aux, children):
    arrays, count = children
    d_max, timings, n_s, n_n, n_f, cap, backend, device, dtype = aux
    return Contacts(
        **dict(zip(_ARRAYS, arrays)),
        d_max=d_max,
        counts=Counts(n_s, n_n, n_f, count=count, capacity=dict(cap)),
        timings=dict(timings),
        backend=backend,
        device=device,
        dtype=dtype,
    )


_ARRAYS = (
    "active",
    "face",
    "xi",
    "point",
    "gap",
    "distance",
    "normal",
    "feature",
    "master_node",
    "status",
    "slave_ids",
    "finer",
)
jax.tree_util.register_pytree_node(Contacts, _flatten_contacts, _unflatten_contacts)


# ---------------------------------------------------------------------------------------------
# swept detection (arraycontact.detect_swept's contract)


@dataclass(frozen=True, eq=False)
class SweptPlan:
    """Static sizes of a jitted swept detection (see `plan_swept`); a pytree."""

    order: object  # face ids in the Morton order of their plan-time capture boxes
    master: Surface = field(repr=False)
    capacity: tuple = ()  # sorted (name, capacity): the tree query's pairs per level
    origin: tuple = (0.0, 0.0, 0.0)
    pads: tuple = (0.0, 0.0)  # (rel, rounding x scale): arraycontact._sweep.capture_pads
    dtype: str = "float32"
    n_slaves: int = 0
    growth: float = GROWTH


jax.tree_util.register_pytree_node(
    SweptPlan,
    lambda p: ((p.order,), (p.master, p.capacity, p.origin, p.pads, p.dtype, p.n_slaves, p.growth)),
    lambda aux, ch: SweptPlan(ch[0], *aux),
)


def _swept_pairs(xp, element, order, s0, s1, m0, m1, faces, pads, capacity):
    """The tree over the faces' capture boxes (in `order`) and the (slave, face) pairs whose
    boxes meet the ball around the slave's segment, both grown by `pads` (rel, rounding times
    the frame's scale: arraycontact._sweep.capture_pads)."""
    from arraycontact import _grid as tree
    from arraycontact._detect import capture_boxes
    from arraycontact._sweep import grown_boxes

    rel, rounding = pads
    lo, hi = capture_boxes(element, m0[faces[order]], m1[faces[order]], xp)
    g_lo, g_hi = grown_boxes(lo, hi, rel, rounding, xp)
    t = tree.build(xp, order, g_lo, g_hi, lo)
    mid = 0.5 * (s0 + s1)
    d = s1 - s0
    half = (0.5 + rel) * xp.sqrt(xp.sum(d * d, -1))
    slave, entry, valid, counts = tree.query(
        xp, t, mid, half, 0.0, capacity, name="pairs", shrink=False
    )
    return slave, t.ids[entry], valid, counts


def plan_swept(
    master, slave_x0, slave_x1=None, master_x1=None, *, dtype=None, growth=GROWTH, minimum=None
) -> SweptPlan:
    """Size a jitted swept detection from a step like those to come (eager): slaves moving
    from slave_x0 to slave_x1 [n, 3] (default: not moving) while the master's points move to
    master_x1 (default: not moving). Capacities are the pairs found now times `growth`; a
    step with more reports overflow (`update_plan` re-plans)."""
    if dtype is None:
        dtype = np.float64 if jax.config.jax_enable_x64 else np.float32
    dtype = np.dtype(dtype)
    if dtype not in (np.float32, np.float64):
        raise ValueError(f"dtype must be float32 or float64, got {dtype}")
    if dtype == np.float64 and not jax.config.jax_enable_x64:
        raise ValueError("dtype float64 needs jax_enable_x64")
    if not isinstance(master, Surface):
        raise ValueError("master must be an arraycontact.Surface")
    if not growth >= 1:
        raise ValueError(f"growth must be >= 1, got {growth}")
    from arraycontact._detect import _swept_inputs, capture_boxes
    from arraycontact._sweep import capture_pads

    x1 = slave_x0 if slave_x1 is None else slave_x1
    m1 = master.points if master_x1 is None else master_x1
    x0, x1, _, m1 = _swept_inputs(slave_x0, x1, master, m1)
    if len(x0) == 0:
        raise ValueError("slave_x0 is empty: there is nothing to plan for")
    if master.n_faces == 0:
        raise ValueError("master has no faces")
    e = master.element
    lo, hi = capture_boxes(e, master.points[master.faces], m1[master.faces])
    b_lo = np.minimum(np.minimum(x0, x1).min(0), lo.min(0))
    b_hi = np.maximum(np.maximum(x0, x1).max(0), hi.max(0))
    origin = b_lo if dtype == np.float32 else np.zeros(3)
    extent = float((b_hi - b_lo).max())
    scale = 2 * max(float(np.abs(np.r_[b_lo - origin, b_hi - origin]).max()), 1e-300)
    rel, rounding = capture_pads(dtype)
    pads = (rel, rounding * scale)
    order = morton_order(0.5 * (lo + hi), b_lo, extent).astype(np.int32)
    _, _, _, counts = _swept_pairs(
        np,
        e,
        order,
        x0 - origin,
        x1 - origin,
        master.points - origin,
        m1 - origin,
        master.faces,
        pads,
        None,
    )
    cap = {k: max(int(np.ceil(int(v) * growth)), len(x0)) for k, v in counts.items()}
    for k, v in (minimum or {}).items():
        if k in cap:
            cap[k] = max(cap[k], int(np.ceil(v * growth)))
    return SweptPlan(
        jnp.asarray(order),
        master,
        tuple(sorted(cap.items())),
        tuple(float(v) for v in origin),
        tuple(float(v) for v in pads),
        dtype.name,
        len(x0),
        growth,
    )


@jax.jit
def detect_swept(p: SweptPlan, slave_x0, slave_x1, master_x0, master_x1) -> SweptContacts:
    """The first contact of every slave over the step (arraycontact.detect_swept's contract):
    jitted, static shapes; toi, xi, point, normal and normal_velocity differentiable with
    respect to all four coordinate arrays (away from ties and grazing contacts). Check
    `overflow` (or call `update_plan`)."""
    if not isinstance(p, SweptPlan):
        raise ValueError("the first argument must be a SweptPlan (arraycontact_jax.plan_swept)")
    for name, a, n in (
        ("slave_x0", slave_x0, p.n_slaves),
        ("slave_x1", slave_x1, p.n_slaves),
        ("master_x0", master_x0, len(p.master.points)),
        ("master_x1", master_x1, len(p.master.points)),
    ):
        if a.shape != (n, 3):
            raise ValueError(f"{name} must have shape ({n}, 3), got {a.shape}")
    dtype = jnp.dtype(p.dtype)
    e = p.master.element
    faces = jnp.asarray(p.master.faces.astype(np.int32))

    def local(x):
        return (x - jnp.asarray(p.origin, x.dtype)[None, :]).astype(dtype)

    s0, s1, m0, m1 = (local(x) for x in (slave_x0, slave_x1, master_x0, master_x1))
    sg = jax.lax.stop_gradient
    cap = dict(p.capacity)
    slave, face, valid, counts = _swept_pairs(
        jnp, e, p.order, sg(s0), sg(s1), sg(m0), sg(m1), faces, p.pads, cap
    )
    xe0, xe1 = sg(m0)[faces[face]], sg(m1)[faces[face]]
    toi, where, conv, visits = _sweep.roots(e, xe0, xe1, sg(s0)[slave], sg(s1)[slave], valid)
    n = s0.shape[0]
    inf = jnp.asarray(jnp.inf, dtype)
    toi = jnp.where(valid, toi, inf)
    first = jax.ops.segment_min(toi, slave, num_segments=n)
    band = jnp.isfinite(toi) & (toi <= first[slave] + T_TOL[np.dtype(dtype)])
    big = jnp.iinfo(jnp.int32).max
    low = jax.ops.segment_min(jnp.where(band, face, big), slave, num_segments=n)
    k = jnp.arange(slave.shape[0], dtype=jnp.int32)
    pick = jax.ops.segment_min(
        jnp.where(band & (face == low[slave]), k, big), slave, num_segments=n
    )
    hit = pick < big
    pk = jnp.where(hit, pick, 0)
    f = jnp.where(hit, face[pk], 0)
    t0 = jnp.where(hit, first, 0.5)
    t, xi, point, normal, vn = _sweep.impact(e, m0[faces[f]], m1[faces[f]], s0, s1, t0, where[pk])
    nan = jnp.asarray(jnp.nan, dtype)

    def masked(v):
        return jnp.where(hit.reshape(hit.shape + (1,) * (v.ndim - 1)), v, nan)

    status = jnp.where(
        hit,
        jnp.where(conv[pk], int(Status.OK), int(Status.NOT_CONVERGED)),
        int(Status.OUT_OF_RANGE),
    )
    return SweptContacts(
        hit=hit,
        toi=jnp.where(hit, t, inf),
        face=jnp.where(hit, f, -1),
        xi=masked(xi),
        point=masked(point + jnp.asarray(p.origin, dtype)[None]),
        normal=masked(normal),
        feature=jnp.where(
            hit, feature_of(e, sg(xi), FEATURE_TOL[np.dtype(dtype)], jnp), int(Feature.NONE)
        ),
        normal_velocity=masked(vn),
        status=status.astype(jnp.int32),
        slave_ids=jnp.arange(n, dtype=jnp.int32),
        t_tol=T_TOL[np.dtype(dtype)],
        counts=Counts(
            slaves_in_box=n, master_faces_in_box=p.master.n_faces, count=counts, capacity=cap
        ),
        backend="jax",
        dtype=np.dtype(dtype).name,
    )


def update_swept_plan(p: SweptPlan, res: SweptContacts, slave_x0, slave_x1, master_x0, master_x1):
    """`p` when `res` did not overflow, else a plan sized for this step (outside `jit`)."""
    if not bool(res.counts.overflow):
        return p
    count = {k: float(np.max(np.asarray(v))) for k, v in res.counts.count.items()}
    return plan_swept(
        p.master.with_points(np.asarray(master_x0, np.float64)),
        np.asarray(slave_x0, np.float64),
        np.asarray(slave_x1, np.float64),
        np.asarray(master_x1, np.float64),
        dtype=p.dtype,
        growth=p.growth,
        minimum=count,
    )


def run_swept(x0, x1, master, m1, su, dtype):
    """`arraycontact.detect_swept(backend="jax")`: plan, detect (re-planned on overflow)."""
    rows = su.slave_rows
    a, b = x0[rows], x1[rows]
    with jax.enable_x64(np.dtype(dtype) == np.float64):
        p = plan_swept(master, a, b, m1, dtype=dtype)
        args = [jnp.asarray(v, dtype) for v in (a, b, master.points, m1)]
        res = detect_swept(p, *args)
        while bool(res.counts.overflow):
            p = update_swept_plan(p, res, a, b, master.points, m1)
            res = detect_swept(p, *args)
    hit = np.asarray(res.hit)
    k = np.nonzero(hit)[0]
    out = {
        n: np.asarray(getattr(res, n))[k]
        for n in ("face", "toi", "xi", "point", "normal", "feature", "normal_velocity")
    }
    out["point"] = out["point"].astype(float) - su.origin  # detect_swept adds it back
    out["converged"] = np.asarray(res.status)[k] == int(Status.OK)
    out["rows"] = k
    return out, {kk: int(v) for kk, v in res.counts.count.items()}, str(jax.devices()[0])


_SWEPT_ARRAYS = (
    "hit",
    "toi",
    "face",
    "xi",
    "point",
    "normal",
    "feature",
    "normal_velocity",
    "status",
    "slave_ids",
)


def _flatten_swept(c):
    arrays = tuple(getattr(c, k) for k in _SWEPT_ARRAYS)
    return (arrays, c.counts.count), (
        c.t_tol,
        c.counts.slaves_in_box,
        c.counts.master_faces_in_box,
        tuple(sorted(c.counts.capacity.items())),
        c.backend,
        c.device,
        c.dtype,
    )


def _unflatten_swept(aux, children):
    arrays, count = children
    t_tol, n_s, n_f, cap, backend, device, dtype = aux
    return SweptContacts(
        **dict(zip(_SWEPT_ARRAYS, arrays)),
        t_tol=t_tol,
        counts=Counts(slaves_in_box=n_s, master_faces_in_box=n_f, count=count, capacity=dict(cap)),
        backend=backend,
        device=device,
        dtype=dtype,
    )


jax.tree_util.register_pytree_node(SweptContacts, _flatten_swept, _unflatten_swept)
