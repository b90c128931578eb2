"""Self-contact (issue 21): detect_self against the two-body detection of the same node and
face counts, same run, same device.

    python benchmarks/self_contact.py --log2 17 20 --device cuda --out DIR   # a GPU machine
    python benchmarks/self_contact.py --log2 16 --device cpu --out DIR      # Warp on the CPU

For each self-contact scene of arraycontact.scenes (quad4, or `--element`; about 2^k nodes)
and size:
  - self: arraycontact_warp.plan_self / detect_self, steady state (device arrays in place,
    detect's CUDA graph on a GPU), first call, plan time;
  - two-body, same counts: two rough surfaces (the same element) with as many master faces
    and slaves,
    plan / detect as a simulator calls it;
  - two-body, same geometry: the surface's nodes as slaves of the surface itself by the
    two-body rule (every node on its own faces at distance 0: the cheapest possible answer);
  - the ratio self / two-body (target: at most 1.5; the three steady states timed in turn,
    medians, so that a shared machine's load moves them alike), and the check of a random
    subset of rows against reference.closest_points_self (misses, wrong faces, gap error /
    longest edge).
--jax: also arraycontact_jax.plan_self / detect_self (search "jax", float32) steady.
--snail: the spiral strip at 130,000 nodes (seed 000 Fig. 12: 30 s in 2012).
One JSON record per scene and size to DIR/self_contact_<machine>.jsonl (default DIR: results/).

    python benchmarks/self_contact.py --table [MACHINE ...]

prints the records as the markdown table of RESULTS.md.
"""

import argparse
import json
import os
import statistics
import sys
import time
from pathlib import Path

import numpy as np

import arraycontact as ac
from arraycontact._backends import quiet_warp

sys.path.insert(0, str(Path(__file__).parent))
import _records  # noqa: E402
from peers_warp import alternating, timed  # noqa: E402

SCENES = ("spiral_strip", "folded_sheet", "coil_spring", "crumpled_sheet", "two_bodies")


def warp_self(surface, d_max, device):
    """(outputs, plan and first-call times, the steady call, the float32 points it saw)."""
    import arraycontact_warp as acw
    import warp as wp

    t0 = time.perf_counter()
    p = acw.plan_self(surface, d_max=d_max, device=device)
    plan_s = time.perf_counter() - t0
    x32 = (surface.points - p.origin).astype(np.float32)
    x = wp.array(x32, dtype=wp.vec3, device=device)
    seen = x32.astype(np.float64) + p.origin  # (the points as the detection saw them)
    p.origin = np.zeros(3)  # x is already in the plan's frame
    first, _ = timed(lambda: acw.detect_self(p, x), 1, device)
    out = {k: v.numpy() for k, v in p.out.items()}
    rec = dict(plan_s=plan_s, first_call_s=first)
    return out, rec, lambda: acw.detect_self(p, x), seen


def warp_two_body(master, slaves, d_max, device):
    """The two-body detection's steady call (its graph captured on a GPU)."""
    import arraycontact_warp as acw
    import warp as wp

    p = acw.plan(master, slaves, d_max=d_max, device=device)
    xs = wp.array((slaves - p.origin).astype(np.float32), dtype=wp.vec3, device=device)
    xm = wp.array((master.points - p.origin).astype(np.float32), dtype=wp.vec3, device=device)
    p.origin = np.zeros(3)
    for _ in range(2):  # (the second call captures the graph the next ones replay)
        acw.detect(p, xs, xm)
    return lambda: acw.detect(p, xs, xm)


def jax_self(surface, d_max, repeats):
    import arraycontact_jax as acj
    import jax
    import jax.numpy as jnp

    t0 = time.perf_counter()
    p = acj.plan_self(surface, d_max=d_max, dtype=np.float32)
    plan_s = time.perf_counter() - t0
    x = jax.device_put(jnp.asarray(surface.points, jnp.float32))
    t0 = time.perf_counter()
    jax.block_until_ready(acj.detect_self(p, x))
    first = time.perf_counter() - t0
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        c = jax.block_until_ready(acj.detect_self(p, x))
        times.append(time.perf_counter() - t0)
    return dict(
        jax_plan_s=plan_s,
        jax_first_call_s=first,
        jax_steady_s=statistics.median(times),
        jax_overflow=bool(c.overflow),
    )


