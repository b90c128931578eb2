"""The scene suite: every scene against the peers a user would pick instead, in the same run.

    python benchmarks/suite.py scenes                 # gmsh scenes -> benchmarks/scenes/*.npz
    python benchmarks/suite.py gpu --log2 20          # CUDA machine with Warp: ours vs wp.Mesh
    python benchmarks/suite.py cpu --log2 16          # CPU: ours vs fcpw, libigl, Warp's BVH
    python benchmarks/suite.py table --machine h100 [--run ID]   # tables from results/suite_*

Scenes (sizes from --log2 k, 2^k nodes per surface where the scene has two surfaces):
- uniform: two rough surfaces facing each other (the README's scene);
- quad4: the same nodes, the master in bilinear quads (the peers take each quad as two
  triangles, whose closest points differ from the bilinear face's where it is not flat);
- steep: rough surfaces with RMS 4 element sizes (faces much longer than their spacing);
- graded_r: the grading family, the same node count with element sizes 1 .. r, r = 1, 10,
  100, 1000 (roughness and gap scale with the local size);
- fine_patch: a patch 1000x finer than the plate around it, a rough punch on the patch;
- tyre: a cylinder pressed into a rough road;
- apart: the rough surfaces 50 element sizes apart (nothing within d_max);
- dmax_f: the uniform scene with d_max = f x the default (0.25, 4, 10);
- ball_block_N: gmsh, a ball pressed into a block, both refined around the contact to 1/N of
  the coarse size (made here by `scenes`, carried to the GPU machine as .npz: it has no gmsh).

Every record: run id, date, commit, command, device, scene, sizes, d_max, our time (plan,
first call, steady state), the peers' times, and the error against the brute-force reference
on a random subset of slaves (miss rate, wrong-face rate, largest gap error / longest edge).
"""

from __future__ import annotations

import argparse
import gc
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np

import arraycontact as ac
from arraycontact._backends import quiet_warp

HERE = Path(__file__).parent
sys.path.insert(0, str(HERE))
import _records  # noqa: E402
from run import errors, warp_contacts  # noqa: E402

SCENE_DIR = HERE / "scenes"


