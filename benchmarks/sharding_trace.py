"""Where a sharded detection's time goes: `jax.profiler` traces of five calls
each of one device unsharded, a mesh of one device (2^20 nodes a surface) and a mesh of all
devices (2^20 a device), rough surfaces, float32.

    python benchmarks/sharding_trace.py run --out DIR [--search warp|jax]   # on the GPU
    python benchmarks/sharding_trace.py summary DIR         # GPU time a call per stream/kernel
    python benchmarks/sharding_trace.py diff A B            # kernels of trace A against B
    python benchmarks/sharding_trace.py collectives         # the collectives alone, all devices
    python benchmarks/sharding_trace.py options [--search jax]  # XLA's command buffers, A/B
    python benchmarks/sharding_trace.py floor --log2 14 [--search warp jax]  # the host's part

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
import time

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
        c, _, median = _timed(lambda p=p, sl=sl, pts=pts: acj.detect(p, sl, pts), 10)
        steps = {k: int(v) for k, v in c.counts.count.items() if k.endswith("steps")}
        print(f"{search} {name}: {median * 1e3:.2f} ms a call (median of 10) {steps}", flush=True)
        tmp = tempfile.mkdtemp()
        with jax.profiler.trace(tmp, create_perfetto_trace=True):
            for _ in range(CALLS):
                jax.block_until_ready(acj.detect(p, sl, pts))
        (trace,) = glob.glob(f"{tmp}/**/perfetto_trace.json.gz", recursive=True)
        shutil.copy(trace, os.path.join(out, f"perfetto_{search}_{name}.json.gz"))
        shutil.rmtree(tmp)
        del p


def _gpu_events(path):
    """The trace's GPU events and the (pid, tid) -> name table."""
    events = json.load(gzip.open(path))
    events = events["traceEvents"] if isinstance(events, dict) else events
    names = {}
    for e in events:
        if e.get("ph") == "M" and e.get("name") in ("process_name", "thread_name"):
            tid = e.get("tid") if e["name"] == "thread_name" else None
            names[e["pid"], tid] = e["args"]["name"]
    gpu = [e for e in events if e.get("ph") == "X" and "GPU" in names.get((e.get("pid"), None), "")]
    return gpu, names


def summary(folder, top=12):
    for path in sorted(glob.glob(os.path.join(folder, "perfetto_*.json.gz"))):
        events, names = _gpu_events(path)
        per_stream, per_kernel = collections.Counter(), collections.Counter()
        for e in events:
            proc = names.get((e.get("pid"), None), "")
            stream = (proc, names.get((e["pid"], e["tid"]), str(e["tid"])))
            per_stream[stream] += e["dur"] / CALLS
            per_kernel[stream[0], e["name"][:70]] += e["dur"] / CALLS
        print(f"== {os.path.basename(path)}: GPU time a call")
        for (proc, stream), us in sorted(per_stream.items()):
            print(f"  {proc} {stream[:40]}: {us / 1e3:.3f} ms")
        for (proc, kernel), us in per_kernel.most_common(top):
            print(f"    {proc} {kernel}: {us:.1f} us")


def diff(a, b, top=25):
    """Kernels by name: launches and GPU time a call on the first GPU of trace a and of trace b,
    the largest differences first (which kernels a part runs more of, or longer)."""
    tables = []
    for path in (a, b):
        events, names = _gpu_events(path)
        first = min(names[e["pid"], None] for e in events)
        n, t = collections.Counter(), collections.Counter()
        for e in events:
            if names[e["pid"], None] == first:
                n[e["name"][:60]] += 1 / CALLS
                t[e["name"][:60]] += e["dur"] / CALLS
        tables.append((n, t))
        print(
            f"{os.path.basename(path)} ({first}): {sum(n.values()):.0f} kernels, "
            f"{sum(t.values()) / 1e3:.2f} ms a call"
        )
    (na, ta), (nb, tb) = tables
    keys = sorted(set(ta) | set(tb), key=lambda k: -abs(tb[k] - ta[k]))
    for k in keys[:top]:
        print(f"  {tb[k] - ta[k]:+8.1f} us  {na[k]:6.1f} -> {nb[k]:6.1f} launches  {k}")


