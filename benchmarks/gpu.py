"""GPU benchmark of the rough-surface scene: our Warp and JAX detection against Warp's own BVH
closest-point query and hash-grid closest-node search, same points, same run.

    python benchmarks/gpu.py all --sizes 16 20 22 [--run ID] [--out DIR]   # CUDA and Warp
    python benchmarks/gpu.py table [--machine h100]    # newest record per back end and size

For each size: two rough surfaces of 2^k nodes each (float32), the JAX plan time, the first
detect (compilation) and the steady-state detect (median of synchronised repeats, coordinates
as device arrays, as inside a simulation loop), the error against the brute-force reference on
a random subset, and the peers: `wp.Mesh` build + `mesh_query_point_no_sign`, refit + query, and
`wp.HashGrid` build + closest-node query. One JSON record per size and back end goes to
DIR/gpu_<machine>.jsonl (default DIR: results/).
"""

import argparse
import functools
import statistics
import sys
import time
from pathlib import Path

import numpy as np

from arraycontact._backends import quiet_warp

sys.path.insert(0, str(Path(__file__).parent))
import _records  # noqa: E402
from run import errors, make_scene, warp_contacts  # noqa: E402


def bench_jax(scene, repeats, mode="exact", search="jax", d_max=None, grad=False):
    """The JAX back end, float32: plan, first call, steady detection; grad: also the steady
    value_and_grad of a gap energy with respect to both coordinate arrays."""
    import arraycontact_jax as acj
    import jax
    import jax.numpy as jnp

    t0 = time.perf_counter()
    p = acj.plan(scene.master, scene.slave, mode=mode, d_max=d_max, dtype=np.float32, search=search)
    plan_s = time.perf_counter() - t0
    # Again, its programs compiled: the plan's own work (plan_s - again: the compilation).
    t0 = time.perf_counter()
    p = acj.plan(scene.master, scene.slave, mode=mode, d_max=d_max, dtype=np.float32, search=search)
    plan_again_s = time.perf_counter() - t0
    s = jax.device_put(jnp.asarray(scene.slave, jnp.float32))
    m = jax.device_put(jnp.asarray(scene.master.points, jnp.float32))
    t0 = time.perf_counter()
    c = jax.block_until_ready(acj.detect(p, s, m))
    first = time.perf_counter() - t0
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        c = jax.block_until_ready(acj.detect(p, s, m))
        times.append(time.perf_counter() - t0)
    extra = {}
    if grad:

        def energy(s, m):
            c = acj.detect(p, s, m)
            return jnp.sum(jnp.where(c.active, jnp.minimum(c.gap, 0.0) ** 2, 0.0))

        vg = jax.jit(jax.value_and_grad(energy, argnums=(0, 1)))
        jax.block_until_ready(vg(s, m))
        gt = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            jax.block_until_ready(vg(s, m))
            gt.append(time.perf_counter() - t0)
        extra["value_and_grad_s"] = statistics.median(gt)
    if search == "warp":
        # Split the time: the Warp search alone (inside jit), and the JAX side's parts.
        from arraycontact_jax._gradients import smooth

        from arraycontact._elements import get_element
        from arraycontact._surface import face_bounds, node_normals

        def median_time(fn, *args):
            fn = jax.jit(fn)
            jax.block_until_ready(fn(*args))
            t = []
            for _ in range(repeats):
                t0 = time.perf_counter()
                jax.block_until_ready(fn(*args))
                t.append(time.perf_counter() - t0)
            return statistics.median(t)

        origin = jnp.asarray(p.origin, jnp.float32)
        extra["search_only_s"] = median_time(lambda s, m: p.search(s - origin, m - origin), s, m)
        el = get_element(p.static.element)
        faces = p.topology.faces
        out = jax.jit(lambda s, m: p.search(s - origin, m - origin))(s, m)
        tie = dict(p.constants)["tie"]
        extra["jax_parts_s"] = dict(
            face_bounds=median_time(lambda m: face_bounds(el, m[faces], jnp)[1].max(), m),
            node_normals=median_time(lambda m: node_normals(el, faces, m, jnp), m),
            smooth=median_time(
                lambda s, m, o: smooth(
                    el,
                    s,
                    m,
                    p.topology,
                    o["face"],
                    o["feature"],
                    o["local"],
                    o["xi"],
                    o["gap"],
                    tie,
                ),
                s - origin,
                m - origin,
                out,
            ),
        )
    c = jax.tree.map(np.asarray, c)
    return c, dict(
        **extra,
        plan_s=plan_s,
        plan_again_s=plan_again_s,
        first_call_s=first,
        steady_s=statistics.median(times),
        steady_min_s=min(times),
        device=str(jax.devices()[0].device_kind),
        overflow=bool(c.overflow),
        counts={k: float(v) for k, v in c.counts.count.items()},
        capacity=dict(c.counts.capacity),
    )


