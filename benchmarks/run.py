"""The benchmark runner: scenes as data, one record per (scene, size, back end, dtype, mode).

    python benchmarks/run.py cpu            # issue 3: 2^16 and 2^20 nodes per surface, CPU
    python benchmarks/run.py cpu --sizes 12 14 --quick

Every record holds the scene, sizes, back end, device, dtype, mode, the first call (compile
and caches) apart from the steady state (median of repeats), the time per stage where the back
end reports it, contact counts, and the error against the brute-force reference on a random
subset of slaves (miss rate, wrong-face rate, largest gap error relative to the longest edge).
Peers are timed in the same run on the same points: scipy's cKDTree closest-node search.
Records are appended to benchmarks/results/<suite>.jsonl and summarised on stdout.
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import time
from pathlib import Path

import numpy as np

import arraycontact as ac

HERE = Path(__file__).parent

# Scenes as data: name -> (generator, keyword arguments). Sizes are added per run.
SCENES = {
    "rough_close": ("rough_surfaces", dict(gap=1.0, rms=0.5)),
    "rough_quad4": ("rough_surfaces", dict(gap=1.0, rms=0.5, element="quad4")),
    "tyre_road": ("cylinder_on_road", dict(radius=40.0, depth=0.5)),
}

SUITES = {
    "cpu": dict(scenes=["rough_close"], sizes=[16, 20],
                runs=[("numpy", "float64", "exact"), ("numpy", "float64", "node"),
                      ("numpy", "float32", "exact"), ("jax", "float32", "exact")]),
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
        _, d2 = _closest_on_faces(scene.master.element, scene.slave[idx][both],
                                  scene.master.points[scene.master.faces[c.face[idx][both]]])
        tol = (2e-5 if dtype == "float32" else 1e-9) * L  # the dtype's tie tolerance
        wrong = float((np.sqrt(d2) - ref.distance[both] > tol).mean())
        gap_err = float(np.abs(c.gap[idx][both] - ref.gap[both]).max() / L)
    return dict(checked=int(len(idx)), miss_rate=miss, extra_rate=extra, wrong_face_rate=wrong,
                max_gap_error_rel=gap_err)


def kdtree_peer(scene, d_max, repeats):
    from scipy.spatial import cKDTree

    nodes = scene.master.points[scene.master.nodes]

    def run():
        tree = cKDTree(nodes)
        return tree.query(scene.slave, distance_upper_bound=d_max)

    _, first, steady = timed(run, repeats)
    return dict(peer="scipy cKDTree closest node (build + query)", first_s=first, steady_s=steady)


def run_suite(suite, sizes=None, repeats=2, n_check=512, out=None):
    cfg = SUITES[suite]
    records = []
    device = f"cpu: {platform.processor() or platform.machine()}, {_cores()} cores"
    for scene_name in cfg["scenes"]:
        for log2n in sizes or cfg["sizes"]:
            scene = make_scene(scene_name, log2n)
            peer = None
            for backend, dtype, mode in cfg["runs"]:
                c, first, steady = timed(
                    lambda: ac.detect(scene.slave, scene.master, backend=backend, mode=mode,
                                      dtype=dtype), repeats)
                if peer is None:
                    peer = kdtree_peer(scene, c.d_max, repeats)
                rec = dict(suite=suite, scene=scene_name, log2_nodes=log2n,
                           n_slaves=len(scene.slave), n_master_faces=scene.master.n_faces,
                           element=scene.master.element.name, backend=backend, device=device,
                           dtype=dtype, mode=mode, first_call_s=first, steady_s=steady,
                           stages_s={k: v for k, v in c.timings.items()},
                           active=int(c.active.sum()), counts=c.counts.count,
                           errors=errors(c, scene, n_check, dtype), peer=peer,
                           ratio_to_peer=steady / peer["steady_s"])
                records.append(rec)
                _print(rec)
    if out:
        with open(out, "a") as f:
            for r in records:
                f.write(json.dumps(r) + "\n")
    return records


def _cores():
    import os

    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()


def _print(r):
    st = ", ".join(f"{k} {v * 1e3:.0f}" for k, v in r["stages_s"].items()
                   if k not in ("detect", "total"))
    e = r["errors"]
    print(f"{r['scene']} 2^{r['log2_nodes']} {r['backend']:5s} {r['dtype']} {r['mode']:5s} | "
          f"first {r['first_call_s']:.3f} s, steady {r['steady_s']:.3f} s "
          f"({r['ratio_to_peer']:.1f}x cKDTree {r['peer']['steady_s']:.3f} s) | "
          f"active {r['active']} | miss {e['miss_rate']:.2g} wrong face "
          f"{e['wrong_face_rate']:.2g} gap err {e['max_gap_error_rel']:.2g}"
          + (f" | stages ms: {st}" if st else ""), flush=True)


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("suite", choices=sorted(SUITES))
    p.add_argument("--sizes", type=int, nargs="*", help="log2 of the nodes per surface")
    p.add_argument("--repeats", type=int, default=2)
    p.add_argument("--check", type=int, default=512, help="slaves checked against the reference")
    p.add_argument("--no-save", action="store_true")
    a = p.parse_args()
    out = None if a.no_save else HERE / "results" / f"{a.suite}.jsonl"
    if out:
        out.parent.mkdir(exist_ok=True)
    run_suite(a.suite, a.sizes, a.repeats, a.check, out)


if __name__ == "__main__":
    main()