def collectives(repeats=50):
    """Median wall time of a jitted shard_map over all devices doing only: +1 (the launch),
    a pmax of a scalar, one all_to_all of C rows of 20 float32 to each device, two in a
    row (a detection's exchange in and home)."""
    import jax
    import jax.numpy as jnp
    from jax.sharding import Mesh, NamedSharding
    from jax.sharding import PartitionSpec as P

    devs = jax.devices()
    d = len(devs)
    mesh = Mesh(np.array(devs), ("x",))

    def timed(f, a):
        jax.block_until_ready(f(a))
        ts = []
        for _ in range(repeats):
            t = time.perf_counter()
            jax.block_until_ready(f(a))
            ts.append(time.perf_counter() - t)
        return float(np.median(ts)) * 1e3

    def sm(body):
        spec = P("x")
        return jax.jit(jax.shard_map(body, mesh=mesh, in_specs=spec, out_specs=spec))

    def rows(n):
        return jax.device_put(jnp.zeros((d * n, 20), jnp.float32), NamedSharding(mesh, P("x")))

    def a2a(a):
        return jax.lax.all_to_all(a.reshape(d, -1, 20), "x", 0, 0).reshape(-1, 20)

    print(f"{d} x {devs[0].device_kind}, median of {repeats} calls")
    print(f"  +1 only: {timed(sm(lambda a: a + 1), rows(1024)):.3f} ms")
    t = timed(sm(lambda a: a + jax.lax.pmax(jnp.max(a), "x")), rows(1024))
    print(f"  pmax of a scalar: {t:.3f} ms")
    for c in (64, 600, 5000, 50000):
        print(f"  all_to_all, C = {c}: {timed(sm(lambda a: a2a(a) + 1), rows(d * c)):.3f} ms")
    t = timed(sm(lambda a: a2a(a2a(a) + 1)), rows(d * 600))
    print(f"  two all_to_alls, C = 600: {t:.3f} ms")


#: XLA compiler options tried on the detection (jit's compiler_options: this call's programs
#: alone, not the process's XLA_FLAGS). The default command buffers leave the collectives
#: out, so a sharded call is several graphs launched around its all_to_alls.
KEY = "xla_gpu_enable_command_buffer"
OPTIONS = {
    "default": None,
    "collectives": "FUSION,CUBLAS,CUBLASLT,CUSTOM_CALL,CUDNN,COLLECTIVES",
    "collectives+while": "FUSION,CUBLAS,CUBLASLT,CUSTOM_CALL,CUDNN,COLLECTIVES,WHILE,CONDITIONAL",
    "off": "",
}


def options(search="jax", log2=20, rounds=4, calls=15):
    """One device's detection at 2^log2 nodes a surface and all devices' at n_dev x 2^log2
    (rough, float32), each compiled with every entry of OPTIONS; rounds of `calls` synchronised
    calls (median) and of `calls` dispatched back to back with one wait (mean, "pipelined"),
    the variants taking turns. Prints a JSON record a case and variant."""
    import arraycontact_jax as acj
    import jax
    from arraycontact_jax import _detect
    from jax.sharding import Mesh, NamedSharding
    from jax.sharding import PartitionSpec as P

    from arraycontact import scenes

    n_dev = len(jax.devices())
    mesh = Mesh(np.array(jax.devices()), ("space",))
    cases = {}
    for name, n, m in (("one", 2**log2, None), (f"mesh{n_dev}", n_dev * 2**log2, mesh)):
        s = scenes.rough_surfaces(n, seed=0)
        p = acj.plan(s.master, s.slave, dtype=np.float32, search=search, mesh=m)
        sl, pts = s.slave.astype(np.float32), s.master.points.astype(np.float32)
        where = None if m is None else NamedSharding(m, P("space"))
        body = _detect.detect.__wrapped__ if m is None else _detect._shard_detect
        fns = {
            k: jax.jit(body, compiler_options=v if v is None else {KEY: v})
            for k, v in OPTIONS.items()
        }
        cases[name] = (p, jax.device_put(sl, where), jax.device_put(pts, where), fns)
    first = {}
    for name, (p, sl, pts, fns) in cases.items():
        for k, f in fns.items():
            face = np.asarray(jax.block_until_ready(f(p, sl, pts)).face)
            first.setdefault(name, face)
            assert np.array_equal(face, first[name]), f"{name} {k}: other faces than the default"
            for _ in range(5):
                jax.block_until_ready(f(p, sl, pts))
    times = collections.defaultdict(list)
    for _ in range(rounds):
        for name, (p, sl, pts, fns) in cases.items():
            for k, f in fns.items():
                ts = []
                for _ in range(calls):
                    t = time.perf_counter()
                    jax.block_until_ready(f(p, sl, pts))
                    ts.append(time.perf_counter() - t)
                times[name, k, "synced"].append(float(np.median(ts)))
                t = time.perf_counter()
                for _ in range(calls):
                    r = f(p, sl, pts)
                jax.block_until_ready(r)
                times[name, k, "pipelined"].append((time.perf_counter() - t) / calls)
    for (name, k, how), v in times.items():
        rec = dict(case=name, search=search, log2=log2, option=k, flag=OPTIONS[k], how=how)
        rec.update(ms=[round(x * 1e3, 3) for x in v], median_ms=round(float(np.median(v)) * 1e3, 3))
        print(json.dumps(rec), flush=True)