def suite(k: int):
    """(label, scene factory, d_max factor) for 2^k nodes a surface."""
    n = 2**k
    s = ac.scenes
    out = [
        ("uniform", lambda: s.rough_surfaces(n), 1.0),
        # The same nodes in bilinear quads (hexahedral meshes' faces); the peers take each quad
        # as two triangles.
        ("quad4", lambda: s.rough_surfaces(n, element="quad4"), 1.0),
        ("steep", lambda: s.steep_rough_surfaces(n), 1.0),
    ]
    for r in (1, 10, 100, 1000):
        out.append((f"graded_{r}", lambda r=r: s.graded_surfaces(n, ratio=float(r)), 1.0))
    out += [
        ("fine_patch", lambda: s.fine_patch(2 ** ((k - 2) // 2)), 1.0),
        ("tyre", lambda: s.cylinder_on_road(n, radius=40.0), 1.0),
        ("apart", lambda: s.rough_surfaces(n, gap=50.0), 1.0),
    ]
    for f in (0.25, 4.0, 10.0):
        out.append((f"dmax_{f:g}", lambda: s.rough_surfaces(n), f))
    for path in sorted(SCENE_DIR.glob("ball_block_*.npz")):
        out.append((path.stem, lambda path=path: load_scene(path), 1.0))
    return out


def triangles(surface):
    """The peers' triangles: tri3 faces, or each quad4 split along its 0-2 diagonal."""
    f = surface.faces
    if surface.element.name == "quad4":
        return np.concatenate([f[:, [0, 1, 2]], f[:, [0, 2, 3]]])
    return f


def load_scene(path):
    d = np.load(path)
    master = ac.Surface(d["points"], d["faces"], "tri3")
    return ac.scenes.Scene(Path(path).stem, master, d["slave"])


def ball_block(refine: float, coarse=1.0, radius=2.0, depth=0.05):
    """gmsh: a ball of `radius` pressed `depth` into a 10 x 10 x 4 block; both volumes meshed
    with tetrahedra of size `coarse`, refined to coarse / refine within a radius of the
    contact point. Master: the block's exterior surface; slaves: the ball's surface nodes."""
    import gmsh

    gmsh.initialize()
    gmsh.option.setNumber("General.Terminal", 0)
    gmsh.model.add("ball_block")
    occ = gmsh.model.occ
    block = occ.addBox(-5, -5, -4, 10, 10, 4)
    ball = occ.addSphere(0, 0, radius - depth, radius)
    occ.synchronize()
    fine = coarse / refine
    f = gmsh.model.mesh.field
    pt = f.add("MathEval")
    # Size: fine at the contact point, growing linearly to coarse.
    f.setString(pt, "F", f"Min({coarse}, {fine} + 0.02 * Sqrt(x^2 + y^2 + z^2))")
    f.setAsBackgroundMesh(pt)
    gmsh.option.setNumber("Mesh.MeshSizeExtendFromBoundary", 0)
    gmsh.option.setNumber("Mesh.MeshSizeFromPoints", 0)
    gmsh.option.setNumber("Mesh.MeshSizeFromCurvature", 0)
    gmsh.model.mesh.generate(2)
    nodes, coords, _ = gmsh.model.mesh.getNodes()
    x = np.zeros((int(nodes.max()) + 1, 3))
    x[nodes.astype(int)] = coords.reshape(-1, 3)

    def surface_of(volume):
        tris = []
        for _, tag in gmsh.model.getBoundary([(3, volume)], oriented=True):
            types, _, conn = gmsh.model.mesh.getElements(2, abs(tag))
            t = conn[list(types).index(2)].reshape(-1, 3).astype(int)
            tris.append(t if tag > 0 else t[:, ::-1])
        return np.concatenate(tris)

    faces_block, faces_ball = surface_of(block), surface_of(ball)
    gmsh.finalize()
    used = np.unique(faces_ball)
    return x, faces_block, x[used]


def make_scenes(refines=(100, 300, 1000)):
    SCENE_DIR.mkdir(exist_ok=True)
    for r in refines:
        x, faces, slave = ball_block(r)
        # Outward: the enclosed volume, a sum over the faces, is positive.
        t = x[faces]
        if np.einsum("ij,ij->i", t[:, 0], np.cross(t[:, 1], t[:, 2])).sum() < 0:
            faces = faces[:, ::-1]
        np.savez_compressed(SCENE_DIR / f"ball_block_{r}.npz", points=x, faces=faces, slave=slave)
        print(f"ball_block_{r}: {len(faces)} master faces, {len(slave)} slaves")


def _meta(a):
    return dict(_records.meta(a.run), host=platform.node())


#: Fresh Surfaces a GPU scene's set-up is timed on (medians reported, each trial recorded).
SETUP_TRIALS = 3


def _setup_once(scene, d_max, dev):
    """One set-up on the GPU: a Surface new to the plan (the constructor's validation timed
    apart), its plan (its topology made on the device), the plan again, the plan of a deformed
    configuration (Surface.with_points: the device tables of the connectivity shared, its
    geometry made) and the first detect after the plan. Returns the times and (plan, slave
    points, master points) on the device in the plan's frame."""
    import warp as wp
    from arraycontact_warp import detect, plan

    def timed(surface):
        t0 = time.perf_counter()
        q = plan(surface, scene.slave, d_max=d_max, device=dev)
        wp.synchronize_device(dev)
        return q, time.perf_counter() - t0

    t0 = time.perf_counter()
    fresh = ac.Surface(scene.master.points, scene.master.faces, scene.master.element.name)
    out = dict(surface_s=time.perf_counter() - t0)
    p, out["plan_s"] = timed(fresh)
    out["replan_s"] = timed(fresh)[1]
    out["deformed_plan_s"] = timed(fresh.with_points(scene.master.points))[1]
    xs = wp.array((scene.slave - p.origin).astype(np.float32), dtype=wp.vec3, device=dev)
    xm = wp.array((scene.master.points - p.origin).astype(np.float32), dtype=wp.vec3, device=dev)
    p.origin = np.zeros(3)
    wp.synchronize_device(dev)
    t0 = time.perf_counter()
    detect(p, xs, xm)
    wp.synchronize_device(dev)
    out["first_s"] = time.perf_counter() - t0
    return out, (p, xs, xm)


def _median_time(fn, repeats, sync=lambda: None):
    fn()
    sync()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        sync()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def _interleaved(fns, repeats):
    """The median times of fns, each called once unmeasured, then all in turn `repeats` times
    (the ratios between them then see the same machine)."""
    for fn in fns:
        fn()
    times = [[] for _ in fns]
    for _ in range(repeats):
        for fn, ts in zip(fns, times):
            t0 = time.perf_counter()
            fn()
            ts.append(time.perf_counter() - t0)
    return [statistics.median(ts) for ts in times]


def _plan_time(make, repeats, faults=None, key=None):
    """(The median time of make() over repeats after an unmeasured call (compilations), the
    last plan made.) Each plan is freed, and the garbage collected, before the next one's
    timing starts: a caller keeps its plan, so freeing one is no part of making one. (A run
    that kept every plan instead timed the Warp plan at 65-123 ms on 9 of 16 scenes at 2^16,
    against 12-23 ms.) faults: a dict that gets, at `key`, the median count of the process's
    minor page faults during a plan: memory new to the process costs about 1 us a 4 KB
    page on the 2-core machine, so the same plan takes longer where the process's allocator
    hands it fresh pages (the thirtieth session: a Warp plan of uniform 2^16 made 8000-9000
    faults and took 24-26 ms with every plan kept, 15 ms with each freed)."""
    plan = make()
    times, counts = [], []
    for _ in range(repeats):
        plan = None
        gc.collect()
        f0 = _minor_faults()
        t0 = time.perf_counter()
        plan = make()
        times.append(time.perf_counter() - t0)
        counts.append(_minor_faults() - f0)
    if faults is not None:
        faults[key] = int(statistics.median(counts))
    return statistics.median(times), plan


def _minor_faults():
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt


def topology_time(master):
    """Seconds to derive, on a fresh Surface, everything a detection reads from it (as the
    NumPy and JAX back ends make it: `Surface.prepare`, topology and geometry in two
    threads)."""
    t0 = time.perf_counter()
    m = ac.Surface(master.points, master.faces, master.element.name).prepare()
    for name in (
        "nodes",
        "node_faces",
        "edges",
        "edge_faces",
        "boundary_nodes",
        "closed",
        "longest_edge",
        "face_normals",
        "face_bounds",
        "node_normals",
    ):
        getattr(m, name)
    return time.perf_counter() - t0


def jax_search(scene, d_max, repeats, check):
    """The JAX back end with search="jax" (no Warp), float32, exact: plan, first call,
    steady detection, and the steady value_and_grad of a gap energy (gpu.bench_jax)."""
    from gpu import bench_jax

    c, r = bench_jax(scene, repeats, search="jax", d_max=d_max, grad=True)
    return dict(
        jax_plan_s=r["plan_s"],
        jax_plan_again_s=r["plan_again_s"],
        jax_first_s=r["first_call_s"],
        jax_steady_s=r["steady_s"],
        jax_value_and_grad_s=r["value_and_grad_s"],
        jax_overflow=r["overflow"],
        jax_counts={k: int(v) for k, v in r["counts"].items()},
        jax_capacity=r["capacity"],
        jax_errors=errors(c, scene, check, "float32"),
    )


def run_gpu(a):
    import arraycontact_warp as acw
    import warp as wp
    from peers_warp import mesh_peers

    quiet_warp()
    dev = "cuda"
    meta = dict(_meta(a), device=wp.get_device(dev).name)
    # Kernel compilation, once a run: the first plan and detect of a small scene of each
    # element the suite has (a cold kernel cache on a fresh machine compiles every module
    # here, so that a scene's "first detect" is the first call on a warm cache).
    t0 = time.perf_counter()
    for element in ("tri3", "quad4"):
        small = ac.scenes.rough_surfaces(2**10, element=element)
        p = acw.plan(small.master, small.slave, device=dev)
        acw.detect(p, small.slave, small.master.points)
    wp.synchronize_device(dev)
    meta["compile_s"] = time.perf_counter() - t0
    for label, make, f in suite(a.log2):
        if a.only and not any(label.startswith(o) for o in a.only):
            continue
        scene = make()
        d_max = f * scene.master.longest_edge
        # Set-up, three times (each a Surface new to the plan), their medians: one plan's time
        # moved by up to 16 ms between runs (graded_10 at 2^20 on an H200: 34.7 ms in h200-s45,
        # 50.6 in h200-s51), one first detect's against the steady state as much (ball_block_300:
        # 1.9x in h200-s47, 3.5x in h200-s51).
        trials = []
        for _ in range(SETUP_TRIALS):  # (the last trial's plan and buffers kept)
            times, (p, xs, xm) = _setup_once(scene, d_max, dev)
            trials.append(times)
        setup = {k: statistics.median(t[k] for t in trials) for k in trials[0]}
        steady = _median_time(
            lambda: acw.detect(p, xs, xm), a.repeats, lambda: wp.synchronize_device(dev)
        )
        # Calls on buffers new to the plan (a simulator's fresh arrays, a JAX program's
        # outputs): launched one by one, no graph of their own (the first captures the plan's
        # graph of the trees' rebuild, timed apart).
        fresh = iter([(wp.clone(xs), wp.clone(xm)) for _ in range(a.repeats + 1)])
        new_buffers = _median_time(
            lambda: acw.detect(p, *next(fresh)), a.repeats, lambda: wp.synchronize_device(dev)
        )
        c = warp_contacts(p)
        err = errors(c, scene, a.check, "float32")

        def one_shot():
            # What a user's one call does: host arrays in, a Surface made for the call, a
            # Contacts record of host arrays out.
            new = ac.Surface(scene.master.points, scene.master.faces, scene.master.element.name)
            ac.detect(scene.slave, new, backend="warp", d_max=d_max, dtype="float32")

        one_shot_s = _median_time(one_shot, min(a.repeats, 3))
        peers = mesh_peers(scene.master, scene.slave, d_max, repeats=a.repeats, device=dev)
        rec = dict(
            meta,
            scene=label,
            log2=a.log2,
            n_slaves=len(scene.slave),
            n_faces=scene.master.n_faces,
            d_max=d_max,
            ours="warp float32 exact",
            **setup,
            setup_trials=trials,
            steady_s=steady,
            new_buffers_s=new_buffers,
            one_shot_s=one_shot_s,
            errors=err,
            mesh_build_query_s=peers["build_query"][1],
            mesh_refit_query_s=peers["refit_query"][1],
            mesh_refit_query_graph_s=peers.get("refit_query_graph", (0, None))[1],
            active=int(c.active.sum()),
        )
        rec["vs_refit"] = steady / rec["mesh_refit_query_s"]
        rec["vs_build"] = steady / rec["mesh_build_query_s"]
        rec["topology_s"] = topology_time(scene.master)
        if a.jax:
            rec.update(jax_search(scene, d_max, a.repeats, a.check))
            rec["jax_vs_warp"] = rec["jax_steady_s"] / steady
        _write(a, rec)


def run_cpu(a):
    import arraycontact_warp as acw
    import fcpw
    import igl
    from peers_warp import mesh_peers

    quiet_warp()
    meta = dict(_meta(a), device="cpu: " + (platform.processor() or platform.machine()))
    for label, make, f in suite(a.log2):
        if a.only and not any(label.startswith(o) for o in a.only):
            continue
        scene = make()
        m = scene.master
        d_max = f * m.longest_edge
        q32 = np.ascontiguousarray(scene.slave, np.float32)
        tris = triangles(m)

        def fcpw_run():
            sc = fcpw.scene_3D()
            sc.set_object_count(1)
            sc.set_object_vertices(np.ascontiguousarray(m.points, np.float32), 0)
            sc.set_object_triangles(np.ascontiguousarray(tris, np.int32), 0)
            sc.build(fcpw.aggregate_type.bvh_surface_area, True)
            hits = fcpw.interaction_3D_list()
            sc.find_closest_points(q32, np.full(len(q32), d_max * d_max, np.float32), hits)

        def igl_run():
            igl.point_mesh_squared_distance(scene.slave, m.points, tris.astype(np.int64))

        def ours32():  # the one-shot call a user makes: plan (Morton order, trees), detect
            return ac.detect(scene.slave, m, backend="warp", d_max=d_max, dtype="float32")

        def fresh32():
            # The same call on a Surface made for it (as fcpw builds from the arrays): the
            # master's topology made in the call.
            new = ac.Surface(m.points, m.faces, m.element.name)
            return ac.detect(scene.slave, new, backend="warp", d_max=d_max, dtype="float32")

        # fcpw's build + query and our float32 one calls in turn: this shared machine's speed
        # drifts by 10-15 % within a run, and timed one after the other the ratios moved with
        # it (cpu-s51: graded_1000 1.17x, dmax_10 1.12x; in turn the same day 0.84x, 0.86x).
        t_fcpw, t32, t32_new = _interleaved([fcpw_run, ours32, fresh32], a.repeats)
        t_igl = _median_time(igl_run, max(a.repeats // 2, 1))
        # Warp's own BVH on its CPU device (wp.Mesh, mesh_query_point_no_sign within d_max;
        # one launch, which Warp runs on one core).
        bvh = mesh_peers(m, scene.slave, d_max, repeats=a.repeats, device="cpu")
        ours, faults = {}, {}
        f0 = _minor_faults()  # (one more call: the faults of fcpw's build + query)
        fcpw_run()
        faults["fcpw"] = _minor_faults() - f0
        ours["warp_cpu_float32_s"], ours["warp_cpu_float32_new_s"] = t32, t32_new
        ours["warp_cpu_float64_s"] = _median_time(
            lambda: ac.detect(scene.slave, m, backend="warp", d_max=d_max), a.repeats
        )
        for dtype in ("float32", "float64"):
            # The plan of a Surface new to it (its topology: the plan's).
            news = iter(
                [ac.Surface(m.points, m.faces, m.element.name) for _ in range(a.repeats + 1)]
            )
            ours[f"warp_cpu_{dtype}_plan_s"], p = _plan_time(
                lambda: acw.plan(next(news), scene.slave, d_max=d_max, device="cpu", dtype=dtype),
                a.repeats,
                faults,
                f"warp_cpu_{dtype}_plan",
            )
            if dtype == "float32":
                # The plan of a deformed configuration (Surface.with_points) of a Surface
                # planned before: the device tables of the connectivity shared.
                base = ac.Surface(m.points, m.faces, m.element.name)
                acw.plan(base, scene.slave, d_max=d_max, device="cpu")
                moved = iter([base.with_points(m.points) for _ in range(a.repeats + 1)])
                ours["warp_cpu_float32_deformed_plan_s"], _ = _plan_time(
                    lambda: acw.plan(next(moved), scene.slave, d_max=d_max, device="cpu"),
                    a.repeats,
                )
            acw.detect(p, scene.slave, m.points)
            ours[f"warp_cpu_{dtype}_detect_s"] = _median_time(
                lambda p=p: acw.detect(p, scene.slave, m.points), a.repeats
            )
        if not a.no_numpy:
            ours["numpy_float64_s"] = _median_time(
                lambda: ac.detect(scene.slave, m, d_max=d_max), 1
            )
        c = ac.detect(scene.slave, m, backend="warp", d_max=d_max, dtype="float32")
        rec = dict(
            meta,
            scene=label,
            log2=a.log2,
            n_slaves=len(scene.slave),
            n_faces=m.n_faces,
            d_max=d_max,
            **ours,
            fcpw_s=t_fcpw,
            libigl_s=t_igl,
            warp_bvh_build_query_s=bvh["build_query"][1],
            warp_bvh_refit_query_s=bvh["refit_query"][1],
            errors=errors(c, scene, a.check, "float32"),
            active=int(c.active.sum()),
        )
        best = min(v for k, v in ours.items() if not k.endswith(("detect_s", "plan_s", "new_s")))
        rec["vs_fcpw"] = best / t_fcpw
        rec["new_vs_fcpw"] = ours["warp_cpu_float32_new_s"] / t_fcpw
        # Set-up, each against fcpw's whole build + query of the scene.
        # (the median of repeats: one measurement of a 40 ms job swung 2x between scenes)
        rec["topology_s"] = statistics.median(topology_time(m) for _ in range(a.repeats))
        for search in ("jax", "warp"):
            import arraycontact_jax as acj

            rec[f"jax_{search}_plan_s"], _ = _plan_time(
                lambda s=search: acj.plan(m, scene.slave, d_max=d_max, dtype=np.float32, search=s),
                a.repeats,
                faults,
                f"jax_{search}_plan",
            )
        rec["plan_faults"] = faults  # median minor page faults of one plan (_plan_time)
        rec["setup_vs_fcpw"] = {
            k[:-2]: rec.get(k, ours.get(k)) / t_fcpw
            for k in (
                "topology_s",
                "warp_cpu_float32_plan_s",
                "warp_cpu_float32_deformed_plan_s",
                "jax_jax_plan_s",
                "jax_warp_plan_s",
            )
        }
        _write(a, rec)


def _write(a, rec):
    _records.append("suite", rec, {}, out=a.out)
    keys = [k for k in rec if k.endswith("_s") or k.startswith("vs_")]
    print(
        rec["scene"],
        rec["n_faces"],
        rec["n_slaves"],
        " ".join(f"{k}={rec[k]:.4g}" for k in keys if rec[k] is not None),
        "errors",
        {k: v for k, v in rec["errors"].items() if k != "checked"},
        flush=True,
    )


def table(a):
    """Markdown tables of run --run (default: the newest) of results/suite_<machine>.jsonl,
    one row per scene, times as ratios to the peers of the same run. --run newest: the
    standing, each scene's newest record at the newest record's size (a column names its run;
    each row's ratios are still those of its own run)."""
    recs = _records.load("suite", a.machine)
    standing = a.run == "newest"
    if standing:
        size = recs[-1]["log2"] if recs else None
        recs = _records.newest([r for r in recs if r.get("log2") == size], "scene")
    else:
        recs = _records.run_of(recs, a.run)
    if recs:
        mode = "cpu" if a.machine == "cpu" else "gpu"
        r0 = recs[0]
        if standing and not a.brief:
            print(f"The newest record of each scene at 2^{r0['log2']}, {r0['device']}:\n")
        elif not a.brief:
            print(
                f"{mode.upper()} run {r0['run']} ({r0['device']}, {r0['date']}, commit "
                f"{_records.commit(r0)}): `{r0['command']}`\n"
            )
        if mode == "gpu":
            print(
                "| scene | faces | slaves | ours (Warp, graph) | wp.Mesh refit + query | "
                "build + query | ours / refit | ours / build | misses | wrong faces | "
                "gap error / edge |" + " run |" * standing
            )
            print("|---|---|---|---|---|---|---|---|---|---|---|" + "---|" * standing)
            for r in recs:
                e = r["errors"]
                print(
                    f"| {r['scene']} | {r['n_faces']} | {r['n_slaves']} | "
                    f"{1e3 * r['steady_s']:.2f} ms | {1e3 * r['mesh_refit_query_s']:.2f} ms | "
                    f"{1e3 * r['mesh_build_query_s']:.2f} ms | {r['vs_refit']:.2f} | "
                    f"{r['vs_build']:.2f} | {e['miss_rate']:.0%} | {e['wrong_face_rate']:.0%} "
                    f"| {e['max_gap_error_rel']:.1e} |" + f" {r['run']} |" * standing
                )
        else:
            fresh = any("warp_cpu_float32_new_s" in r for r in recs)  # runs since cpu-s13
            new_head, new_ratio_head = (
                ("new Surface | ", "new Surface / fcpw | ") if fresh else ("", "")
            )
            print(
                f"| scene | faces | slaves | ours (Warp CPU, one call) | {new_head}"
                f"fcpw build + query | libigl | ours / fcpw | {new_ratio_head}misses | "
                "wrong faces |"
            )
            print("|---|---|---|---|---|---|---|---|---|" + "---|---|" * fresh)
            for r in recs:
                best = min(
                    v
                    for k, v in r.items()
                    if k.endswith("_s")
                    and k.startswith(("warp_cpu", "numpy"))
                    and not k.endswith(("detect_s", "plan_s", "new_s"))
                )
                new = r.get("warp_cpu_float32_new_s")
                new_ms = new_ratio = ""
                if fresh:
                    new_ms = "- | " if new is None else f"{1e3 * new:.1f} ms | "
                    new_ratio = "- | " if new is None else f"{r['new_vs_fcpw']:.2f} | "
                e = r["errors"]
                print(
                    f"| {r['scene']} | {r['n_faces']} | {r['n_slaves']} | {1e3 * best:.1f} ms | "
                    f"{new_ms}{1e3 * r['fcpw_s']:.1f} ms | {1e3 * r['libigl_s']:.1f} ms | "
                    f"{r['vs_fcpw']:.2f} | {new_ratio}{e['miss_rate']:.0%} | "
                    f"{e['wrong_face_rate']:.0%} |"
                )
        if mode == "cpu" and all("warp_bvh_build_query_s" in r for r in recs):
            print(
                "\nWarp's BVH on the CPU device (`wp.Mesh`, one launch: Warp runs it on one "
                "core; ours splits its per-slave launches over the cores), same run:\n\n"
                "| scene | wp.Mesh build + query | refit + query | ours / build + query | "
                "ours / refit + query |\n|---|---|---|---|---|"
            )
            for r in recs:
                ours = r["vs_fcpw"] * r["fcpw_s"]
                b, f = r["warp_bvh_build_query_s"], r["warp_bvh_refit_query_s"]
                print(
                    f"| {r['scene']} | {1e3 * b:.1f} ms | {1e3 * f:.1f} ms | {ours / b:.2f} | "
                    f"{ours / f:.2f} |"
                )
        if a.brief:
            return
        _setup_table(mode, recs)
        if mode == "gpu" and any("jax_steady_s" in r for r in recs):
            print(
                '\nJAX without Warp (`search="jax"`), same run:\n\n'
                "| scene | detect | value_and_grad | / Warp back end | plan | plan again | "
                "first call | candidates a slave (max) | misses | wrong faces |\n"
                "|---|---|---|---|---|---|---|---|---|---|"
            )
            for r in recs:
                if "jax_steady_s" not in r:
                    continue
                e = r["jax_errors"]
                again = f"{r['jax_plan_again_s']:.2f} s" if "jax_plan_again_s" in r else "-"
                print(
                    f"| {r['scene']} | {1e3 * r['jax_steady_s']:.1f} ms | "
                    f"{1e3 * r['jax_value_and_grad_s']:.1f} ms | {r['jax_vs_warp']:.1f} | "
                    f"{r['jax_plan_s']:.2f} s | {again} | {r['jax_first_s']:.2f} s | "
                    f"{r['jax_counts'].get('face_candidates', '-')} | {e['miss_rate']:.0%} | "
                    f"{e['wrong_face_rate']:.0%} |"
                )


def _setup_table(mode, recs):
    """Set-up times of the run: the Surface topology and the plans (and, on the CPU, their
    ratio to fcpw's whole build + query)."""
    if not any("topology_s" in r for r in recs):
        return
    if mode == "gpu":
        if "replan_s" not in recs[0]:  # runs before the plan made its topology on the device
            print("\nSet-up, same run (host: topology; Warp plan on the GPU, with its topology):\n")
            print("| scene | Surface topology | Warp plan | first detect | steady |")
            print("|---|---|---|---|---|")
            for r in recs:
                if "topology_s" in r:
                    print(
                        f"| {r['scene']} | {r['topology_s']:.2f} s | {r['plan_s']:.2f} s | "
                        f"{1e3 * r['first_s']:.1f} ms | {1e3 * r['steady_s']:.2f} ms |"
                    )
            return
        print(
            f"\nSet-up, same run (kernels compiled first: {recs[0]['compile_s']:.1f} s). Warp "
            "plan: of a Surface new to it, its topology made on the GPU; again: a second plan of "
            "that Surface. Surface: the constructor's validation (host). Host topology: the "
            "Surface's own NumPy tables, which the Warp plan no longer reads.\n"
        )
        one = any("one_shot_s" in r for r in recs)
        if one:
            print(
                'One call: `ac.detect(slave, Surface(points, faces), backend="warp")` on a '
                "Surface made for it, host arrays in and out (the Surface's validation, the "
                "topology, plan, detect and the copies).\n"
            )
        new = any("new_buffers_s" in r for r in recs)
        if new:
            print(
                "New buffers: a detect on input buffers new to the plan (launched one by one, "
                "the trees' rebuild decided on the device).\n"
            )
        deformed = any("deformed_plan_s" in r for r in recs)
        if deformed:
            print(
                "Deformed: the plan of `Surface.with_points` of the planned Surface (the device "
                "tables of its connectivity shared, its geometry made).\n"
            )
        print(
            "| scene | Warp plan | again | "
            + ("deformed | " if deformed else "")
            + "first detect | steady | first / steady | "
            + ("new buffers | " if new else "")
            + "Surface | host topology |"
            + (" one call |" if one else "")
        )
        print(
            "|---|---|---|---|---|---|---|---|"
            + ("---|" if one else "")
            + ("---|" if new else "")
            + ("---|" if deformed else "")
        )
        for r in recs:
            tail = f" {1e3 * r['one_shot_s']:.0f} ms |" if "one_shot_s" in r else (" - |" * one)
            nb = ""
            if new:
                nb = f" {1e3 * r['new_buffers_s']:.2f} ms |" if "new_buffers_s" in r else " - |"
            df = ""
            if deformed:
                df = f" {1e3 * r['deformed_plan_s']:.1f} ms |" if "deformed_plan_s" in r else " - |"
            print(
                f"| {r['scene']} | {1e3 * r['plan_s']:.1f} ms | {1e3 * r['replan_s']:.1f} ms |{df} "
                f"{1e3 * r['first_s']:.2f} ms | {1e3 * r['steady_s']:.2f} ms | "
                f"{r['first_s'] / r['steady_s']:.1f} |{nb} {1e3 * r['surface_s']:.0f} ms | "
                f"{r['topology_s']:.2f} s |" + tail
            )
        return
    print("\nSet-up against fcpw's whole build + query of the same scene, same run:\n")
    deformed = any("warp_cpu_float32_deformed_plan" in r.get("setup_vs_fcpw", {}) for r in recs)
    print(
        "| scene | Surface topology | Warp plan | "
        + ("Warp plan, deformed | " if deformed else "")
        + "JAX plan (jax) | JAX plan (warp) |"
    )
    print("|---|---|---|---|---|" + ("---|" if deformed else ""))
    for r in recs:
        if "setup_vs_fcpw" in r:
            v = r["setup_vs_fcpw"]
            df = ""
            if deformed:
                x = v.get("warp_cpu_float32_deformed_plan")
                df = " -" if x is None else f" {x:.2f}x"
                df += " |"
            print(
                f"| {r['scene']} | {v['topology']:.2f}x | {v['warp_cpu_float32_plan']:.2f}x |{df} "
                f"{v['jax_jax_plan']:.2f}x | {v['jax_warp_plan']:.2f}x |"
            )


def main():
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("mode", choices=("scenes", "gpu", "cpu", "table"))
    ap.add_argument("--log2", type=int, default=20)
    ap.add_argument("--repeats", type=int, default=10)
    ap.add_argument("--check", type=int, default=64, help="slaves checked against the reference")
    ap.add_argument("--only", nargs="*", help="scene labels (prefixes) to run")
    ap.add_argument("--no-numpy", action="store_true")
    ap.add_argument(
        "--jax",
        action="store_true",
        help="gpu: also the JAX back end with search='jax' (no Warp); JAX in the process slows "
        "the Warp set-up's figures (plan, first detect) up to 2x: take those from a run without",
    )
    ap.add_argument("--run", help="run id recorded with every record (table: the run shown)")
    ap.add_argument("--machine", default="h100", help="table: the records' machine (cpu, h100)")
    ap.add_argument("--brief", action="store_true", help="table: the main table alone")
    ap.add_argument("--out", help="folder for suite_<machine>.jsonl (default benchmarks/results)")
    a = ap.parse_args()
    {"scenes": lambda a: make_scenes(), "gpu": run_gpu, "cpu": run_cpu, "table": table}[a.mode](a)


if __name__ == "__main__":
    main()
