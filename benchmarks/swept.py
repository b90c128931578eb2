"""Swept detection (issue 22): detect_swept against the static detection of the same step's
end, same run, same device; on the CPU also IPC Toolkit (`ipctk`) on the same trajectories.

    python benchmarks/swept.py --log2 20 --device cuda --out DIR     # a GPU machine
    python benchmarks/swept.py --log2 14 --device cpu --ipctk --out DIR

Scenes (arraycontact.scenes, each about 2^k slaves and as many master nodes): rough surfaces
closing within the step (tri3 and quad4; closing 1.6 gaps, and 0.4 and 6.4 for a motion
sweep), steep rough surfaces closing, graded surfaces (size ratio 100) closing, and a tyre
rolling onto a road; with --only, the rough surfaces of tri6, quad8 and quad9 faces closing.
For each:
  - swept: arraycontact_warp.plan_swept / detect_swept steady state (device arrays in place;
    on a GPU its launches replayed as one CUDA graph, like detect's own), first call;
  - static: arraycontact_warp.plan / detect of the step's end (default d_max), steady state;
  - swept / static (target: at most 2), the two steady states timed in turn, medians (a
    shared machine's load moves over a run: in turn both see the same);
  - ipctk (--ipctk, CPU): its CCD broad phase (Candidates.build, the fastest of its HashGrid,
    LBVH and SweepAndPrune in the run) and narrow phase: compute_collision_free_stepsize (C++,
    one global step, not per node) and, for per-node times of impact, each slave-face
    candidate's ccd through its Python API; agreement of its per-node toi with ours;
  - the check of a random subset of rows against reference.swept (hits, toi within
    [exact - t_tol, exact], face hit at that time).
One JSON record per scene and size to DIR/swept_<machine>.jsonl (default DIR: results/);

    python benchmarks/swept.py --table [MACHINE ...]

prints them as the markdown table of RESULTS.md.
"""

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

import arraycontact as ac
from arraycontact import scenes
from arraycontact._backends import quiet_warp

sys.path.insert(0, str(Path(__file__).parent))
import _records  # noqa: E402
from peers_warp import alternating, timed  # noqa: E402


def steps(n):
    return {
        "rough_tri3": lambda: scenes.closing_rough_surfaces(n),
        "rough_quad4": lambda: scenes.closing_rough_surfaces(n, element="quad4"),
        "rough_slow": lambda: scenes.closing_rough_surfaces(n, closing=0.4),
        "rough_fast": lambda: scenes.closing_rough_surfaces(n, closing=6.4),
        "steep": lambda: scenes.closing_step(scenes.steep_rough_surfaces(n)),
        "graded_100": lambda: scenes.closing_step(scenes.graded_surfaces(n, ratio=100.0)),
        "tyre": lambda: scenes.rolling_tyre(n, drop=1.2),
        **{
            name: lambda e=e: scenes.closing_rough_surfaces(n, element=e)
            for name, e in CURVED.items()
        },
    }


#: Curved faces (the certified search on Bernstein hulls), run only when named (--only): not
#: in the suite's default scenes.
CURVED = {f"rough_{e}": e for e in ("tri6", "quad8", "quad9")}


def warp_swept(st, device, repeats):
    import arraycontact_warp as acw
    import warp as wp

    t0 = time.perf_counter()
    p = acw.plan_swept(st.master, st.slave_x0, device=device)
    plan_s = time.perf_counter() - t0

    def arr(x):
        return wp.array((x - p.origin).astype(np.float32), dtype=wp.vec3, device=device)

    xs = [arr(st.slave_x0), arr(st.slave_x1), arr(st.master.points), arr(st.master_x1)]
    p.origin = np.zeros(3)  # the arrays are in the plan's frame already
    first, plain = timed(lambda: acw.detect_swept(p, *xs), repeats, device)
    rec = dict(plan_s=plan_s, first_call_s=first, steady_no_graph_s=plain)
    out = {k: v.numpy() for k, v in p.out.items()}
    # The (slave, face) pairs the capture test gave (GPU: the pair list's need; 0 on the CPU,
    # which searches one thread a slave without a list).
    rec["pairs_per_slave"] = p.pairs_needed() / len(st.slave_x0)
    return out, rec, lambda: acw.detect_swept(p, *xs)