def _node_stage_kernel():
    import warp as wp
    from arraycontact_warp._closest_node import closest_node
    from arraycontact_warp._grid import Grid, Plain

    @wp.kernel(module="unique")
    def node_stage(
        grid: Grid,
        slaves: wp.array(dtype=wp.vec3),
        order: wp.array(dtype=int),
        d_max: float,
        tie: float,
        kind: Plain,
        normals: wp.array(dtype=wp.vec3),
        node_out: wp.array(dtype=int),
    ):
        i = order[wp.tid()]
        node, dn = closest_node(slaves[i], 0, 1, grid, d_max, tie, kind, normals)
        node_out[i] = node

    return node_stage


def kernel_resources(device):
    """Registers per thread and local (spilled) bytes of every CUDA kernel Warp has loaded:
    what limits the detection kernel's occupancy."""
    import ctypes

    import warp as wp

    cuda = ctypes.CDLL("libcuda.so.1")
    out = {}
    for module in list(wp._src.context.user_modules.values()):
        for ex in module.execs.values():
            if not ex.device.is_cuda or ex.device != wp.get_device(device):
                continue
            for name, hooks in ex.kernel_hooks.items():
                v = {}
                for what, attr in (("registers", 4), ("local_bytes", 3)):
                    r = ctypes.c_int(0)
                    cuda.cuFuncGetAttribute(ctypes.byref(r), attr, ctypes.c_void_p(hooks.forward))
                    v[what] = r.value
                out[name] = v
    return out


def warp_plan(scene, device="cuda", **plan_options):
    """A Warp plan for the scene and its slave and master coordinates as device arrays in the
    plan's frame, as a simulator holds them (the plan's origin then zero)."""
    import arraycontact_warp as acw
    import warp as wp

    p = acw.plan(scene.master, scene.slave, device=device, **plan_options)
    xs = wp.array((scene.slave - p.origin).astype(np.float32), dtype=wp.vec3, device=device)
    xm = wp.array((scene.master.points - p.origin).astype(np.float32), dtype=wp.vec3, device=device)
    p.origin = np.zeros(3)  # the arrays above are already local
    return p, xs, xm


@functools.cache
def _move_kernel():
    import warp as wp

    @wp.kernel(module="unique")
    def move(x: wp.array(dtype=wp.vec3), d: wp.vec3):
        x[wp.tid()] = x[wp.tid()] + d

    return move


def bench_warp_moving(scene, steps, step, device="cuda"):
    """A moving master: before each detect, master and slaves move `step` (a vector) in place,
    as a simulator's step writes them. The mean time of the steps (detect's graph: a refit
    while every face stays within the plan's margin of where it was keyed, else a build) and
    how many steps built the grids again."""
    import arraycontact_warp as acw
    import warp as wp

    p, xs, xm = warp_plan(scene, device)
    move = _move_kernel()
    d = wp.vec3(*[float(v) for v in step])
    for _ in range(3):  # the build, the capture, a replay
        wp.launch(move, xs.shape[0], inputs=[xs, wp.vec3(0.0)], device=device)  # (compiled)
        acw.detect(p, xs, xm)
    wp.synchronize_device(device)
    times, rebuilds = [], 0
    for _ in range(steps):
        t0 = time.perf_counter()
        wp.launch(move, xs.shape[0], inputs=[xs, d], device=device)
        wp.launch(move, xm.shape[0], inputs=[xm, d], device=device)
        acw.detect(p, xs, xm)
        wp.synchronize_device(device)
        times.append(time.perf_counter() - t0)
        rebuilds += int(p.rebuild.numpy()[0])
    # The last step's contacts against a plan that builds its grids in every call.
    q = warp_plan(scene, device, refit=False)[0]
    ref = acw.detect(q, xs, xm)
    got = {k: v.numpy() for k, v in p.out.items()}
    same = all(
        np.array_equal(a, ref[k].numpy(), equal_nan=a.dtype.kind == "f") for k, a in got.items()
    )
    return dict(
        mean_s=statistics.fmean(times),
        median_s=statistics.median(times),
        steps=steps,
        rebuilds=rebuilds,
        step=[float(v) for v in step],
        same_as_building=same,
    )


