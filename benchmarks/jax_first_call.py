"""The JAX back end's first calls in a new process, with JAX's persistent compilation cache
cold and warm (issue 20: "first detect after the plan, kernel cache warm"; Warp's kernel
cache is its counterpart). Each scene of the suite runs in a child process of its own, twice
on one cache folder: the first fills it (cold: XLA compiles), the second reads it (warm).

    python benchmarks/jax_first_call.py --log2 20 --only uniform graded_1000 quad4 [--run ID]

Per process: the plan (`search="jax"`, which compiles and runs its counting programs), the
detection's trace and lowering (`detect.lower`: Python, every new process and shape), its
compilation (cold) or load from the cache (warm), its first call, and the steady state (the
median of --repeats). One record per scene and cache state to
results/jax_first_call_<machine>.jsonl.
"""

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).parent
sys.path[:0] = [str(HERE.parent), str(HERE.parent / "backends"), str(HERE)]
import _records  # noqa: E402


def child(label, log2, repeats, cache):
    import jax

    jax.config.update("jax_compilation_cache_dir", cache)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    import arraycontact_jax as acj
    from suite import suite

    make, f = next((m, f) for name, m, f in suite(log2) if name == label)
    s = make()
    d_max = f * s.master.longest_edge
    xs = jax.device_put(s.slave.astype(np.float32))
    xm = jax.device_put(s.master.points.astype(np.float32))
    rec = dict(scene=label, slaves=len(s.slave), device=jax.devices()[0].device_kind)
    t = time.perf_counter()
    p = acj.plan(s.master, s.slave, d_max=d_max, dtype=np.float32, search="jax")
    rec["plan_s"] = time.perf_counter() - t
    t = time.perf_counter()
    lowered = acj.detect.lower(p, xs, xm)
    rec["trace_lower_s"] = time.perf_counter() - t
    t = time.perf_counter()
    lowered.compile()
    rec["compile_s"] = time.perf_counter() - t
    t = time.perf_counter()
    jax.block_until_ready(acj.detect(p, xs, xm))
    rec["first_call_s"] = time.perf_counter() - t
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        jax.block_until_ready(acj.detect(p, xs, xm))
        times.append(time.perf_counter() - t)
    rec["steady_s"] = statistics.median(times)
    print(json.dumps(rec), flush=True)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--log2", type=int, default=20)
    ap.add_argument("--only", nargs="+", default=[])
    ap.add_argument("--repeats", type=int, default=10)
    ap.add_argument("--run", default=None)
    ap.add_argument("--out", default=None)
    ap.add_argument("--child", nargs=2, help=argparse.SUPPRESS)  # label, cache folder
    a = ap.parse_args()
    if a.child:
        return child(a.child[0], a.log2, a.repeats, a.child[1])
    meta = _records.meta(a.run)
    for label in a.only:
        cache = tempfile.mkdtemp(prefix="jax_cache_")
        for state in ("cold", "warm"):
            cmd = [sys.executable, __file__, "--log2", str(a.log2), "--repeats", str(a.repeats)]
            out = subprocess.run(
                [*cmd, "--child", label, cache], capture_output=True, text=True, env=os.environ
            )
            lines = [x for x in out.stdout.splitlines() if x.startswith("{")]
            if out.returncode or not lines:
                raise SystemExit(f"{label} {state}: {out.stderr[-2000:]}")
            rec = dict(json.loads(lines[-1]), cache=state)
            print(json.dumps(rec), flush=True)
            _records.append("jax_first_call", rec, meta, out=a.out)


if __name__ == "__main__":
    main()
