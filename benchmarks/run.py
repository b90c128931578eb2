"""The benchmark runner: scenes as data, one record per (scene, size, back end, dtype, mode).

    python benchmarks/run.py cpu            # 2^16 and 2^20 nodes per surface on the CPU
    python benchmarks/run.py pareto         # time against error, every variant
    python benchmarks/run.py scaling        # 2^12 .. 2^20, time per slave, memory
    python benchmarks/run.py peers          # Open3D, libigl, Warp BVH (CPU), cKDTree
    python benchmarks/run.py table1         # seed 000 Table 1 at 2^20 nodes each
    python benchmarks/report.py             # every table of RESULTS.md and GPU.md

Every record holds the scene, sizes, back end, device, dtype, mode, the first call (compile
and caches) apart from the steady state (median of repeats), the time per stage where the back
end reports it, contact counts, and the error against the brute-force reference on a random
subset of slaves (miss rate, wrong-face rate, largest gap error relative to the longest edge).
Peers are timed in the same run on the same points: scipy's cKDTree closest-node search.
Records are appended to benchmarks/results/<suite>_cpu.jsonl (the `cpu` suite's to
detect_cpu.jsonl) and summarised on stdout.
"""

from __future__ import annotations

import argparse
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np

import arraycontact as ac
from arraycontact._backends import quiet_warp

sys.path.insert(0, str(Path(__file__).parent))
import _records  # noqa: E402

HERE = Path(__file__).parent

# Scenes as data: name -> (generator, keyword arguments). Sizes are added per run.
SCENES = {
    "rough_close": ("rough_surfaces", dict(gap=1.0, rms=0.5)),
    "rough_quad4": ("rough_surfaces", dict(gap=1.0, rms=0.5, element="quad4")),
    "tyre_road": ("cylinder_on_road", dict(radius=40.0, depth=0.5)),
    # Seed 000 Table 1 (quadrilateral faces): close, convex, close but not touching.
    "table1_close": ("rough_surfaces", dict(gap=1.0, rms=0.5, element="quad4")),
    "table1_convex": ("rough_surfaces", dict(gap=1.0, rms=0.5, curvature=2e-4, element="quad4")),
    "table1_apart": ("rough_surfaces", dict(gap=4.0, rms=0.5, curvature=2e-4, element="quad4")),
}

_EVERY = [
    (b, d, m)
    for b in ("numpy", "jax", "warp")
    for d in ("float64", "float32")
    for m in ("exact", "node")
    if not (b == "warp" and (d == "float64" or m == "node"))
]
SUITES = {
    "cpu": dict(
        scenes=["rough_close"],
        sizes=[16, 20],
        runs=[
            ("numpy", "float64", "exact"),
            ("numpy", "float64", "node"),
            ("numpy", "float32", "exact"),
            ("jax", "float32", "exact"),
        ],
    ),
    # Every back end x dtype x mode x d_max factor (times the default d_max).
    "pareto": dict(
        scenes=["rough_close", "tyre_road"], sizes=[14], runs=_EVERY, d_max_factors=[0.5, 1.0, 2.0]
    ),
    "scaling": dict(
        scenes=["rough_close"],
        sizes=[12, 14, 16, 18, 20, 22],
        runs=[("numpy", "float64", "exact"), ("warp", "float32", "exact")],
        memory=True,
    ),
    # Warp's CPU device only: NumPy quad4 at 2^20 takes minutes per call on this machine.
    "table1": dict(
        scenes=["table1_close", "table1_convex", "table1_apart"],
        sizes=[20],
        runs=[("warp", "float32", "exact")],
    ),
    "peers": dict(
        scenes=["rough_close", "tyre_road"],
        sizes=[16],
        runs=[("numpy", "float64", "exact"), ("warp", "float32", "exact")],
        peers=True,
    ),
}


def make_scene(name, log2n):
    gen, kw = SCENES[name]
    return getattr(ac.scenes, gen)(2**log2n, **kw)


def timed(fn, repeats):
    t0 = time.perf_counter()
    out = fn()
    first = time.perf_counter() - t0
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return out, first, statistics.median(times) if times else first


def warp_contacts(p):
    """The Contacts of a Warp plan's last detection (its output arrays, on the host)."""
    o = {k: v.numpy() for k, v in p.out.items()}
    names = ("face", "xi", "point", "gap", "distance", "normal", "feature", "master_node")
    return ac.Contacts(
        active=o["active"].astype(bool),
        **{k: o[k] for k in names},
        status=o["status"],
        slave_ids=np.arange(p.n_slaves),
        d_max=p.constants.d_max,
    )