def bench_warp(scene, repeats, device="cuda", sort_slaves="plan", quick=False, **plan_options):
    """quick: the steady-state time only (variants beside the main record)."""
    import arraycontact_warp as acw
    import warp as wp

    t0 = time.perf_counter()
    p, xs, xm = warp_plan(scene, device, sort_slaves=sort_slaves, **plan_options)
    plan_s = time.perf_counter() - t0

    def run():
        acw.detect(p, xs, xm)

    from peers_warp import timed

    # Steady state: from the second call on the same buffers, detect replays its launches as
    # a CUDA graph (the plan's `graphs`), which refits the master's grids (the plan's `refit`).
    first, steady = timed(run, repeats, device)
    if quick:
        return steady
    graph_s = None
    kernels = None
    launches_s = None
    if wp.get_device(device).is_cuda:
        p.graphs = False  # the launches one by one from Python
        launches_s = timed(run, repeats, device)[1]
        # Time per kernel / copy / memset of one detection (CUDA activity timing).
        with wp.ScopedTimer(
            "detect", cuda_filter=wp.TIMING_ALL, synchronize=True, print=False
        ) as timer:
            run()
        p.graphs = True
        kernels = {}
        for r in timer.timing_results:
            kernels[r.name] = kernels.get(r.name, 0.0) + r.elapsed / 1e3

        # The closest-node stage alone (same grid, same slave order): its share of the kernel.
        from arraycontact_warp._grid import Plain

        node_stage = _node_stage_kernel()  # built once: not inside the timed call
        rec_node = timed(
            lambda: wp.launch(
                node_stage,
                p.n_slaves,
                inputs=[
                    p.node_grid,
                    xs,
                    p.order,
                    float(p.constants.d_max),
                    float(p.constants.tie),
                    Plain(),
                    p.normals,
                    p.out["master_node"],
                ],
                device=device,
            ),
            repeats,
            device,
        )[1]
        kernels["closest_node_stage_alone"] = rec_node

        # The caller's own capture of detect (as a simulator's step graph).
        with wp.ScopedCapture(device=device) as cap:
            run()
        gt = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            wp.capture_launch(cap.graph)
            wp.synchronize_device(device)
            gt.append(time.perf_counter() - t0)
        graph_s = statistics.median(gt)
        kernels["resources"] = kernel_resources(device)
    c = warp_contacts(p)
    return c, dict(
        plan_s=plan_s,
        first_call_s=first,
        steady_s=steady,
        launches_s=launches_s,
        graph_replay_s=graph_s,
        kernels_s=kernels,
        device=wp.get_device(device).name,
        overflow=False,
    )


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument(
        "what",
        choices=["jax", "jax-warp", "warp", "all", "table"],
        help="jax-warp: the JAX back end with search='warp' (Warp kernels through Warp's JAX FFI)",
    )
    ap.add_argument("--sizes", type=int, nargs="*", default=[16, 20])
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--check", type=int, default=256)
    ap.add_argument("--device", default="cuda", help="Warp device of the peers")
    ap.add_argument("--out", default=None, help="folder of the records (default results/)")
    ap.add_argument("--run", default=None, help="run id recorded with every record")
    ap.add_argument("--machine", default="h100", help="table: the records' machine")
    a = ap.parse_args()
    if a.what == "table":
        return table(a.machine)
    import warp as wp

    quiet_warp()
    wp.init()
    from peers_warp import hashgrid_peer, mesh_peers

    meta = _records.meta(a.run)
    backends = ["jax", "jax-warp", "warp"] if a.what == "all" else [a.what]
    for k in a.sizes:
        scene = make_scene("rough_close", k)
        d_max = scene.master.longest_edge
        mesh = mesh_peers(scene.master, scene.slave, d_max, a.repeats, a.device)
        grid = hashgrid_peer(scene.master, scene.slave, d_max, a.repeats, a.device)
        peers = dict(
            warp_mesh_build_query=dict(zip(("first_s", "steady_s"), mesh["build_query"])),
            warp_mesh_refit_query=dict(zip(("first_s", "steady_s"), mesh["refit_query"])),
            warp_mesh_refit_query_graph=dict(
                zip(("first_s", "steady_s"), mesh.get("refit_query_graph", (None, None)))
            ),
            warp_hashgrid_closest_node=dict(zip(("first_s", "steady_s"), grid["build_query"])),
        )
        for backend in backends:
            if backend.startswith("jax"):
                c, rec = bench_jax(
                    scene, a.repeats, search="warp" if backend == "jax-warp" else "jax"
                )
            else:
                c, rec = bench_warp(scene, a.repeats, a.device)
                # The same detection with the slaves sorted again in every call, and in the
                # order they come; then on the slaves in a random order (a mesh numbered
                # without spatial order), sorted at plan time or not.
                perm = np.random.default_rng(0).permutation(len(scene.slave))
                shuffled = type(scene)(
                    scene.name, scene.master, scene.slave[perm], scene.slave_surface, scene.params
                )
                rec["variants_steady_s"] = {
                    "sorted_per_call": bench_warp(scene, a.repeats, a.device, "detect", True),
                    "unsorted": bench_warp(scene, a.repeats, a.device, False, True),
                    "shuffled_sorted": bench_warp(shuffled, a.repeats, a.device, "plan", True),
                    "shuffled_unsorted": bench_warp(shuffled, a.repeats, a.device, False, True),
                    # a build of the face grid in every call, no refit
                    "no_refit": bench_warp(scene, a.repeats, a.device, "plan", True, refit=False),
                }
                # Master and slaves moving a thousandth of the longest edge a step.
                rec["moving_master"] = bench_warp_moving(
                    scene, 200, np.array([1e-3, 0.0, 0.0]) * scene.master.longest_edge, a.device
                )
            ok = c.active & (mesh["face"] >= 0)
            rec.update(
                suite="gpu",
                scene="rough_close",
                log2_nodes=k,
                n_slaves=len(scene.slave),
                n_master_faces=scene.master.n_faces,
                backend=backend,
                dtype="float32",
                mode="exact",
                active=int(c.active.sum()),
                errors=errors(c, scene, a.check, "float32"),
                peers=peers,
                warp_mesh_active_agreement=float(((mesh["face"] >= 0) == c.active).mean()),
                warp_mesh_max_distance_diff=float(
                    np.abs(mesh["distance"][ok] - c.distance[ok]).max()
                )
                if ok.any()
                else None,
            )
            rec["ratio_to_mesh_build_query"] = (
                rec["steady_s"] / peers["warp_mesh_build_query"]["steady_s"]
            )
            rec["ratio_to_mesh_refit_query"] = (
                rec["steady_s"] / peers["warp_mesh_refit_query"]["steady_s"]
            )
            rg = peers["warp_mesh_refit_query_graph"]["steady_s"]
            rec["ratio_to_mesh_refit_query_graph"] = rec["steady_s"] / rg if rg else None
            _records.append("gpu", rec, meta, out=a.out)
            if rec.get("search_only_s"):
                print(
                    f"   the Warp search alone {rec['search_only_s'] * 1e3:.3f} ms; JAX parts "
                    + ", ".join(f"{k} {v * 1e3:.3f} ms" for k, v in rec["jax_parts_s"].items())
                )
            g = rec.get("graph_replay_s")
            la = rec.get("launches_s")
            print(
                f"2^{k} {backend} {rec['device']}: plan {rec['plan_s']:.2f} s, first "
                f"{rec['first_call_s']:.2f} s, steady {rec['steady_s'] * 1e3:.3f} ms"
                + (f", launches one by one {la * 1e3:.3f} ms" if la else "")
                + (f", in the caller's graph {g * 1e3:.3f} ms" if g else "")
                + " | wp.Mesh build+query "
                f"{peers['warp_mesh_build_query']['steady_s'] * 1e3:.3f} ms, refit+query "
                f"{peers['warp_mesh_refit_query']['steady_s'] * 1e3:.3f} ms"
                + (f" (as a graph {rg * 1e3:.3f} ms)" if rg else "")
                + ", HashGrid node "
                f"{peers['warp_hashgrid_closest_node']['steady_s'] * 1e3:.3f} ms | ratio to "
                f"build+query {rec['ratio_to_mesh_build_query']:.2f}, refit+query "
                f"{rec['ratio_to_mesh_refit_query']:.2f} | errors {rec['errors']} | overflow "
                f"{rec['overflow']}",
                flush=True,
            )
            if rec.get("moving_master"):
                mm = rec["moving_master"]
                print(
                    f"   moving master: mean {mm['mean_s'] * 1e3:.3f} ms a step "
                    f"(incl. moving both), {mm['rebuilds']} builds in {mm['steps']} steps"
                )
            if rec.get("variants_steady_s"):
                print(
                    "   variants ms: "
                    + ", ".join(f"{n} {t * 1e3:.3f}" for n, t in rec["variants_steady_s"].items())
                )
            if rec.get("kernels_s"):
                res = rec["kernels_s"].pop("resources", {})  # printed apart
                print(
                    "   per kernel ms: "
                    + ", ".join(
                        f"{n[:40]} {t * 1e3:.3f}"
                        for n, t in sorted(rec["kernels_s"].items(), key=lambda kv: -kv[1])
                    )
                )
                print(
                    "   registers / local bytes: "
                    + ", ".join(
                        f"{n[:30]} {v['registers']}/{v['local_bytes']}"
                        for n, v in res.items()
                        if "detect" in n or "node_stage" in n
                    )
                )