def check(out, surface, d_max, n_check, seen=None, seed=0):
    """The Warp answer on random rows against the brute-force reference. A wrong face: one
    whose closest point is farther than the reference's by more than float32's tie tolerance
    (2e-5 of the longest edge), or that does not face the node; `other_tied_face` counts the
    equidistant faces chosen other than the reference's smallest id (float32 ties).
    `input_rounding` counts the rows of another face or gap whose gap is the reference's on
    `seen`, the float32 points the detection was given (to 5e-6 of the longest edge): where
    a face stands almost at right angles to the node's normal, rounding the points to float32
    turns it by more than the facing test's 1e-6 (a folded sheet's rounded fold, a coil's end
    caps), and the face counts on one side of the rounding and not on the other; so do the
    rows active on one side only (misses or extra rows that the reference on `seen` makes
    alike). Those rows are neither wrong, missed nor in the gap error."""
    from arraycontact._elements import interpolate
    from arraycontact.reference import _closest_on_faces

    rows = np.sort(np.random.default_rng(seed).choice(len(surface.nodes), n_check, replace=False))
    ref = ac.reference.closest_points_self(surface, d_max=d_max, rows=rows)
    L = surface.longest_edge
    want = ref.distance <= d_max
    near = np.abs(ref.distance - d_max) <= 1e-5 * L
    active = out["active"][rows].astype(bool)
    a = active & want
    rounded = None if seen is None else ac.Surface(seen, surface.faces, surface.element.name)
    # A row active on one side of the rounding only (its one admissible face in reach standing
    # at right angles to the node's normal) is input rounding too, as the reference on the
    # points seen says.
    flip = (active != want) & ~near
    flipped = np.zeros_like(flip)
    if flip.any() and rounded is not None:
        again = ac.reference.closest_points_self(rounded, d_max=d_max, rows=rows[flip])
        flipped[flip] = (again.distance <= d_max) == active[flip]
    rec = dict(
        checked=int(n_check),
        misses=int((want & ~active & ~near & ~flipped).sum()),
        extra=int((active & ~want & ~near & ~flipped).sum()),
        wrong_faces=0,
        other_tied_face=0,
        input_rounding=int(flipped.sum()),
        max_gap_err_rel=0.0,
    )
    if a.any():
        ids = surface.nodes[rows][a]
        f = out["face"][rows][a]
        xe = surface.points[surface.faces[f]]
        _, d2 = _closest_on_faces(surface.element, surface.points[ids], xe)
        far = np.sqrt(d2) - ref.distance[a] > 2e-5 * L
        _, dx = interpolate(surface.element, xe, out["xi"][rows][a].astype(float))
        nf = np.cross(dx[..., 0], dx[..., 1])
        nf /= np.linalg.norm(nf, axis=-1, keepdims=True)
        away = np.einsum("pk,pk->p", surface.node_normals[ids], nf) > 1e-4
        err = np.abs(out["gap"][rows][a] - ref.gap[a])
        odd = far | away | (err > 2e-5 * L)
        rounding = np.zeros_like(odd)
        if odd.any() and rounded is not None:
            again = ac.reference.closest_points_self(rounded, d_max=d_max, rows=rows[a][odd])
            # (the gap agrees to float32's tie band: a gap error on the same face is no
            # rounding of the input)
            rounding[odd] = np.abs(out["gap"][rows][a][odd] - again.gap) <= 5e-6 * L
        rec["wrong_faces"] = int(((far | away) & ~rounding).sum())
        rec["other_tied_face"] = int(((f != ref.face[a]) & ~far & ~away & ~rounding).sum())
        rec["input_rounding"] += int(rounding.sum())
        rec["max_gap_err_rel"] = float(err[~rounding].max(initial=0.0) / L)
    return rec


