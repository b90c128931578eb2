"""Where a sharded detection's time goes: `jax.profiler` traces of five calls
each of one device unsharded, a mesh of one device (2^20 nodes a surface) and a mesh of all
devices (2^20 a device), rough surfaces, float32.

    python benchmarks/sharding_trace.py run --out DIR [--search warp|jax]   # on the GPU
    python benchmarks/sharding_trace.py summary DIR         # GPU time a call per stream/kernel

`run` writes DIR/perfetto_<search>_<one|mesh1|meshN>.json.gz (flat: the device's copy-back takes no
deep folders) and prints each case's median wall time of 10 calls.
"""

from __future__ import annotations

import argparse
import collections
import glob
import gzip
import json
import os
import shutil
import sys
import tempfile

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path[:0] = [os.path.dirname(HERE), os.path.join(os.path.dirname(HERE), "backends")]
CALLS = 5


def run(out, search="warp"):
    import arraycontact_jax as acj
    import jax
    from jax.sharding import Mesh, NamedSharding
    from jax.sharding import PartitionSpec as P
    from sharding import _timed

    from arraycontact import scenes

    n_dev = len(jax.devices())
    cases = [("one", 2**20, 0), ("mesh1", 2**20, 1), (f"mesh{n_dev}", n_dev * 2**20, n_dev)]
    for name, n, d in cases:
        s = scenes.rough_surfaces(n, seed=0)
        sl = jax.device_put(s.slave.astype(np.float32))
        pts = jax.device_put(s.master.points.astype(np.float32))
        if d == 0:
            p = acj.plan(s.master, s.slave, dtype=np.float32, search=search)
        else:
            mesh = Mesh(np.array(jax.devices()[:d]), ("space",))
            p = acj.plan(s.master, s.slave, dtype=np.float32, mesh=mesh, search=search)
            rows = NamedSharding(mesh, P("space"))
            sl, pts = jax.device_put(sl, rows), jax.device_put(pts, rows)
        _, _, median = _timed(lambda p=p, sl=sl, pts=pts: acj.detect(p, sl, pts), 10)
        print(f"{search} {name}: {median * 1e3:.2f} ms a call (median of 10)", flush=True)
        tmp = tempfile.mkdtemp()
        with jax.profiler.trace(tmp, create_perfetto_trace=True):
            for _ in range(CALLS):
                jax.block_until_ready(acj.detect(p, sl, pts))
        (trace,) = glob.glob(f"{tmp}/**/perfetto_trace.json.gz", recursive=True)
        shutil.copy(trace, os.path.join(out, f"perfetto_{search}_{name}.json.gz"))
        shutil.rmtree(tmp)
        del p


def summary(folder, top=12):
    for path in sorted(glob.glob(os.path.join(folder, "perfetto_*.json.gz"))):
        events = json.load(gzip.open(path))
        events = events["traceEvents"] if isinstance(events, dict) else events
        names = {}
        for e in events:
            if e.get("ph") == "M" and e.get("name") in ("process_name", "thread_name"):
                names[e["pid"], e.get("tid") if e["name"] == "thread_name" else None] = e["args"][
                    "name"
                ]
        per_stream, per_kernel = collections.Counter(), collections.Counter()
        for e in events:
            proc = names.get((e.get("pid"), None), "")
            if e.get("ph") != "X" or "GPU" not in proc:
                continue
            stream = (proc, names.get((e["pid"], e["tid"]), str(e["tid"])))
            per_stream[stream] += e["dur"] / CALLS
            per_kernel[stream[0], e["name"][:70]] += e["dur"] / CALLS
        print(f"== {os.path.basename(path)}: GPU time a call")
        for (proc, stream), us in sorted(per_stream.items()):
            print(f"  {proc} {stream[:40]}: {us / 1e3:.3f} ms")
        for (proc, kernel), us in per_kernel.most_common(top):
            print(f"    {proc} {kernel}: {us:.1f} us")


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("what", choices=["run", "summary"])
    ap.add_argument("folder", nargs="?", default=None)
    ap.add_argument("--out", default=None)
    ap.add_argument("--search", choices=["warp", "jax"], default="warp")
    a = ap.parse_args()
    if a.what == "run":
        run(a.out or os.environ["OUT"], a.search)
    else:
        summary(a.folder)


if __name__ == "__main__":
    main()