def replayed(call, device):
    """call's launches as a CUDA graph on a GPU (launched once: instantiated), else call.
    The graph holds call (its plan and arrays): a graph keeps no array alive, and one whose
    plan was collected replays on freed memory (an illegal access once another plan
    reuses it)."""
    import warp as wp

    if not wp.get_device(device).is_cuda:
        return call
    with wp.ScopedCapture(device=device) as cap:
        call()
    wp.capture_launch(cap.graph)

    def launch(graph=cap.graph, keep=call):
        wp.capture_launch(graph)

    return launch


def warp_static(st, device):
    import arraycontact_warp as acw
    import warp as wp

    m1 = st.master.with_points(st.master_x1)
    p = acw.plan(m1, st.slave_x1, device=device)
    xs = wp.array((st.slave_x1 - p.origin).astype(np.float32), dtype=wp.vec3, device=device)
    xm = wp.array((st.master_x1 - p.origin).astype(np.float32), dtype=wp.vec3, device=device)
    p.origin = np.zeros(3)
    for _ in range(2):  # (the second call captures the graph the next ones replay)
        acw.detect(p, xs, xm)
    return lambda: acw.detect(p, xs, xm)


def ipctk_peer(st, ours, n_check_rows):
    """IPC Toolkit on the same step: slaves as isolated vertices of one collision mesh with the
    master's faces and edges (it also checks the master against itself: its API has no
    two-body mode but a per-pair Python callback). Quads are split into two triangles, so on
    quad4 scenes its times of impact are of another surface (agreement not comparable)."""
    import ipctk

    m = st.master
    nm = len(m.points)
    v0 = np.asfortranarray(np.r_[m.points, st.slave_x0])
    v1 = np.asfortranarray(np.r_[st.master_x1, st.slave_x1])
    tris = m.faces
    if m.element.name == "quad4":  # ipctk takes triangles: each quad as two (not bilinear)
        tris = np.r_[m.faces[:, [0, 1, 2]], m.faces[:, [0, 2, 3]]]
    elif m.element.name != "tri3":
        raise ValueError("the ipctk peer takes tri3 or quad4 masters")
    mesh = ipctk.CollisionMesh(v0, ipctk.edges(tris), tris)
    best = None
    for bp in (ipctk.HashGrid, ipctk.LBVH, ipctk.SweepAndPrune):
        cand = ipctk.Candidates()
        t0 = time.perf_counter()
        cand.build(mesh, v0, v1, 0.0, bp())
        t = time.perf_counter() - t0
        if best is None or t < best[1]:
            best = (bp.__name__, t, cand)
    name, build_s, cand = best
    t0 = time.perf_counter()
    cand.compute_collision_free_stepsize(mesh, v0, v1)
    step_s = time.perf_counter() - t0
    fv = [c for c in cand.fv_candidates if c.vertex_id >= nm]
    t0 = time.perf_counter()
    toi = np.full(len(st.slave_x0), np.inf)
    for c in fv:
        ids = c.vertex_ids(mesh.edges, mesh.faces)
        hit, t = c.ccd(v0[list(ids)].ravel(), v1[list(ids)].ravel())
        if hit:
            s = c.vertex_id - nm
            toi[s] = min(toi[s], t)
    per_node_s = time.perf_counter() - t0
    hit = np.isfinite(toi)
    both = hit & ours["hit"].astype(bool)
    return dict(
        ipctk_broad_phase=name,
        ipctk_build_s=build_s,
        ipctk_stepsize_s=step_s,
        ipctk_per_node_s=per_node_s,
        ipctk_fv_candidates=len(fv),
        ipctk_hits=int(hit.sum()),
        ipctk_hit_disagree=int((hit != ours["hit"].astype(bool)).sum()),
        ipctk_max_toi_diff=float(np.abs(toi[both] - ours["toi"][both]).max()) if both.any() else 0,
    )


