"""The Warp detection on each element type: the rough surfaces of 2^k nodes each with tri3,
quad4, tri6, quad8 or quad9 faces (`arraycontact.scenes.rough_surfaces(n, element=...)`),
float32, exact mode, default d_max, the steady state of `detect` (on a GPU its CUDA graph),
and the brute-force reference on a few checked slaves. No peer takes curved faces; the
linear elements' rows are the scale.

    python benchmarks/elements.py --device cuda --log2 18 --run ID --out DIR
    python benchmarks/elements.py --device cpu --log2 14
    python benchmarks/elements.py --table [MACHINE ...]
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
import _records  # noqa: E402

ELEMENTS = ("tri3", "quad4", "tri6", "quad8", "quad9")
#: The scenes' RMS roughness, in element sizes.
RMS = {"rough": 0.5, "gentle": 0.1}


def run(element, scene, n, device, repeats, n_check):
    import arraycontact_warp as acw
    import warp as wp
    from gpu import warp_plan

    import arraycontact as ac

    sc = ac.scenes.rough_surfaces(n, element=element, rms=RMS[scene])
    d_max = sc.master.longest_edge  # (the default: seed 000 eq. 2)
    p, xs, xm = warp_plan(sc, device=device, d_max=d_max)
    for _ in range(3):
        out = acw.detect(p, xs, xm)
    wp.synchronize_device(device)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        acw.detect(p, xs, xm)
        wp.synchronize_device(device)
        times.append(time.perf_counter() - t0)
    rec = dict(
        element=element,
        scene=scene,
        log2=int(np.log2(n)),
        n_slaves=len(sc.slave),
        n_faces=sc.master.n_faces,
        dtype="float32",
        steady_s=statistics.median(times),
        active=int(_host(out["active"]).sum()),
    )
    if n_check:
        from arraycontact.reference import closest_points

        rows = np.random.default_rng(0).choice(len(sc.slave), min(n_check, len(sc.slave)), False)
        ref = closest_points(sc.slave[rows], sc.master)
        dist = _host(out["distance"])[rows]
        active = _host(out["active"]).astype(bool)[rows]
        want = ref.distance <= d_max
        rec["checked"] = len(rows)
        rec["misses"] = int((want & ~active).sum())
        both = want & active
        err = np.abs(dist[both] - ref.distance[both]) / sc.master.longest_edge
        rec["max_distance_err_rel"] = float(err.max()) if both.any() else 0.0
    return rec


def _host(v):
    """A detect output (a Warp array when the inputs were) as a NumPy array."""
    return np.asarray(v.numpy() if hasattr(v, "numpy") else v)


def table(machines):
    recs = [r for m in machines for r in _records.load("elements", m)]
    print(
        "| run | commit | device | scene | element | nodes a surface | faces | steady | per slave |"
        " checked | misses | distance error / edge |"
    )
    print("|" + "---|" * 12)
    for r in recs:
        r.setdefault("scene", "rough")  # (the records before the gentle scene)
    for r in _records.newest(recs, "device", "scene", "element", "log2"):
        print(
            f"| {r['run']} | {_records.commit(r)} | {r['device']} | {r['scene']} | {r['element']} |"
            f" 2^{r['log2']} | {r['n_faces']} | {r['steady_s'] * 1e3:.2f} ms |"
            f" {r['steady_s'] / r['n_slaves'] * 1e9:.0f} ns | {r.get('checked', 0)} |"
            f" {r.get('misses', '-')} | {r.get('max_distance_err_rel', 0):.1e} |"
        )


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--log2", type=int, default=14)
    ap.add_argument("--only", nargs="*", default=list(ELEMENTS))
    ap.add_argument("--scenes", nargs="*", default=list(RMS), choices=list(RMS))
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--repeats", type=int, default=10)
    ap.add_argument("--check", type=int, default=32)
    ap.add_argument("--out", default=None)
    ap.add_argument("--run", default=None, help="run id recorded with every record")
    ap.add_argument("--table", nargs="*", help="print the records of these machines as a table")
    a = ap.parse_args()
    if a.table is not None:
        return table(a.table or ["*"])
    from arraycontact._backends import quiet_warp

    quiet_warp()
    import warp as wp

    device = wp.get_device(a.device)
    meta = _records.meta(a.run)
    for scene in a.scenes:
        for element in a.only:
            r = run(element, scene, 2**a.log2, device, a.repeats, a.check)
            r["device"] = device.name if device.is_cuda else "CPU"
            print(json.dumps(r), flush=True)
            _records.append("elements", r, meta, out=a.out)


if __name__ == "__main__":
    main()