def table(machine):
    """The newest record of each back end and size on `machine`, as a markdown table."""
    recs = _records.newest(_records.load("gpu", machine), "backend", "log2_nodes")
    recs.sort(key=lambda r: (r["log2_nodes"], r["backend"]))

    def ms(v):
        return f"{v * 1e3:.2f}" if v else "-"

    rows = []
    for r in recs:
        p, e = r["peers"], r["errors"]
        var = r.get("variants_steady_s", {})
        rows.append(
            [
                f"2^{r['log2_nodes']}",
                r["backend"],
                f"{r['run']} ({_records.commit(r)})",
                f"{r['plan_s']:.2f}",
                f"{r['first_call_s']:.2f}",
                ms(r["steady_s"]),
                ms(r.get("launches_s")),
                ms(r.get("graph_replay_s")),
                ms(var.get("no_refit")),
                ms(r.get("moving_master", {}).get("mean_s")),
                ms(p["warp_mesh_build_query"]["steady_s"]),
                ms(p["warp_mesh_refit_query"]["steady_s"]),
                ms(p.get("warp_mesh_refit_query_graph", {}).get("steady_s")),
                ms(p["warp_hashgrid_closest_node"]["steady_s"]),
                f"{r['ratio_to_mesh_build_query']:.2f}",
                f"{r['ratio_to_mesh_refit_query']:.2f}",
                f"{e['miss_rate']:.0%}",
                f"{e['wrong_face_rate']:.0%}",
                f"{e['max_gap_error_rel']:.1e}",
            ]
        )
    header = [
        "nodes per surface", "back end", "run (commit)", "plan s", "first call s",
        "steady ms", "launched one by one ms", "in the caller's graph ms", "refit=False ms",
        "moving master ms a step", "wp.Mesh build + query ms", "wp.Mesh refit + query ms",
        "wp.Mesh refit + query as a graph ms", "wp.HashGrid closest node ms",
        "/ wp.Mesh build + query", "/ wp.Mesh refit + query", "misses", "wrong faces",
        "max gap error / edge",
    ]  # fmt: skip
    print(f"{recs[0]['device']}, float32, exact mode, rough surfaces (`rough_close`):\n")
    print(_records.markdown(header, rows))


if __name__ == "__main__":
    main()