def floor(searches=("warp", "jax"), log2=14, calls=30):
    """The host's part of a call on a small scene (rough, 2^log2 nodes a surface a device,
    float32): one device's plan and all devices' (inputs sharded by rows, as sharding.py puts
    them), each waited for (sharding.py's median of `calls`), back to back (mean), and the
    host's time to dispatch those (before the wait); the sharded plan also with inputs on one
    device (jit moves them), closed over by jit (no pytree to flatten) and, with the Warp
    search, with the search's Python replaced by a no-op (its answers garbage: timing only)."""
    import arraycontact_jax as acj
    import jax
    from jax.sharding import Mesh, NamedSharding
    from jax.sharding import PartitionSpec as P
    from sharding import _timed

    from arraycontact import scenes

    n_dev = len(jax.devices())
    s = scenes.rough_surfaces(n_dev * 2**log2, seed=0)
    mesh = Mesh(np.array(jax.devices()), ("space",))
    one_device = tuple(jax.numpy.asarray(a, np.float32) for a in (s.slave, s.master.points))
    by_rows = jax.device_put(one_device, NamedSharding(mesh, P("space")))

    def bench(case, search, q, f, inputs, devices=n_dev):
        _, _, synced = _timed(lambda: f(q, *inputs), calls)
        t = time.perf_counter()
        r = [f(q, *inputs) for _ in range(calls)]
        dispatch = (time.perf_counter() - t) / calls
        jax.block_until_ready(r)
        back_to_back = (time.perf_counter() - t) / calls
        rec = dict(case=case, search=search, log2=log2, devices=devices)
        rec.update(synced_ms=synced * 1e3, pipelined_ms=back_to_back * 1e3)
        print(json.dumps(dict(rec, dispatch_ms=dispatch * 1e3)), flush=True)

    for search in searches:
        detect = jax.jit(acj.detect)
        one = acj.plan(s.master, s.slave, dtype=np.float32, search=search)
        bench("one device", search, one, detect, one_device, devices=1)
        p = acj.plan(s.master, s.slave, dtype=np.float32, search=search, mesh=mesh)
        bench("sharded", search, p, detect, by_rows)
        bench("sharded, inputs on one device", search, p, detect, one_device)
        closed = jax.jit(lambda _, a, b: acj.detect(p, a, b))
        bench("sharded, plan closed over", search, None, closed, by_rows)
        if search == "warp":
            p.local.search.call.func = lambda *a: None
            bench("sharded, search a no-op", search, p, detect, by_rows)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("what", choices=["run", "summary", "diff", "collectives", "options", "floor"])
    ap.add_argument("folder", nargs="*", default=None)
    ap.add_argument("--out", default=None)
    ap.add_argument("--search", nargs="+", choices=["warp", "jax"], default=["warp"])
    ap.add_argument("--log2", type=int, default=20, help="options: nodes a surface a device")
    a = ap.parse_args()
    if a.what == "run":
        run(a.out or os.environ["OUT"], a.search[0])
    elif a.what == "collectives":
        collectives()
    elif a.what == "options":
        options(a.search[0], a.log2)
    elif a.what == "floor":
        floor(a.search, a.log2)
    elif a.what == "diff":
        diff(*a.folder)
    else:
        summary(a.folder[0])


if __name__ == "__main__":
    main()