def errors(c, scene, n_check, dtype, seed=0):
    """Error against the brute-force reference on a random subset of slaves."""
    rng = np.random.default_rng(seed)
    idx = rng.choice(len(scene.slave), min(n_check, len(scene.slave)), replace=False)
    ref = ac.reference.closest_points(scene.slave[idx], scene.master)
    want = ref.distance <= c.d_max
    got = c.active[idx]
    both = want & got
    L = scene.master.longest_edge
    miss = float((want & ~got).sum() / max(want.sum(), 1))
    extra = float((got & ~want).sum() / max(len(idx), 1))
    # A wrong face: one not at the minimal distance (equidistant faces are all right).
    from arraycontact.reference import _closest_on_faces

    wrong = 0.0
    gap_err = 0.0
    if both.any():
        _, d2 = _closest_on_faces(
            scene.master.element,
            scene.slave[idx][both],
            scene.master.points[scene.master.faces[c.face[idx][both]]],
        )
        tol = (2e-5 if dtype == "float32" else 1e-9) * L  # the dtype's tie tolerance
        wrong = float((np.sqrt(d2) - ref.distance[both] > tol).mean())
        gap_err = float(np.abs(c.gap[idx][both] - ref.gap[both]).max() / L)
    return dict(
        checked=int(len(idx)),
        miss_rate=miss,
        extra_rate=extra,
        wrong_face_rate=wrong,
        max_gap_error_rel=gap_err,
    )


def kdtree_peer(scene, d_max, repeats):
    from scipy.spatial import cKDTree

    nodes = scene.master.points[scene.master.nodes]

    def run():
        tree = cKDTree(nodes)
        return tree.query(scene.slave, distance_upper_bound=d_max)

    _, first, steady = timed(run, repeats)
    return dict(peer="scipy cKDTree closest node (build + query)", first_s=first, steady_s=steady)


def peer_records(scene, d_max, repeats, n_check):
    """Closest-point peers on the same points: Open3D, libigl, Warp's BVH on the CPU device.
    Each is timed (first call apart) and checked against the reference on the same subset."""
    tri = (
        scene.master.faces
        if scene.master.element.name == "tri3"
        else np.concatenate([scene.master.faces[:, [0, 1, 2]], scene.master.faces[:, [0, 2, 3]]])
    )
    pts = scene.master.points
    q = scene.slave
    rng = np.random.default_rng(0)
    idx = rng.choice(len(q), min(n_check, len(q)), replace=False)
    ref = ac.reference.closest_points(q[idx], scene.master)
    out = {}

    def record(name, fn):
        try:
            dist, first, steady = timed(fn, repeats)
        except ImportError as e:
            out[name] = dict(error=f"not installed: {e}")
            return
        near = ref.distance <= d_max
        err = float(np.abs(dist[idx][near] - ref.distance[near]).max() / scene.master.longest_edge)
        out[name] = dict(first_s=first, steady_s=steady, max_distance_error_rel=err)

    def open3d():
        import open3d as o3d

        sc = o3d.t.geometry.RaycastingScene()
        sc.add_triangles(
            o3d.core.Tensor(pts.astype(np.float32)), o3d.core.Tensor(tri.astype(np.uint32))
        )
        r = sc.compute_closest_points(o3d.core.Tensor(q.astype(np.float32)))
        return np.linalg.norm(r["points"].numpy() - q, axis=1)

    def libigl():
        import igl

        d2, _, _ = igl.point_mesh_squared_distance(q, pts, tri.astype(np.int64))
        return np.sqrt(d2)

    def warp_bvh():

        sys.path.insert(0, str(HERE))
        from peers_warp import mesh_peers

        quiet_warp()
        r = mesh_peers(scene.master, q, d_max, repeats=1, device="cpu")
        return np.where(r["face"] >= 0, r["distance"], np.inf)

    record("open3d RaycastingScene.compute_closest_points (build + query)", open3d)
    record("libigl point_mesh_squared_distance (AABB build + query)", libigl)
    record("warp wp.Mesh BVH on the CPU device (build + query)", warp_bvh)
    return out


def _peak_bytes(fn):
    """Peak Python-visible allocation (NumPy arrays included) of one call."""
    import tracemalloc

    tracemalloc.start()
    fn()
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    return peak


