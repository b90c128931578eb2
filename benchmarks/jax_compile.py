"""How long XLA compiles the JAX search's programs (`search="jax"`), per scene of the suite
or rough surfaces of 2^k nodes (`rough:k`), under XLA compiler options: the plan's counting
program and the detection (the plan closed over), with the detection's steady time under
the same options. On a GPU some scenes' scans took 30-60 s in LLVM and ptxas (RESULTS.md,
runs h100-s19/s20).

    python benchmarks/jax_compile.py --log2 20 --only ball_block_100 rough:13 rough:20
"""

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from suite import suite  # noqa: E402

OPTIONS = {
    "default": None,
    "level0": {"xla_backend_optimization_level": 0},
    "ptxas_O0": {"xla_gpu_disable_gpuasm_optimizations": True},
}


def _scenes(a):
    from arraycontact import scenes

    for name in a.only:
        if name.startswith("rough:"):
            k = int(name.split(":")[1])
            yield name, scenes.rough_surfaces(2**k), 1.0
    for label, make, f in suite(a.log2):
        if label in a.only:
            yield label, make(), f


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--log2", type=int, default=20)
    ap.add_argument("--only", nargs="+", required=True)
    ap.add_argument("--options", nargs="+", default=list(OPTIONS), choices=list(OPTIONS))
    ap.add_argument("--repeats", type=int, default=7)
    a = ap.parse_args()
    import arraycontact_jax as acj
    import arraycontact_jax._detect as jd
    import jax

    for label, scene, f in _scenes(a):
        d_max = f * scene.master.longest_edge
        for name in a.options:
            opts = OPTIONS[name]
            times = {}

            def once(fn, *args, opts=opts, times=times, **static):
                t0 = time.perf_counter()
                c = fn.lower(*args, **static).compile(opts)
                times["count"] = time.perf_counter() - t0
                return c(*args)

            jd.once = once  # the plan's counting program under these options, uncached
            p = acj.plan(scene.master, scene.slave, d_max=d_max, dtype=np.float32, search="jax")
            xs = jax.device_put(scene.slave.astype(np.float32))
            xm = jax.device_put(scene.master.points.astype(np.float32))
            t0 = time.perf_counter()
            run = jax.jit(lambda s, m, p=p: acj.detect(p, s, m)).lower(xs, xm).compile(opts)
            times["detect"] = time.perf_counter() - t0
            jax.block_until_ready(run(xs, xm))
            steady = []
            for _ in range(a.repeats):
                t0 = time.perf_counter()
                jax.block_until_ready(run(xs, xm))
                steady.append(time.perf_counter() - t0)
            print(
                f"{label} ({len(scene.slave)} slaves) {name}: compile count "
                f"{times['count']:.1f} s, detect {times['detect']:.1f} s; steady detect "
                f"{1e3 * statistics.median(steady):.2f} ms ({jax.devices()[0].device_kind})",
                flush=True,
            )


if __name__ == "__main__":
    main()