def run(name, n, device, repeats, n_check, with_jax, element="quad4"):
    sc = getattr(ac.scenes, name)(n, element=element)
    s, d = sc.master, sc.params["d_max"]
    out, rec, self_call, seen = warp_self(s, d, device)
    counts = dict(nodes=len(s.nodes), faces=s.n_faces)
    # Two rough surfaces of the element with as many master faces and slaves.
    rough = ac.scenes.rough_surfaces(len(s.nodes), element=element)
    two_body = warp_two_body(rough.master, rough.slave, None, device)
    rec["two_body_counts"] = dict(nodes=len(rough.slave), faces=rough.master.n_faces)
    same = warp_two_body(s, s.points[s.nodes], d, device)
    # The three steady states timed in turn (medians): a shared machine's load moves all alike.
    times = alternating([self_call, two_body, same], repeats, device)
    rec["steady_s"], rec["two_body_steady_s"], rec["same_geometry_steady_s"] = times
    rec["self_over_two_body"] = rec["steady_s"] / rec["two_body_steady_s"]
    rec["self_over_same_geometry"] = rec["steady_s"] / rec["same_geometry_steady_s"]
    rec["active"] = int(out["active"].sum())
    if n_check:
        rec.update(check(out, s, d, min(n_check, len(s.nodes)), seen))
    if with_jax:
        rec.update(jax_self(s, d, repeats))
    return dict(scene=name, element=element, **counts, d_max=d, dtype="float32", **rec)


def table(machines):
    """The newest record of each scene and size on each machine, as a markdown table."""
    recs = [r for m in machines for r in _records.load("self_contact", m)]
    print(
        "| run | commit | device | scene | element | nodes | self ms | two-body ms |"
        " self / two-body | same geometry ms | self / same geometry | checked | miss |"
        " wrong face | tied face | input rounding | max gap err / edge |"
    )
    print("|" + "---|" * 17)
    for r in recs:
        r.setdefault("element", "quad4")  # (the records before --element)
    for r in _records.newest(recs, "device", "scene", "element", "nodes"):
        print(
            f"| {r['run']} | {_records.commit(r)} | {r['device']} | {r['scene']} | {r['element']} |"
            f" {r['nodes']} | {r['steady_s'] * 1e3:.2f} | {r['two_body_steady_s'] * 1e3:.2f} |"
            f" {r['self_over_two_body']:.2f} | {r['same_geometry_steady_s'] * 1e3:.2f} |"
            f" {r['self_over_same_geometry']:.2f} | {r.get('checked', 0)} |"
            f" {r.get('misses', '-')} | {r.get('wrong_faces', '-')} |"
            f" {r.get('other_tied_face', '-')} | {r.get('input_rounding', '-')} |"
            f" {r.get('max_gap_err_rel', 0):.1e} |"
        )


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--log2", type=int, nargs="+", default=[16])
    ap.add_argument("--only", nargs="*", default=list(SCENES))
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--repeats", type=int, default=10)
    ap.add_argument("--check", type=int, default=256)
    ap.add_argument("--element", default="quad4", help="the scenes' faces (and the two-body's)")
    ap.add_argument("--jax", action="store_true")
    ap.add_argument("--snail", action="store_true")
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
    jobs = [(name, 2**k) for k in args.log2 for name in args.only]
    if args.snail:
        jobs.append(("spiral_strip", 130_000))
    meta = _records.meta(args.run)
    for name, n in jobs:
        r = run(name, n, device, args.repeats, args.check, args.jax, args.element)
        r.update(device=device.name, host_cores=os.cpu_count())
        print(json.dumps(r), flush=True)
        _records.append("self_contact", r, meta, out=args.out)


if __name__ == "__main__":
    main()