def check(out, st, n_check, seed=0):
    """Random rows against reference.swept: hits that differ, toi after the exact one or more
    than t_tol (float32: 1e-4) before it, faces not hit at the reported time's band."""
    n = len(st.slave_x0)
    rows = np.sort(np.random.default_rng(seed).choice(n, min(n_check, n), replace=False))
    ref = ac.reference.swept(st.slave_x0[rows], st.slave_x1[rows], st.master, st.master_x1)
    hit = out["hit"][rows].astype(bool)
    toi = out["toi"][rows].astype(float)
    face = out["face"][rows]
    h = hit & ref.hit
    t_tol = 1e-4
    wrong = [
        i
        for i in np.nonzero(h)[0]
        if ref.pair_toi.get((int(i), int(face[i])), np.inf) > ref.toi[i] + 2 * t_tol
    ]
    return dict(
        checked=len(rows),
        ref_hits=int(ref.hit.sum()),
        hit_disagree=int((hit != ref.hit).sum()),
        late=int((toi[h] > ref.toi[h] + 1e-9).sum()),
        early=int((toi[h] < ref.toi[h] - t_tol - 1e-9).sum()),
        wrong_faces=len(wrong),
    )


def run(name, n, device, repeats, n_check, with_ipctk):
    st = steps(n)[name]()
    out, rec, swept = warp_swept(st, device, repeats)
    static = warp_static(st, device)
    swept = replayed(swept, device)
    rec["steady_s"], rec["static_steady_s"] = alternating([swept, static], repeats, device)
    rec["swept_over_static"] = rec["steady_s"] / rec["static_steady_s"]
    rec["hits"] = int(out["hit"].sum())
    rec["visits_per_hit"] = float(out["visits"].sum() / max(rec["hits"], 1))
    rec["not_converged"] = int(((out["converged"] == 0) & (out["hit"] == 1)).sum())
    if n_check:
        rec.update(check(out, st, n_check))
    if with_ipctk:
        rec.update(ipctk_peer(st, out, n_check))
        rec["swept_over_ipctk"] = rec["steady_s"] / (rec["ipctk_build_s"] + rec["ipctk_stepsize_s"])
    return dict(
        scene=name,
        element=st.master.element.name,
        slaves=len(st.slave_x0),
        faces=st.master.n_faces,
        dtype="float32",
        **rec,
    )


def table(machines):
    """The newest record of each scene and size on each machine, as a markdown table."""
    recs = [r for m in machines for r in _records.load("swept", m)]
    print(
        "| run | commit | device | scene | slaves | faces | swept ms | static ms |"
        " swept / static | hits | visits / hit | ipctk build + step ms | ipctk per node s |"
        " swept / ipctk | checked | hit diff | late | early | wrong face |"
    )
    print("|" + "---|" * 19)
    for r in _records.newest(recs, "device", "scene", "slaves"):
        ip = r.get("ipctk_build_s")
        if ip is None:
            peer = "- | - | -"
        else:
            peer = (
                f"{(ip + r['ipctk_stepsize_s']) * 1e3:.1f} | {r['ipctk_per_node_s']:.2f} |"
                f" {r['swept_over_ipctk']:.2f}"
            )
        print(
            f"| {r['run']} | {_records.commit(r)} | {r['device']} | {r['scene']} |"
            f" {r['slaves']} | {r['faces']} | {r['steady_s'] * 1e3:.2f} |"
            f" {r['static_steady_s'] * 1e3:.2f} | {r['swept_over_static']:.2f} |"
            f" {r['hits']} | {r['visits_per_hit']:.0f} | {peer} |"
            f" {r.get('checked', 0)} | {r.get('hit_disagree', '-')} | {r.get('late', '-')} |"
            f" {r.get('early', '-')} | {r.get('wrong_faces', '-')} |"
        )


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--log2", type=int, nargs="+", default=[16])
    ap.add_argument("--only", nargs="*", default=None)
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--repeats", type=int, default=10)
    ap.add_argument("--check", type=int, default=256)
    ap.add_argument("--ipctk", action="store_true")
    ap.add_argument("--out", default=None)
    ap.add_argument("--run", default=None, help="run id recorded with every record")
    ap.add_argument(
        "--table", nargs="*", help="print the records of these machines (default all) as a table"
    )
    args = ap.parse_args()
    if args.table is not None:
        return table(args.table or ["*"])
    quiet_warp()
    import warp as wp

    device = wp.get_device(args.device)
    meta = _records.meta(args.run)
    for k in args.log2:
        for name in args.only or [n for n in steps(2**k) if n not in CURVED]:
            r = run(name, 2**k, device, args.repeats, args.check, args.ipctk)
            r["device"] = device.name if device.is_cpu else wp.get_cuda_device().name
            print(json.dumps(r), flush=True)
            _records.append("swept", r, meta, out=args.out)


if __name__ == "__main__":
    main()