def run_suite(suite, sizes=None, repeats=2, n_check=512, save=True, run=None):
    cfg = SUITES[suite]
    records = []
    meta = _records.meta(run)
    device = f"cpu: {platform.processor() or platform.machine()}, {_cores()} cores"
    for scene_name in cfg["scenes"]:
        for log2n in sizes or cfg["sizes"]:
            scene = make_scene(scene_name, log2n)
            d0 = ac.detect(scene.slave[:1], scene.master).d_max
            peer = None
            for factor in cfg.get("d_max_factors", [1.0]):
                for backend, dtype, mode in cfg["runs"]:
                    d_max = d0 * factor

                    def call():
                        return ac.detect(
                            scene.slave,
                            scene.master,
                            backend=backend,
                            mode=mode,
                            dtype=dtype,
                            d_max=d_max,
                        )

                    c, first, steady = timed(call, repeats)
                    if peer is None:
                        peer = kdtree_peer(scene, d_max, repeats)
                    rec = dict(
                        suite=suite,
                        scene=scene_name,
                        log2_nodes=log2n,
                        n_slaves=len(scene.slave),
                        n_master_faces=scene.master.n_faces,
                        element=scene.master.element.name,
                        backend=backend,
                        device=device,
                        dtype=dtype,
                        mode=mode,
                        d_max_factor=factor,
                        d_max=d_max,
                        first_call_s=first,
                        steady_s=steady,
                        stages_s={k: v for k, v in c.timings.items()},
                        active=int(c.active.sum()),
                        counts=c.counts.count,
                        penetrating=int((c.active & (c.gap < 0)).sum()),
                        nodes_in_box=c.counts.slaves_in_box + c.counts.master_nodes_in_box,
                        errors=errors(c, scene, n_check, dtype),
                        peer=peer,
                        ratio_to_peer=steady / peer["steady_s"],
                        time_per_slave_s=steady / len(scene.slave),
                    )
                    if cfg.get("memory") and backend == "numpy":
                        rec["peak_bytes"] = _peak_bytes(call)
                        rec["bytes_per_node"] = rec["peak_bytes"] / (
                            len(scene.slave) + len(scene.master.points)
                        )
                    if cfg.get("peers") and backend == "numpy":
                        rec["peers"] = peer_records(scene, d_max, repeats, n_check)
                    records.append(rec)
                    _print(rec)
                    if save:
                        bench = "detect" if suite == "cpu" else suite
                        _records.append(bench, rec, meta)
    return records


def _cores():
    import os

    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()


def _print(r):
    st = ", ".join(
        f"{k} {v * 1e3:.0f}" for k, v in r["stages_s"].items() if k not in ("detect", "total")
    )
    e = r["errors"]
    print(
        f"{r['scene']} 2^{r['log2_nodes']} {r['backend']:5s} {r['dtype']} {r['mode']:5s} "
        f"d_max x{r.get('d_max_factor', 1.0)} | "
        f"first {r['first_call_s']:.3f} s, steady {r['steady_s']:.3f} s "
        f"({r['ratio_to_peer']:.1f}x cKDTree {r['peer']['steady_s']:.3f} s) | "
        f"active {r['active']} | miss {e['miss_rate']:.2g} wrong face "
        f"{e['wrong_face_rate']:.2g} gap err {e['max_gap_error_rel']:.2g}"
        + (f" | stages ms: {st}" if st else "")
        + (f" | peak {r['bytes_per_node']:.0f} B/node" if "bytes_per_node" in r else "")
        + "".join(
            f"\n    peer {k}: "
            + (
                v.get("error")
                or f"{v['steady_s']:.3f} s, dist err {v['max_distance_error_rel']:.1e}"
            )
            for k, v in r.get("peers", {}).items()
        ),
        flush=True,
    )


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("suite", choices=sorted(SUITES))
    p.add_argument("--sizes", type=int, nargs="*", help="log2 of the nodes per surface")
    p.add_argument("--repeats", type=int, default=2)
    p.add_argument("--check", type=int, default=512, help="slaves checked against the reference")
    p.add_argument("--no-save", action="store_true")
    p.add_argument("--run", default=None, help="run id recorded with every record")
    a = p.parse_args()
    run_suite(a.suite, a.sizes, a.repeats, a.check, not a.no_save, a.run)


if __name__ == "__main__":
    main()
