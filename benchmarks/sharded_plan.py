"""The sharded JAX plan's set-up time on the devices this machine has (a mesh of all of
them, or --devices): a first plan (it compiles) and a second of the same scene with the
slaves moved by 1e-4 (compiled programs), per scene.

    python benchmarks/sharded_plan.py --log2 20 --scenes rough graded
"""

import argparse
import time

import arraycontact_jax as acj
import jax
import numpy as np
from jax.sharding import Mesh
from sharding import _scene


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--log2", type=int, default=16)
    ap.add_argument("--scenes", nargs="*", default=["rough", "graded"])
    ap.add_argument("--search", default="jax", choices=["jax", "warp"])
    ap.add_argument("--devices", type=int, default=len(jax.devices()))
    a = ap.parse_args()
    mesh = Mesh(np.array(jax.devices()[: a.devices]), ("space",))
    for name in a.scenes:
        s = _scene(name, 1 << a.log2)
        for k in range(2):
            t = time.perf_counter()
            acj.plan(s.master, s.slave + 1e-4 * k, dtype="float32", mesh=mesh, search=a.search)
            dt = time.perf_counter() - t
            print(f"{name} 2^{a.log2} {a.search} {a.devices} device(s) plan {k + 1}: {dt:.2f} s")


if __name__ == "__main__":
    main()
